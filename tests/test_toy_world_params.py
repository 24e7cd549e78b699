"""A world with parameters of its own, from outside smana (tests/support/toy_pillars_world.py,
one file): its `[sim.pillars]` section is read from TOML and `--set`, checked in one line,
written into config.toml and handed to the world as it is, with no edit of smana: named by its
module:Class spec (in a config or `smana world --world`) or registered in-process."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.config import ConfigError, SmanaConfig
from smana.services.sim import worlds
from smana.services.sim.world_cli import cli as world_cli
from smana.services.sim.worlds import build_world
from tests.support.toy_pillars_world import HEDGE, Pillars, PillarsConfig, pillar_centres

SPEC = "tests.support.toy_pillars_world:Pillars"  # importable from the repository root


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setattr(worlds, "WORLDS", worlds.WORLDS.copy())  # undone after the test
    worlds.register("pillars", Pillars)
    return "pillars"


def pillar_xy(world) -> list[tuple[float, float]]:
    return sorted((o.primitives[0].centre[0], o.primitives[0].centre[1]) for o in world.objects)


def test_its_section_comes_from_toml_and_shapes_the_world(tmp_path):
    path = tmp_path / "smana.toml"
    path.write_text(f'[sim]\nworld = "{SPEC}"\n\n[sim.pillars]\ncount = 5\nradius_m = 0.25\n')
    cfg = SmanaConfig.load(path)
    assert cfg.sim.pillars == PillarsConfig(count=5, radius_m=0.25)
    world = build_world(cfg.sim)
    assert world.name == "pillars" and len(world.objects) == 5
    np.testing.assert_allclose(pillar_xy(world), sorted(pillar_centres(cfg.sim.pillars)))
    assert {o.primitives[0].half_extents[0] for o in world.objects} == {0.25}
    x, y = pillar_centres(cfg.sim.pillars)[0]
    assert world.top_class().at(x, y) == HEDGE
    # --set on top of the file, with the same spelling
    fewer = build_world(SmanaConfig.load(path, ["sim.pillars.count=2"]).sim)
    assert len(fewer.objects) == 2
    # the written config shows the section (and the in-tree worlds') and reads back the same
    text = cfg.write(tmp_path / "run" / "config.toml").read_text()
    assert "[sim.pillars]\ncount = 5\nradius_m = 0.25\nring_m = 1.5\n" in text
    assert "[sim.garden]" in text and "[sim.ply]" in text
    assert SmanaConfig.load(tmp_path / "run" / "config.toml") == cfg


def test_a_registered_world_is_configured_the_same_way(registered):
    cfg = SmanaConfig.load(None, ["sim.world=pillars", "sim.pillars.ring_m=2.5"])
    world = build_world(cfg.sim)
    assert len(world.objects) == 3  # its default count
    assert np.hypot(*np.array(pillar_xy(world)).T).tolist() == pytest.approx([2.5] * 3)


@pytest.mark.parametrize(
    "sets, message",
    [
        ([f"sim.world={SPEC}", "sim.pillars.count=0"], "sim.pillars.count: expected a number >= 1"),
        (
            [f"sim.world={SPEC}", "sim.pillars.height_m=2"],
            "unknown key sim.pillars.height_m (known in [sim.pillars]: count, radius_m, ring_m)",
        ),
        (["sim.pillars.count=2"], "unknown key sim.pillars"),  # not named, not registered
    ],
)
def test_its_bad_values_fail_in_one_line_naming_the_key(sets, message):
    with pytest.raises(ConfigError) as info:
        SmanaConfig.load(None, sets)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_smana_world_takes_its_section_with_the_world_flag(capsys):
    assert world_cli(["info", "--world", SPEC, "--set", "sim.pillars.count=4"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["name"] == "pillars" and len(summary["objects"]) == 4
