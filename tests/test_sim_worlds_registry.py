"""The world registry: `sim.world` names a kind of world, an out-of-tree world is one file
(tests/support/toy_world.py) found by `module:Class` or `register()`, and it runs through the
stack: in-process (the camera sees its box with the box's label) and in a sim process over an
isolated zenoh (the published SemanticCloud carries that label)."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from smana.common import keys
from smana.common.config.sim import CameraConfig, SimConfig
from smana.common.messages import SemanticCloud, decode
from smana.services.sim import worlds
from smana.services.sim.labelled_ply import write_labelled_ply
from smana.services.sim.simulation import Simulation
from smana.services.sim.world_cli import cli as world_cli
from smana.services.sim.worlds import BOX, Primitive, WorldError, build_world, world_source
from smana.services.sim.worlds.cloud import PlyWorld
from smana.services.sim.worlds.garden import Garden
from tests.conftest import REPO, wait_for
from tests.support.toy_world import BOX_CENTRE, BOX_HALF_EXTENTS, HEDGE, ToyWorld

SUPPORT = REPO / "tests" / "support"
PLUGIN = "tests.support.toy_world:ToyWorld"  # importable from the repository root


@pytest.fixture
def registry(monkeypatch):
    """The registry, restored after the test."""
    monkeypatch.setattr(worlds, "WORLDS", worlds.WORLDS.copy())
    return worlds.WORLDS


def test_world_names_resolve_through_the_registry(tmp_path):
    assert type(world_source("garden")) is Garden and world_source("garden").arg is None
    src = world_source("ply:/data/garden.ply")
    assert type(src) is PlyWorld and src.arg == "/data/garden.ply"
    bare = world_source("some/where/garden.ply")  # a bare path to a .ply, as before
    assert type(bare) is PlyWorld and bare.arg == "some/where/garden.ply"
    plugin = world_source(PLUGIN + ":variant")
    assert type(plugin) is ToyWorld and plugin.arg == "variant"


def test_bad_world_names_fail_in_one_line(tmp_path):
    cases = [
        ("mars", "neither 'garden' nor a PLY file"),
        ("no_such_module:Toy", "no module 'no_such_module'"),
        ("tests.support.toy_world:Nothing", "no world class 'Nothing'"),
    ]
    for spec, message in cases:
        with pytest.raises(WorldError, match=message) as err:
            world_source(spec)
        assert "\n" not in str(err.value) and str(err.value).startswith("sim.world: ")
    with pytest.raises(WorldError, match="neither 'garden' nor a PLY file"):
        build_world(SimConfig(world=f"ply:{tmp_path / 'missing.ply'}"))


def test_a_registered_world_is_built_and_seen_by_the_camera(registry):
    worlds.register("toy", ToyWorld)
    world = build_world(SimConfig(world="toy"))
    assert world.name == "toy" and [o.class_id for o in world.objects] == [HEDGE]
    assert world.top_class().at(*BOX_CENTRE[:2]) == HEDGE
    cfg = SimConfig(world="toy", noise="off", camera=CameraConfig(width=96, height=96))
    with Simulation(cfg) as sim:
        x, y, _ = sim.world.spawn_pose(0.5)
        assert np.hypot(x, y) < 0.2  # the free centre, facing +x: the box is in view
        f = sim.camera_frame()
    box = f.labels == HEDGE
    assert box.sum() > 50
    assert set(np.unique(f.labels)) == {1, HEDGE}  # grass and the box, nothing else
    grown = Primitive(BOX, BOX_CENTRE, tuple(h + 0.03 for h in BOX_HALF_EXTENTS))
    assert grown.contains(f.points[box].astype(float)).all()
    with pytest.raises(ValueError, match="identifier"):
        worlds.register("not a name", ToyWorld)


def test_world_cli_builds_a_plugin_world_through_the_registry(tmp_path, capsys):
    out = tmp_path / "toy.ply"
    assert world_cli(["export", "--world", PLUGIN, "--spacing", "0.1", "--out", str(out)]) == 0
    assert world_cli(["preview", "--world", PLUGIN, "--out", str(tmp_path / "toy.png")]) == 0
    assert (tmp_path / "toy.png").stat().st_size > 0
    # the exported cloud is itself a world: `ply:PATH` and a bare path build the same one
    for spec in (f"ply:{out}", str(out)):
        capsys.readouterr()
        assert world_cli(["info", "--world", spec]) == 0
        assert '"name": "toy"' in capsys.readouterr().out
    assert world_cli(["info", "--world", "mars"]) == 2
    assert "neither 'garden' nor a PLY file" in capsys.readouterr().err


def test_cloud_worlds_take_their_section(tmp_path):
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)])
    labels = np.full(2000, 1, np.uint16)
    path = tmp_path / "flat.ply"
    write_labelled_ply(path, pts, labels, np.zeros((2000, 3), np.uint8))
    cfg = SimConfig(world=str(path))
    assert len(build_world(cfg).objects) == 4  # the walls
    from smana.services.sim.worlds.cloud import PlyConfig

    assert build_world(SimConfig(world=str(path), ply=PlyConfig(walls=False))).objects == []


@pytest.mark.multiprocess
def test_a_plugin_world_runs_in_a_sim_process(zenoh_stack):
    stack = zenoh_stack
    path = os.pathsep.join(p for p in (str(SUPPORT), os.environ.get("PYTHONPATH")) if p)
    stack.start(
        "sim",
        "-m",
        "smana.services.sim",
        *stack.zenoh_args(),
        "--robot",
        stack.robot,
        "--set",
        "sim.world=toy_world:ToyWorld",  # a bare word is a string
        "--camera",
        "64x64",
        "--noise",
        "off",
        env={"PYTHONPATH": path},
    )
    stack.wait_alive("sim")
    clouds: list[SemanticCloud] = []
    lock = threading.Lock()

    def on_cloud(sample):
        with lock:
            clouds.append(decode(sample.payload.to_bytes(), SemanticCloud))

    sub = stack.session.declare_subscriber(keys.cloud(stack.robot), on_cloud)
    try:
        assert wait_for(lambda: len(clouds) >= 1, 30.0), stack.log("sim")
        with lock:
            cloud = clouds[0]
        assert HEDGE in set(np.unique(cloud.labels).tolist())
        assert set(np.unique(cloud.labels).tolist()) <= {1, HEDGE}
    finally:
        sub.undeclare()
    assert "world toy" in stack.log("sim")
