"""The Rerun recorder core: messages in, a readable .rrd with the expected entities out."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.messages import GraphPatch, MapDelta, Pose
from smana.deploy import recording as recmod

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
        stamp_s=stamp, seq=1, cloud_seq=1, backend="octree-max", resolution_m=0.1,
        centres=np.asarray(centres, np.float32), labels=np.asarray(labels, np.uint16),
        confidences=np.ones(n, np.float32), occupied=np.asarray(occupied, np.uint8),
        values=np.ones(n, np.float32),
    )  # fmt: skip


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
    b = msgpack.packb({"stamp_s": 2.0, "width": 2, "height": 2, "encoding": "rgb8",
                       "data": img.tobytes()})  # fmt: skip
    assert np.array_equal(recmod.decode_image(b)[1], img)
    with pytest.raises(ValueError):
        recmod.decode_image(msgpack.packb({"data": b"123", "shape": [2, 2]}))
    with pytest.raises(ValueError):
        recmod.decode_image(msgpack.packb([1, 2]))


def test_recording_holds_every_stream(tmp_path):
    rrd = tmp_path / "run.rrd"
    rec = recmod.RunRecorder(ClassTable.load("garden3drms"), rrd, graph_resolution_m=0.2,
                             graph_bounds=((0.0, 0.0), (8.0, 8.0)))  # fmt: skip
    for i in range(5):
        rec.on_pose(Pose.from_xyz_yaw(0.1 * i, 0.0, 0.0, 0.0, stamp_s=0.5 * i + 0.1))
        rec.on_pose(Pose.from_xyz_yaw(0.1 * i, 0.01, 0.0, 0.0, stamp_s=0.5 * i + 0.1), truth=True)
    rec.on_delta(_delta([[1.05, 1.05, 0.05], [1.15, 1.05, 0.05]], [1, 4], [1, 1], 1.0))
    cells = np.array([[5, 5], [5, 6], [6, 6]], np.int32)
    rec.on_patch(GraphPatch(
        stamp_s=1.2, seq=1, resolution_m=0.2, origin_xy=np.zeros(2), cells=cells,
        labels=np.array([2, 4, 1], np.uint16), heights=np.zeros(3, np.float32),
        flags=np.array([1, 3, 5], np.uint8),
    ))  # fmt: skip
    rgb = np.zeros((64, 64, 3), np.uint8)
    sem = np.full((64, 64), 2, np.uint8)
    for kind, img in (("rgb", rgb), ("semantic", sem)):
        payload = msgpack.packb({"stamp_s": 1.3, "data": img.tobytes(), "shape": list(img.shape),
                                 "dtype": "u1"})  # fmt: skip
        rec.on_image(kind, payload)
    rec.on_explorer_state({
        "t_s": 2.0, "candidates": [[1.0, 1.0], [2.0, 2.0]], "candidate_gains_m2": [1.0, 3.0],
        "path": [[0.0, 0.0], [1.0, 1.0]], "goal": {"xy": [1.0, 1.0], "yaw": 0.5},
        "explored_m2": 4.0, "distance_m": 0.4, "frontier_size": 12,
    })  # fmt: skip
    rec.close()
    ents = _entities(rrd)
    for e in ("/world/robot", "/world/trajectory", "/world/trajectory_truth", "/camera/rgb",
              "/camera/semantic", "/world/map/b0_0", "/world/graph/nodes",
              "/world/graph/obstacles", "/world/graph/safety_zone", "/world/explorer/frontier",
              "/world/explorer/path", "/world/explorer/goal", "/metrics/explored_m2"):  # fmt: skip
        assert e in ents, (e, sorted(ents))
    assert rec.counts["pose"] == 5 and rec.counts["patch"] == 1
    rec.save_trajectories(tmp_path)
    truth = np.loadtxt(tmp_path / "trajectory_truth.csv", delimiter=",", skiprows=1)
    assert truth.shape == (5, 5) and truth[-1, 1] == pytest.approx(0.4)
