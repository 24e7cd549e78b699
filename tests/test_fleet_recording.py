"""A fleet's recording: one recorder started as the fleet records every member's poses, path and
goal under its own entity, the fleet's map and graph once, per-member trajectory files and
counts. The core in-process, the service on the fake zenoh (tests/support/fake_zenoh.py)."""

from __future__ import annotations

import json
import threading

import msgpack
import numpy as np
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import GraphPatch, MapDelta, Pose, encode
from smana.services.recorder import recorder as recmod
from smana.services.recorder import service as recsvc
from tests.conftest import wait_for

rr = pytest.importorskip("rerun")

MEMBERS = ("r1", "r2")


def _entities(path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    out: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        out[str(chunk.entity_path)] = out.get(str(chunk.entity_path), 0) + chunk.num_rows
    return out


def _delta(stamp):
    c = np.array([[1.05, 1.05, 0.05], [1.15, 1.05, 0.05]], np.float32)
    return MapDelta(
        stamp_s=stamp,
        seq=1,
        cloud_seq=1,
        backend="octree-max",
        resolution_m=0.1,
        centres=c,
        labels=np.array([1, 4], np.uint16),
        confidences=np.ones(2, np.float32),
        occupied=np.ones(2, np.uint8),
        values=np.ones(2, np.float32),
    )


def _patch(stamp):
    return GraphPatch(
        stamp_s=stamp,
        seq=1,
        resolution_m=0.2,
        origin_xy=np.zeros(2),
        cells=np.array([[5, 5], [5, 6]], np.int32),
        labels=np.array([2, 4], np.uint16),
        heights=np.zeros(2, np.float32),
        flags=np.array([1, 3], np.uint8),
    )


def _state(k, t):
    return {
        "t_s": t,
        "path": [[0.0, float(k)], [1.0, float(k)]],
        "goal": {"xy": [1.0, float(k)], "yaw": 0.0},
        "explored_m2": 3.0 + k,
        "distance_m": 0.5,
        "frontier_size": 4,
    }


def test_a_fleet_recording_holds_every_member(tmp_path):
    rrd = tmp_path / "recording.rrd"
    rec = recmod.RunRecorder(
        ClassTable.load("garden3drms"), rrd, trajectory_dir=tmp_path, members=MEMBERS
    )
    for k, r in enumerate(MEMBERS):
        for i in range(4):
            pose = Pose.from_xyz_yaw(0.1 * i, float(k), 0.0, 0.0, stamp_s=0.5 * i + 0.1)
            rec.on_pose(pose, robot=r)
            rec.on_pose(pose, truth=True, robot=r)
        rec.on_explorer_state(_state(k, 2.0), robot=r)
    rec.on_delta(_delta(1.0))
    rec.on_patch(_patch(1.2))
    rec.close()
    ents = _entities(rrd)
    for r in MEMBERS:
        for e in ("robot", "robot/body", "trajectory", "trajectory_truth"):
            assert f"/world/robots/{r}/{e}" in ents, (r, e, sorted(ents))
        for e in ("path", "goal"):
            assert f"/world/robots/{r}/explorer/{e}" in ents, (r, e, sorted(ents))
        assert f"/metrics/{r}/explored_m2" in ents
        rows = np.loadtxt(
            tmp_path / "robots" / r / "trajectory_truth.csv", delimiter=",", skiprows=1
        )
        assert rows.shape == (4, 5) and rows[0, 2] == MEMBERS.index(r)
        assert rec.tracks[r].counts == {"pose": 4, "pose_truth": 4, "explorer_state": 1}
    # the map and graph once, no single-robot entities
    assert "/world/map/b0_0" in ents and "/world/graph/nodes" in ents
    assert not any(e.startswith(("/world/robot/", "/world/trajectory")) for e in ents)
    assert "/world/robot" not in ents and not (tmp_path / "trajectory_pose.csv").exists()


def test_the_fleet_recorder_service_subscribes_to_every_member(fake_stack, tmp_path):
    stack = fake_stack
    run = tmp_path / "run"
    cfg = SmanaConfig.load(
        None,
        [
            f'zenoh.connect=["{stack.endpoint}"]',
            'general.robot="fleet"',
            f'general.run_dir="{run}"',
            f"fleet.robots={list(MEMBERS)!r}".replace("'", '"'),
        ],
    )
    svc = recsvc.RecorderService(cfg, run / "recording.rrd")
    assert svc.members == list(MEMBERS)
    t = threading.Thread(target=svc.run, daemon=True)
    t.start()
    try:
        stack.wait_alive("recorder", timeout_s=60, robot="fleet")
        n = 3
        for k, r in enumerate(MEMBERS):
            poses = stack.publisher(keys.pose(r))
            states = stack.publisher(keys.explorer_state(r))
            for i in range(n):
                poses.put(encode(Pose.from_xyz_yaw(0.1 * i, float(k), 0, 0, stamp_s=0.1 * i)))
            states.put(msgpack.packb(_state(k, 1.0)))
        stack.publisher(keys.map_delta("fleet")).put(encode(_delta(1.0)))
        stack.publisher(keys.graph_patch("fleet")).put(encode(_patch(1.0)))

        def done():
            c = svc.core.counts
            return c.get("pose") == 2 * n and c.get("explorer_state") == 2 and c.get("patch")

        assert wait_for(done, 30), svc.core.counts
    finally:
        svc.stop()
        t.join(30)
    assert not t.is_alive()
    summary = json.loads((run / recmod.SUMMARY_NAME).read_text())
    assert summary["recorded"]["delta"] == 1 and summary["recorded"]["patch"] == 1
    for r in MEMBERS:
        assert summary["members"][r] == {"pose": n, "pose_truth": 0, "explorer_state": 1}
        assert summary["trajectories"][r] == {"pose": f"robots/{r}/trajectory_pose.csv"}
        rows = (run / "robots" / r / "trajectory_pose.csv").read_text().splitlines()
        assert len(rows) == n + 1
    ents = _entities(run / "recording.rrd")
    assert {"/world/robots/r1/explorer/goal", "/world/robots/r2/explorer/goal"} <= set(ents)
