"""Config: defaults, file, overrides, validation that names the key, and the TOML round trip."""

from __future__ import annotations

import pytest

from smana.common.classes import ClassTable, ClassTableError
from smana.common.config import ConfigError, SmanaConfig


def test_defaults_file_and_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text(
        '[mapper]\nbackend = "tsdf"\nresolution_m = 0.2\n[deploy.mapper]\nrestart = "always"\n'
    )
    cfg = SmanaConfig.load(f, ["mapper.resolution_m=0.3", "general.robot=rover2"])
    assert cfg.mapper.backend == "tsdf" and cfg.mapper.resolution_m == 0.3
    assert cfg.deploy.mapper.restart == "always" and cfg.general.robot == "rover2"
    assert cfg.planner.h_f == 0.1 and cfg.planner.t_f == 0.8  # the paper's defaults


def test_round_trip(tmp_path):
    cfg = SmanaConfig.load(None, ["sim.noise=high", 'zenoh.connect=["tcp/10.0.0.1:7447"]'])
    back = SmanaConfig.load(cfg.write(tmp_path / "used.toml"))
    assert back == cfg


@pytest.mark.parametrize(
    "override, message",
    [
        ("mapper.resolution_m=0", "mapper.resolution_m: expected a number > 0"),
        ("mapper.voxel=1", "unknown key mapper.voxel"),
        ("nosuch.key=1", "unknown key nosuch"),
        ("sim.seed=2.5", "sim.seed: expected an integer"),
        ("sim.lockstep=1", "sim.lockstep: expected true or false"),
        ("zenoh.connect=3", "zenoh.connect: expected a list"),
        ("general.robot=a/b", "general.robot"),
        ("deploy.mapper.restart=sometimes", "deploy.mapper.restart: expected one of"),
        ("justaword", "must look like section.key=value"),
    ],
)
def test_bad_values_name_the_key(override, message):
    with pytest.raises(ConfigError) as info:
        SmanaConfig.load(None, [override])
    assert message in str(info.value)


def test_bad_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        SmanaConfig.load(tmp_path / "missing.toml")
    f = tmp_path / "broken.toml"
    f.write_text("[mapper\n")
    with pytest.raises(ConfigError, match="broken.toml"):
        SmanaConfig.load(f)


def test_class_table_luts_and_errors(tmp_path):
    t = ClassTable.load("garden3drms")
    assert t.cost_lut[1] == 2.0 and t.cost_lut[2] == 1.0 and t.cost_lut[4] == float("inf")
    assert t.obstacle_lut[[4, 5, 6, 7, 8]].all() and not t.obstacle_lut[[0, 1, 2]].any()
    import numpy as np

    labels, n = t.sanitise(np.array([1, 3, 2, 200, 8], np.uint16))
    assert labels.tolist() == [1, 0, 2, 0, 8] and n == 2
    f = tmp_path / "t.toml"
    f.write_text('[[class]]\nid = 1\nname = "x"\nkind = "traversable"\n')
    with pytest.raises(ClassTableError):
        ClassTable.load(f)  # no unknown class, no cost
    with pytest.raises(ClassTableError, match="no bundled class table"):
        ClassTable.load("nonexistent_table")
