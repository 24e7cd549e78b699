"""The Rerun recorder: messages in, a readable .rrd with the expected entities out, and every pose
it is sent in its trajectory file until the stack stops."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import ServiceDeployConfig, SmanaConfig
from smana.common.messages import GraphPatch, MapDelta, Pose, encode
from smana.deploy.supervisor import Supervisor
from smana.services.recorder import recorder as recmod
from smana.services.recorder import service as recsvc
from tests.conftest import free_port, wait_for

rr = pytest.importorskip("rerun")


def _entities(path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    out: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        out[str(chunk.entity_path)] = out.get(str(chunk.entity_path), 0) + chunk.num_rows
    return out


def _delta(centres, labels, occupied, stamp):
    n = len(centres)
    return MapDelta(
        stamp_s=stamp,
        seq=1,
        cloud_seq=1,
        backend="octree-max",
        resolution_m=0.1,
        centres=np.asarray(centres, np.float32),
        labels=np.asarray(labels, np.uint16),
        confidences=np.ones(n, np.float32),
        occupied=np.asarray(occupied, np.uint8),
        values=np.ones(n, np.float32),
    )


def test_voxel_store_keeps_the_newest_state_per_voxel():
    vs = recmod.VoxelStore(block_m=2.0)
    vs.apply(_delta([[0.05, 0.05, 0.05], [3.05, 0.05, 0.05]], [1, 4], [1, 1], 1.0))
    assert len(vs.keys) == 2 and vs.dirty_blocks == {(0, 0), (1, 0)}
    vs.apply(_delta([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]], [2, 8], [1, 0], 2.0))
    c, lab = vs.block((0, 0))
    assert c.tolist() == [[pytest.approx(0.05)] * 3] and lab.tolist() == [2]
    vs.apply(_delta([[3.05, 0.05, 0.05]], [4], [0], 3.0))  # freed
    assert len(vs.block((1, 0))[0]) == 0


def test_decode_image_forms():
    img = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    a = msgpack.packb({"stamp_s": 1.5, "data": img.tobytes(), "shape": [2, 2, 3], "dtype": "u1"})
    t, out = recmod.decode_image(a)
    assert t == 1.5 and np.array_equal(out, img)
    b = msgpack.packb(
        {"stamp_s": 2.0, "width": 2, "height": 2, "encoding": "rgb8", "data": img.tobytes()}
    )
    assert np.array_equal(recmod.decode_image(b)[1], img)
    with pytest.raises(ValueError):
        recmod.decode_image(msgpack.packb({"data": b"123", "shape": [2, 2]}))
    with pytest.raises(ValueError):
        recmod.decode_image(msgpack.packb([1, 2]))


def test_recording_holds_every_stream(tmp_path):
    rrd = tmp_path / "run.rrd"
    rec = recmod.RunRecorder(
        ClassTable.load("garden3drms"),
        rrd,
        graph_resolution_m=0.2,
        graph_bounds=((0.0, 0.0), (8.0, 8.0)),
    )
    for i in range(5):
        rec.on_pose(Pose.from_xyz_yaw(0.1 * i, 0.0, 0.0, 0.0, stamp_s=0.5 * i + 0.1))
        rec.on_pose(Pose.from_xyz_yaw(0.1 * i, 0.01, 0.0, 0.0, stamp_s=0.5 * i + 0.1), truth=True)
    rec.on_delta(_delta([[1.05, 1.05, 0.05], [1.15, 1.05, 0.05]], [1, 4], [1, 1], 1.0))
    cells = np.array([[5, 5], [5, 6], [6, 6]], np.int32)
    rec.on_patch(
        GraphPatch(
            stamp_s=1.2,
            seq=1,
            resolution_m=0.2,
            origin_xy=np.zeros(2),
            cells=cells,
            labels=np.array([2, 4, 1], np.uint16),
            heights=np.zeros(3, np.float32),
            flags=np.array([1, 3, 5], np.uint8),
        )
    )
    rgb = np.zeros((64, 64, 3), np.uint8)
    sem = np.full((64, 64), 2, np.uint8)
    for kind, img in (("rgb", rgb), ("semantic", sem)):
        payload = msgpack.packb(
            {"stamp_s": 1.3, "data": img.tobytes(), "shape": list(img.shape), "dtype": "u1"}
        )
        rec.on_image(kind, payload)
    rec.on_explorer_state(
        {
            "t_s": 2.0,
            "candidates": [[1.0, 1.0], [2.0, 2.0]],
            "candidate_gains_m2": [1.0, 3.0],
            "path": [[0.0, 0.0], [1.0, 1.0]],
            "goal": {"xy": [1.0, 1.0], "yaw": 0.5},
            "explored_m2": 4.0,
            "distance_m": 0.4,
            "frontier_size": 12,
        }
    )
    rec.close()
    ents = _entities(rrd)
    for e in (
        "/world/robot",
        "/world/trajectory",
        "/world/trajectory_truth",
        "/camera/rgb",
        "/camera/semantic",
        "/world/map/b0_0",
        "/world/graph/nodes",
        "/world/graph/obstacles",
        "/world/graph/safety_zone",
        "/world/explorer/frontier",
        "/world/explorer/path",
        "/world/explorer/goal",
        "/metrics/explored_m2",
    ):
        assert e in ents, (e, sorted(ents))
    assert rec.counts["pose"] == 5 and rec.counts["patch"] == 1
    rec.save_trajectories(tmp_path)
    truth = np.loadtxt(tmp_path / "trajectory_truth.csv", delimiter=",", skiprows=1)
    assert truth.shape == (5, 5) and truth[-1, 1] == pytest.approx(0.4)


def test_an_explorer_state_whose_goal_has_no_yaw_is_recorded_whole(tmp_path):
    # `smana goto X Y` sets no heading: the state was dropped at float(None), metrics and all
    rrd = tmp_path / "run.rrd"
    rec = recmod.RunRecorder(ClassTable.load("garden3drms"), rrd)
    for i in range(3):
        rec.on_explorer_state(
            {"t_s": float(i), "goal": {"xy": [0.5, 0.2], "yaw": None}, "explored_m2": 1.0 + i}
        )
    rec.close()
    ents = _entities(rrd)
    assert "/world/explorer/goal" in ents and "/metrics/explored_m2" in ents, sorted(ents)
    assert rec.counts["explorer_state"] == 3


def test_recorder_core_keeps_every_pose_as_it_comes(tmp_path):
    """Every pose is a row, whatever it holds (repeated, out of order, a zero stamp, a jump): in
    memory and in the trajectory file at once, before the recorder is closed or killed."""
    rec = recmod.RunRecorder(ClassTable.load("garden3drms"), None, trajectory_dir=tmp_path)
    poses = [(1.0, 0.0), (1.1, 0.1), (1.1, 0.1), (1.05, 0.2), (0.0, 0.3), (1.2, 500.0)]
    for stamp, x in poses:
        rec.on_pose(Pose.from_xyz_yaw(x, 1.0, 0.0, 0.5, stamp_s=stamp))
    rec.on_pose(Pose.from_xyz_yaw(0.0, 1.01, 0.0, 0.5, stamp_s=1.0), truth=True)
    rows = np.loadtxt(tmp_path / "trajectory_pose.csv", delimiter=",", skiprows=1, ndmin=2)
    assert rows[:, [0, 1]].tolist() == [list(p) for p in poses]
    assert rows[:, 4] == pytest.approx(0.5, abs=1e-4) and len(rec.trajectory) == len(poses)
    assert (
        len(np.loadtxt(tmp_path / "trajectory_truth.csv", delimiter=",", skiprows=1, ndmin=2)) == 1
    )
    assert rec.counts == {"pose": len(poses), "pose_truth": 1}
    rec.close()
    assert len((tmp_path / "trajectory_pose.csv").read_text().splitlines()) == len(poses) + 1


def test_voxel_store_blocks_match_a_mask_per_block():
    rng = np.random.default_rng(1)
    vs = recmod.VoxelStore(block_m=2.0)
    for k in range(3):
        c = (np.floor(rng.uniform(-9, 9, (500, 3)) / 0.1) + 0.5) * 0.1
        vs.apply(_delta(c, rng.integers(1, 9, 500), rng.random(500) < 0.8, float(k)))
    wanted = set(vs.dirty_blocks)
    assert len(wanted) > 20
    got = vs.blocks(wanted)
    assert sum(len(c) for _, c, _ in got) == len(vs.keys)
    blocks = np.floor(vs.centres[:, :2] / 2.0).astype(int)
    for b, c, lab in got:
        sel = (blocks == np.asarray(b)).all(axis=1)
        assert sorted(map(tuple, c.tolist())) == sorted(map(tuple, vs.centres[sel].tolist()))
        assert sorted(lab.tolist()) == sorted(vs.labels[sel].tolist())


def test_a_recorder_behind_records_its_backlog_when_stopped(fake_stack, tmp_path):
    """A stop that comes while the recorder is still working on a delta (the mapper's are large)
    records the poses queued behind it too, and says so in recorder.json. In-process on the fake
    zenoh (tests/support/fake_zenoh.py)."""
    zenoh_stack = fake_stack
    robot = zenoh_stack.robot
    cfg = SmanaConfig.load(
        None,
        [
            f'zenoh.connect=["{zenoh_stack.endpoint}"]',
            f'general.robot="{robot}"',
            f'general.run_dir="{tmp_path / "run"}"',
        ],
    )
    svc = recsvc.RecorderService(cfg, tmp_path / "run" / "recording.rrd")
    on_delta, release, holding = svc.core.on_delta, threading.Event(), threading.Event()

    def held_delta(delta):  # the first delta holds the recorder until the stop has come
        holding.set()
        release.wait(30)
        on_delta(delta)

    svc.core.on_delta = held_delta
    t = threading.Thread(target=svc.run, daemon=True)
    t.start()
    try:
        zenoh_stack.wait_alive("recorder", timeout_s=60)
        asked = svc.books.received  # the status queries of wait_alive (kernels loaded?)
        poses = zenoh_stack.publisher(keys.pose(robot))
        deltas = zenoh_stack.publisher(keys.map_delta(robot))
        n = 10
        # the first delta first, and held: then everything else queues behind it (the two keys
        # have no order between them, so the poses wait for the hold)
        deltas.put(encode(_delta([[0.0, 0.05, 0.05]], [1], [1], 0.0)))
        assert holding.wait(30)
        for i in range(n):
            if i:
                deltas.put(encode(_delta([[0.05 * i, 0.05, 0.05]], [1], [1], 0.1 * i)))
            poses.put(encode(Pose.from_xyz_yaw(0.1 * i, 0.0, 0.0, 0.0, stamp_s=0.1 * i)))
        assert wait_for(lambda: svc.books.received >= 2 * n + asked, 30)
        assert "pose" not in svc.core.counts  # all of them queued behind the first delta
    finally:
        svc.stop()
        release.set()
        t.join(30)
    assert not t.is_alive()
    rows = (tmp_path / "run" / "trajectory_pose.csv").read_text().splitlines()
    assert len(rows) == n + 1
    summary = json.loads((tmp_path / "run" / recmod.SUMMARY_NAME).read_text())
    assert summary["recorded"] == {"pose": n, "pose_truth": 0, "delta": n, "patch": 0}
    assert summary["dropped"] == {}
    assert summary["accepted"] == summary["msgs_in"] == 2 * n + asked


@pytest.mark.multiprocess
def test_recorder_records_every_pose_until_the_stack_stops(tmp_path):
    """A source publishing poses as fast as it can until `smana up` stops it: the recorder is
    stopped after it, so every pose published is in trajectory_pose.csv and its books add up."""
    cfg = SmanaConfig.load(
        None,
        [
            f'deploy.router_listen=["tcp/127.0.0.1:{free_port()}"]',
            "general.robot=rec",
            "general.status_period_s=0.5",
        ],
    )
    run = tmp_path / "run"
    sup = Supervisor(cfg, run, services=[])
    source = str(Path(__file__).parent / "support" / "pose_source.py")
    sup.add(
        "sim",
        [sys.executable, source, "--config", str(sup.config_path)],
        ServiceDeployConfig(restart="never"),
    )
    sup.add(
        "recorder",
        recsvc.recorder_argv(sup.config_path, "rec"),
        ServiceDeployConfig(restart="never"),
    )
    t = threading.Thread(target=sup.run, kwargs={"progress_period_s": 3600}, daemon=True)
    t.start()
    rows = run / "trajectory_pose.csv"

    def recorded() -> int:
        return len(rows.read_text().splitlines()) - 1 if rows.is_file() else 0

    try:
        # Stop once the recorder has recorded poses for a while (counted from its first row).
        assert wait_for(lambda: recorded() > 0, 120), (run / "logs" / "recorder.log").read_text()
        assert wait_for(lambda: recorded() > 100, 60)
    finally:
        sup.stop()
        t.join(60)
    assert not t.is_alive()
    published = json.loads((run / "pose_source.json").read_text())["published"]
    summary = json.loads((run / recmod.SUMMARY_NAME).read_text())
    assert recorded() == published == summary["recorded"]["pose"], summary
    books = (
        summary["accepted"]
        + sum(summary["dropped"].values())
        + sum(summary["rejected"].values())
        + summary["pending"]
    )
    assert summary["msgs_in"] == books and not summary["dropped"] and not summary["rejected"]
