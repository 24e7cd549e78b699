"""The mapper's back-end registry: every back-end declares its name, the kind of its delta values
and its config section; an unknown name fails in one line naming the known ones; a toy back-end
from the test folder runs through the stack, in-process and as a mapper process (by spec)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from smana.common import keys
from smana.common.config import ConfigError, SmanaConfig
from smana.common.config.mapper import MapperConfig
from smana.common.messages import VALUES_KINDS, MapDelta, SemanticCloud, decode, encode
from smana.services.mapper import backends
from smana.services.mapper.backends import BACKENDS, backend_class, check_backend, register
from smana.services.mapper.semantic_map import SemanticMap
from tests.support.toy_backend import LastLabel

SUPPORT = Path(__file__).parent / "support"
TOY_SPEC = "toy_backend:LastLabel"  # with SUPPORT on PYTHONPATH


@pytest.fixture
def toy_registered():
    register("toy-last-label", LastLabel)
    try:
        yield "toy-last-label"
    finally:
        del BACKENDS["toy-last-label"]


def test_every_registered_backend_declares_its_name_values_and_section():
    assert list(BACKENDS) == ["octree-max", "octree-bayes", "tsdf"]
    sections = MapperConfig.variant_classes()  # declared beside each back-end
    for name in BACKENDS:
        cls = backend_class(name)
        assert cls.name == name and cls.values_kind in VALUES_KINDS
        assert sections[cls.config_key] is cls.config_class  # [mapper.<config_key>]
        m = SemanticMap.from_config(MapperConfig(backend=name, resolution_m=0.3))
        assert type(m._core) is cls and type(m.config) is cls.config_class


def test_the_core_receives_its_section_as_it_is():
    cfg = SmanaConfig.load(None, ["mapper.backend=tsdf", "mapper.tsdf.truncation_voxels=3"])
    m = SemanticMap.from_config(cfg.mapper)
    assert m._core.config is cfg.mapper.tsdf and m._core.trunc_m == pytest.approx(0.3)
    cfg = SmanaConfig.load(None, ["mapper.octree.prob_hit=0.8"])
    assert SemanticMap.from_config(cfg.mapper)._core.config is cfg.mapper.octree
    # octree-max's same-label rule: Semantic Octomap's by default, the gain rule by name
    assert SmanaConfig.load(None, []).mapper.octree.max_fusion == "average"
    cfg = SmanaConfig.load(None, ["mapper.octree.max_fusion=gain"])
    assert SemanticMap.from_config(cfg.mapper)._core._consts.max_rule == 1


@pytest.mark.parametrize(
    "override, message",
    [
        ("mapper.octree.prob_hit=1.5", "mapper.octree.prob_hit: expected a number < 1, got 1.5"),
        ("mapper.octree.prob_hit=0.4", "need prob_miss < 0.5 < prob_hit"),
        ("mapper.tsdf.max_weight=0", "mapper.tsdf.max_weight: expected a number > 0, got 0"),
        ("mapper.tsdf_max_weight=1", "unknown key mapper.tsdf_max_weight"),
        (
            "mapper.octree.max_fusion=nope",
            "mapper.octree.max_fusion: expected one of ['average', 'gain'], got 'nope'",
        ),
    ],
)
def test_backend_sections_are_checked_with_one_line_naming_the_key(override, message):
    with pytest.raises(ConfigError) as info:
        SmanaConfig.load(None, [override])
    assert message in str(info.value) and "\n" not in str(info.value)


def test_an_unknown_backend_fails_in_one_line_naming_the_known_ones():
    cfg = SmanaConfig.load(None, ["mapper.backend=octomap"])  # common cannot know the names
    with pytest.raises(ConfigError) as info:
        check_backend(cfg.mapper.backend)
    assert "mapper.backend: expected one of" in str(info.value)
    assert "'octree-max', 'octree-bayes', 'tsdf'" in str(info.value)
    with pytest.raises(ValueError, match="expected one of"):
        SemanticMap("octomap")
    with pytest.raises(ConfigError, match="cannot import 'no_such_module'"):
        check_backend("no_such_module:Backend")
    with pytest.raises(ConfigError, match="is not a MapBackend class"):
        check_backend("numpy:ndarray")


@pytest.mark.parametrize("command", ["mapper", "up"])
def test_smana_mapper_and_up_refuse_an_unknown_backend_before_starting(command, tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "smana.deploy.cli", command, "--set", "mapper.backend=nope"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "expected one of ['octree-max', 'octree-bayes', 'tsdf']" in lines[0]
    assert not list(tmp_path.iterdir())  # nothing started, nothing written


def test_a_toy_backend_runs_through_semantic_map_in_process(toy_registered, tmp_path):
    m = SemanticMap(toy_registered, 0.5)
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.1, 0.1, 0.1], [0.3, 0.1, 0.1]], np.float32)
    d = m.integrate(pts, np.array([1, 2, 4, 8]), None, (0.0, 0.0, 0.0))
    assert m.values_kind == "signed_distance" and len(d) == 2
    q = m.query(np.array([[0.25, 0.25, 0.25], [1.2, 0.2, 0.2], [5.0, 5.0, 5.0]]))
    assert q.known.tolist() == [True, True, False]
    assert q.labels.tolist() == [8, 4, 0]  # the last point of the first voxel won
    assert m.stats()["voxels_observed"] == 2 and len(m.occupied_voxels()) == 2
    back = SemanticMap.load(m.save(tmp_path / "toy.npz"))
    assert back.query(np.array([[0.25, 0.25, 0.25]])).labels.tolist() == [8]
    # the same class by its module:Class spec, as a plugin would be named in mapper.backend
    spec = SemanticMap("tests.support.toy_backend:LastLabel", 0.5)
    assert len(spec.integrate(pts, np.array([1, 2, 4, 8]))) == 2


def test_a_format_1_map_file_still_loads(tmp_path):
    m = SemanticMap("octree-max", 0.2, 4.0, 1.0)
    rng = np.random.default_rng(5)
    m.integrate(rng.uniform(-3, 3, (500, 3)).astype(np.float32), rng.integers(0, 9, 500))
    path = m.save(tmp_path / "map.npz")
    # rewrite the meta the way the code before the registry wrote it
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta"]).decode())
    octree = meta.pop("config")
    del octree["max_fusion"]  # format 1 predates it
    fusion = ("max_same_gain", "max_disagree_factor", "bayes_min_confidence")
    meta["occupancy"] = {k: v for k, v in octree.items() if k not in fusion}
    meta["fusion"] = {k: octree[k] for k in fusion}
    meta["tsdf"] = dataclasses.asdict(backend_class("tsdf").default_config())
    meta["format"] = 1
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "old.npz", **arrays)
    old = SemanticMap.load(tmp_path / "old.npz")
    # a file from before `max_fusion` was fused by the gain rule, and keeps it
    assert old.config == dataclasses.replace(m.config, max_fusion="gain")
    probe = rng.uniform(-3, 3, (300, 3))
    np.testing.assert_array_equal(old.query(probe).values, m.query(probe).values)


def test_a_saved_octree_map_keeps_its_max_fusion_rule(tmp_path):
    from smana.services.mapper.backends.occupancy import OctreeConfig

    gain = SemanticMap("octree-max", 0.2, 4.0, 1.0, config=OctreeConfig(max_fusion="gain"))
    assert SemanticMap.load(gain.save(tmp_path / "gain.npz")).config.max_fusion == "gain"
    plain = SemanticMap("octree-max", 0.2, 4.0, 1.0)
    path = plain.save(tmp_path / "plain.npz")
    assert SemanticMap.load(path).config.max_fusion == "average"
    # a format-2 file written before the field existed was fused by the gain rule
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta"]).decode())
    del meta["config"]["max_fusion"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "before.npz", **arrays)
    assert SemanticMap.load(tmp_path / "before.npz").config.max_fusion == "gain"


@pytest.mark.multiprocess
def test_a_toy_backend_by_spec_runs_in_a_mapper_process(zenoh_stack, tmp_path):
    st = zenoh_stack
    env = {"PYTHONPATH": os.pathsep.join([str(SUPPORT), os.environ.get("PYTHONPATH", "")])}
    args = ["--set", f"mapper.backend={TOY_SPEC}", "--set", "mapper.resolution_m=0.5"]
    argv = [*st.zenoh_args(), "--robot", st.robot, *args, "--set", "mapper.autosave_period_s=0"]
    st.start("mapper", "-m", "smana.services.mapper", *argv, env=env)
    st.wait_alive("mapper")
    got: list[MapDelta] = []
    sub = st.session.declare_subscriber(
        keys.map_delta(st.robot), lambda s: got.append(decode(s.payload.to_bytes(), MapDelta))
    )
    try:
        pub = st.publisher(keys.cloud(st.robot))
        pts = np.array([[1.1, 0.1, 0.1], [1.2, 0.2, 0.2], [2.1, 0.1, 0.1]], np.float32)
        cloud = SemanticCloud(
            stamp_s=1.0,
            seq=1,
            points=pts,
            labels=np.array([1, 2, 4], np.uint16),
            confidences=np.ones(3, np.float32),
            sensor_position=np.zeros(3),
        )
        deadline = time.monotonic() + 30
        while not got and time.monotonic() < deadline:
            pub.put(encode(cloud))
            time.sleep(0.3)
    finally:
        sub.undeclare()
    assert got, st.log("mapper")
    d = got[0]
    assert d.backend == TOY_SPEC and d.values_kind == LastLabel.values_kind == "signed_distance"
    order = np.lexsort(d.centres.T[::-1])
    np.testing.assert_allclose(d.centres[order], [[1.25, 0.25, 0.25], [2.25, 0.25, 0.25]])
    assert d.labels[order].tolist() == [2, 4] and d.values.tolist() == [0.0, 0.0]


def test_the_registry_module_is_lazy():
    code = (
        "import sys; from smana.services.mapper import backends; "
        "print(any(m.endswith(('tsdf', 'occupancy')) for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr
    assert backends.__doc__
