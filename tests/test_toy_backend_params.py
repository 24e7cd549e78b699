"""A back-end with parameters of its own, from outside smana (tests/support/toy_count_backend.py,
one file): its `[mapper.toy_count]` section is read from TOML and `--set`, checked in one line,
written into config.toml, handed to the back-end as it is and kept in saved maps, with no edit of
smana: named by its module:Class spec or registered in-process."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from smana.common import keys
from smana.common.config import ConfigError, SmanaConfig
from smana.common.messages import MapDelta, SemanticCloud, decode, encode
from smana.services.mapper import backends
from smana.services.mapper.semantic_map import SemanticMap
from tests.conftest import REPO
from tests.support.toy_count_backend import ToyCount, ToyCountConfig

SPEC = "tests.support.toy_count_backend:ToyCount"  # importable from the repository root
# three points in the voxel at the origin, one in the next one along x (resolution 0.5 m)
POINTS = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1], [0.3, 0.3, 0.3], [0.7, 0.1, 0.1]], np.float32)
LABELS = np.array([1, 2, 4, 8])


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setattr(backends, "BACKENDS", backends.BACKENDS.copy())  # undone after the test
    backends.register("toy-count", ToyCount)
    return "toy-count"


def occupied_counts(m: SemanticMap) -> dict[tuple, float]:
    rows = m.occupied_voxels()
    return {tuple(c): float(v) for c, v in zip(rows.centres.tolist(), rows.values.tolist())}


def test_its_section_comes_from_toml_and_reaches_the_backend_as_it_is(tmp_path):
    path = tmp_path / "smana.toml"
    path.write_text(
        f'[mapper]\nbackend = "{SPEC}"\nresolution_m = 0.5\n\n'
        "[mapper.toy_count]\nmin_hits = 3\nweight = 0.5\n"
    )
    cfg = SmanaConfig.load(path)
    assert cfg.mapper.toy_count == ToyCountConfig(min_hits=3, weight=0.5)
    m = SemanticMap.from_config(cfg.mapper)
    assert type(m._core) is ToyCount and m._core.config is cfg.mapper.toy_count
    m.integrate(POINTS, LABELS, None, (0.0, 0.0, 0.0))
    assert occupied_counts(m) == {(0.25, 0.25, 0.25): 1.5}  # 3 hits x 0.5; the other voxel: 1
    # --set on top of the file, with the same spelling
    looser = SmanaConfig.load(path, ["mapper.toy_count.min_hits=1"])
    m = SemanticMap.from_config(looser.mapper)
    m.integrate(POINTS, LABELS, None, (0.0, 0.0, 0.0))
    assert occupied_counts(m) == {(0.25, 0.25, 0.25): 1.5, (0.75, 0.25, 0.25): 0.5}
    # the written config shows the section and reads back the same
    written = cfg.write(tmp_path / "run" / "config.toml")
    assert "[mapper.toy_count]\nmin_hits = 3\nweight = 0.5\n" in written.read_text()
    assert "[mapper.octree]" in written.read_text() and "[mapper.tsdf]" in written.read_text()
    assert SmanaConfig.load(written) == cfg
    # a saved map keeps the back-end's section
    saved = m.save(tmp_path / "toy.npz")
    back = SemanticMap.load(saved, backend=SPEC)
    assert back.config == ToyCountConfig(min_hits=1, weight=0.5) and occupied_counts(
        back
    ) == occupied_counts(m)


def test_a_registered_backend_is_configured_the_same_way(registered):
    sets = [f"mapper.backend={registered}", "mapper.resolution_m=0.5", "mapper.toy_count.weight=2"]
    m = SemanticMap.from_config(SmanaConfig.load(None, sets).mapper)
    m.integrate(POINTS, LABELS, None, (0.0, 0.0, 0.0))
    assert occupied_counts(m) == {(0.25, 0.25, 0.25): 6.0}  # min_hits 2 (its default), 3 x 2
    # registered, its section is known whichever back-end runs, as [mapper.tsdf] is
    other = SmanaConfig.load(None, ["mapper.toy_count.min_hits=5"])
    assert other.mapper.backend == "octree-max" and other.mapper.toy_count.min_hits == 5


@pytest.mark.parametrize(
    "sets, message",
    [
        (
            [f"mapper.backend={SPEC}", "mapper.toy_count.min_hits=0"],
            "mapper.toy_count.min_hits: expected a number >= 1, got 0",
        ),
        (
            [f"mapper.backend={SPEC}", "mapper.toy_count.hits=3"],
            "unknown key mapper.toy_count.hits (known in [mapper.toy_count]: min_hits, weight)",
        ),
        # not named, not registered: smana does not know the section
        (["mapper.toy_count.min_hits=3"], "unknown key mapper.toy_count"),
    ],
)
def test_its_bad_values_fail_in_one_line_naming_the_key(sets, message):
    with pytest.raises(ConfigError) as info:
        SmanaConfig.load(None, sets)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_smana_mapper_refuses_a_bad_value_of_it_in_one_line(tmp_path):
    sets = ["--set", f"mapper.backend={SPEC}", "--set", "mapper.toy_count.weight=-1"]
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.mapper", *sets],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "smana mapper: mapper.toy_count.weight: expected a number > 0, got -1"
    ]


@pytest.mark.multiprocess
def test_a_mapper_process_takes_its_section_from_the_config_file(zenoh_stack, tmp_path):
    st = zenoh_stack
    path = tmp_path / "smana.toml"
    path.write_text(
        f'[mapper]\nbackend = "{SPEC}"\nresolution_m = 0.5\nautosave_period_s = 0\n\n'
        "[mapper.toy_count]\nmin_hits = 3\nweight = 0.25\n"
    )
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)}
    argv = [*st.zenoh_args(), "--robot", st.robot, "--config", str(path)]
    st.start("mapper", "-m", "smana.services.mapper", *argv, env=env)
    st.wait_alive("mapper")
    got: list[MapDelta] = []
    sub = st.session.declare_subscriber(
        keys.map_delta(st.robot), lambda s: got.append(decode(s.payload.to_bytes(), MapDelta))
    )
    try:
        pub = st.publisher(keys.cloud(st.robot))
        cloud = SemanticCloud(
            stamp_s=1.0,
            seq=1,
            points=POINTS,
            labels=LABELS.astype(np.uint16),
            confidences=np.ones(len(POINTS), np.float32),
            sensor_position=np.zeros(3),
        )
        deadline = time.monotonic() + 30
        while not got and time.monotonic() < deadline:  # until the mapper's first delta
            pub.put(encode(cloud))
            time.sleep(0.3)
    finally:
        sub.undeclare()
    assert got, st.log("mapper")
    d = got[0]
    order = np.lexsort(d.centres.T[::-1])
    # one cloud: 3 points and 1, weighted 0.25; only the first voxel reaches min_hits = 3
    assert d.backend == SPEC and d.values[order].tolist() == [0.75, 0.25]
    assert d.occupied[order].tolist() == [1, 0]
