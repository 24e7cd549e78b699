"""`smana replay --label-field none`: scans without labels (KITTI .bin without .label, PLY/NPZ
without a label, PointCloud2 without a label field) are read without labels and labelled by
geometry in the world frame, with the `geometric` class table; labelled data is unchanged; a
missing label field without `none` says what to do. Ends with the real stack: an unlabelled
sequence through mapper and navgraph processes builds a graph with ground and obstacle nodes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.geometric import GROUND, OBSTACLE, GeometricLabeller, label_geometric
from smana.common.ros import check_cloud, decode_cloud
from smana.lab.data import synthetic as syn
from smana.services.replay.prepare import prepare_scan
from smana.services.replay.readers import DatasetError, open_dataset
from smana.services.replay.readers.base import Scan
from smana.services.replay.readers.folder import write_ply
from smana.services.replay.service import open_reader, table_name

N_RUN = 8


def drop_labels(seq):
    shutil.rmtree(seq / "os1_cloud_node_semantickitti_label_id")
    return seq


@pytest.fixture(scope="module")
def unlabelled(tmp_path_factory):
    """A synthetic RELLIS-3D sequence (KITTI .bin scans) with its label folder removed, and the
    labels kept aside as the truth."""
    root = tmp_path_factory.mktemp("unlabelled")
    params = syn.SyntheticConfig(n_scans=N_RUN, beams=32, columns=1024, noise_m=0.0)
    seq = syn.write_rellis_sequence(root, params)
    truth = {
        p.stem: np.fromfile(p, np.uint32)
        for p in (seq / "os1_cloud_node_semantickitti_label_id").glob("*.label")
    }
    drop_labels(seq)
    return SimpleNamespace(root=root, seq=seq, truth=truth, params=params)


def flat_scan(n=4000, seed=0):
    """Flat ground 1.5 m below a sensor, and a wall: in the sensor frame."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-6, 6, (n, 2)), np.full(n, -1.5)]
    wall = np.c_[np.full(n // 4, 3.0), rng.uniform(-2, 2, n // 4), rng.uniform(-1.5, 1.0, n // 4)]
    return np.concatenate([ground, wall]).astype(np.float32)


# -- readers ----------------------------------------------------------------------------------


def test_kitti_bins_without_labels(unlabelled):
    with pytest.raises(DatasetError, match=r"label folder is missing \(--label-field none"):
        open_dataset(unlabelled.root)
    reader = open_dataset(unlabelled.root, label_field="none")
    assert not reader.labelled and len(reader) == N_RUN and reader.skipped == []
    assert reader.info().class_table == "geometric"
    scan = reader.scan(0)
    assert scan.labels is None and scan.points.shape[1] == 3


def test_kitti_labels_win_when_present(tmp_path):
    params = syn.SyntheticConfig(n_scans=2, beams=8, columns=64, noise_m=0.0)
    syn.write_rellis_sequence(tmp_path, params)
    reader = open_dataset(tmp_path)
    assert reader.labelled and reader.info().class_table == "rellis3d"
    assert reader.scan(0).labels is not None
    with pytest.raises(ValueError, match="only 'none' applies"):
        open_dataset(tmp_path, label_field="class")


def test_ply_and_npz_without_labels(tmp_path):
    pts = flat_scan(400)
    ply_dir, npz_dir = tmp_path / "ply", tmp_path / "npz"
    ply_dir.mkdir()
    npz_dir.mkdir()
    from smana.common import ply_files

    ply_files.write_ply(ply_dir / "0.ply", {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
    (ply_dir / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    np.savez(npz_dir / "0.npz", points=pts, pose=np.eye(4))
    for folder in (ply_dir, npz_dir):
        with pytest.raises(DatasetError, match="--label-field none"):
            open_dataset(folder)
        reader = open_dataset(folder, label_field="none")
        scan = reader.scan(0)
        assert scan.labels is None
        np.testing.assert_allclose(scan.points, pts, atol=1e-6)
    # a labelled PLY keeps its labels
    labelled = tmp_path / "labelled"
    labelled.mkdir()
    write_ply(labelled / "0.ply", pts, np.arange(len(pts)) % 3)
    (labelled / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    np.testing.assert_array_equal(open_dataset(labelled).scan(0).labels, np.arange(len(pts)) % 3)


class _Field(SimpleNamespace):
    pass


def cloud_msg(points, label=None):
    """A PointCloud2-like object: x, y, z float32 and optionally a uint16 label."""
    names, formats = ["x", "y", "z"], ["<f4", "<f4", "<f4"]
    if label is not None:
        names.append("label")
        formats.append("<u2")
    dt = np.dtype({"names": names, "formats": formats})
    rec = np.zeros(len(points), dt)
    for k, a in enumerate("xyz"):
        rec[a] = points[:, k]
    if label is not None:
        rec["label"] = label
    codes = {"<f4": 7, "<u2": 4}
    fields = [
        _Field(name=n, offset=dt.fields[n][1], datatype=codes[f], count=1)
        for n, f in zip(names, formats, strict=True)
    ]
    return SimpleNamespace(
        fields=fields,
        is_bigendian=False,
        point_step=dt.itemsize,
        row_step=dt.itemsize * len(points),
        width=len(points),
        height=1,
        data=rec.tobytes(),
    )


def test_ros_cloud_without_a_label_field():
    pts = flat_scan(100)
    bare = cloud_msg(pts)
    assert "label field 'label' missing" in check_cloud(bare, "label")
    assert check_cloud(bare, None) is None
    points, labels, conf = decode_cloud(bare, None)
    np.testing.assert_array_equal(points, pts)
    assert labels is None and conf is None
    # labelled clouds read as before, and may still be read without their labels
    lab = np.arange(len(pts)) % 5
    labelled = cloud_msg(pts, lab)
    assert check_cloud(labelled, "label") is None
    np.testing.assert_array_equal(decode_cloud(labelled, "label")[1], lab)
    assert decode_cloud(labelled, None)[1] is None
    empty = cloud_msg(pts[:0])
    assert decode_cloud(empty, None)[1] is None


def test_bag_without_a_label_field(tmp_path):
    pytest.importorskip("rosbags")
    from tests.test_replay_rosbag import scan_data, write_bag

    path = write_bag(tmp_path / "b.bag", "ros1", scan_data(), cloud_kw={"label_field": "class"})
    with pytest.raises(DatasetError, match="--label-field none"):
        open_dataset(path)
    with open_dataset(path, label_field="none") as reader:
        assert not reader.labelled and len(reader) == len(scan_data())
        scan = reader.scan(1)
        assert scan.labels is None
        np.testing.assert_array_equal(scan.points, scan_data()[1][1])


# -- preparing: labelled by geometry in the world frame ---------------------------------------


def pitched_pose(pitch, z):
    c, s = np.cos(pitch), np.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[2, 3] = z
    return m


def test_prepare_labels_unlabelled_scans_in_the_world_frame():
    """A sensor pitched by 25 degrees sees flat ground as a 25-degree slope in its own frame:
    labelled in the world frame (after the pose), it is ground."""
    world_pts = flat_scan(30000) + np.array([0, 0, 1.5], np.float32)  # the ground at z = 0
    pose = pitched_pose(np.radians(25), 1.5)  # the sensor 1.5 m above it
    inv = np.linalg.inv(pose)
    sensor = (world_pts.astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
    scan = Scan(0, "s", 0.0, sensor, None, pose)
    table = ClassTable.load("geometric")
    lab = GeometricLabeller.from_config(SmanaConfig())
    pc = prepare_scan(scan, table, max_range_m=20.0, min_range_m=0.5, labeller=lab)
    assert pc.n_out == len(world_pts) and pc.n_unclaimed == 0 and pc.n_ignored == 0
    np.testing.assert_allclose(pc.points, world_pts, atol=1e-4)
    np.testing.assert_array_equal(pc.labels, lab.label(pc.points, pose[:3, 3]))
    is_ground = np.abs(pc.points[:, 2]) < 1e-3
    assert np.mean(pc.labels[is_ground] == GROUND) > 0.98
    assert np.all(pc.labels[pc.points[:, 2] > 0.35] == OBSTACLE)  # the wall
    # in the sensor frame the same points are a steep slope, not ground
    assert np.mean(label_geometric(sensor, [0, 0, 0])[is_ground] == GROUND) < 0.5


def test_prepare_refuses_unlabelled_scans_without_the_labeller():
    scan = Scan(0, "s", 0.0, flat_scan(100), None, np.eye(4))
    with pytest.raises(ValueError, match="has no labels"):
        prepare_scan(scan, ClassTable.load("geometric"), 10.0)
    lab = GeometricLabeller.from_config(SmanaConfig())
    with pytest.raises(ValueError, match="'geometric' class table"):
        prepare_scan(scan, ClassTable.load("rellis3d"), 10.0, labeller=lab)


def test_a_table_other_than_geometric_is_refused(unlabelled):
    rc = SmanaConfig.load(
        overrides=[f'replay.dataset="{unlabelled.root}"', "replay.label_field=none"]
    ).replay
    reader = open_reader(rc)
    assert table_name(rc, reader) == "geometric"
    import dataclasses

    with pytest.raises(ValueError, match="leave out --table"):
        table_name(dataclasses.replace(rc, class_table="rellis3d"), reader)
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.replay", str(unlabelled.root)]
        + ["--label-field", "none", "--table", "rellis3d", "--info"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "leave out --table" in out.stderr
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.replay", str(unlabelled.root)]
        + ["--label-field", "none", "--info"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0 and "class table geometric" in out.stdout


# -- the real stack ---------------------------------------------------------------------------


@pytest.mark.multiprocess
def test_run_unlabelled_builds_a_graph_with_ground_and_obstacles(unlabelled, tmp_path):
    """`smana replay --label-field none --run`: replay, mapper, navgraph and planner as
    processes on an isolated loopback endpoint."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    run = tmp_path / "run"
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.replay", str(unlabelled.root)]
        + ["--label-field", "none", "--run", "--run-dir", str(run)]
        + ["--set", f'deploy.router_listen=["tcp/127.0.0.1:{port}"]'],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run / "replay.json").read_text())
    assert summary["published"] == summary["acknowledged"] == N_RUN and summary["lost"] == 0
    config = (run / "config.toml").read_text()
    assert 'class_table = "geometric"' in config and 'label_field = "none"' in config
    per_class = json.loads((run / "metrics.json").read_text())["map_content"]["per_class"]
    assert per_class["ground"]["share"] > 0.3 and per_class["obstacle"]["share"] > 0.01, per_class
    with np.load(run / "graph.npz") as g:
        known = (g["flags"] & 1).astype(bool)
        obstacle = (g["flags"] & 2).astype(bool)
        ground = known & (g["labels"] == GROUND)
        print(
            f"\nunlabelled replay: {known.sum()} known nodes, {ground.sum()} ground, "
            f"{obstacle.sum()} obstacle; map points {per_class}"
        )
        assert ground.sum() > 100, "ground nodes"
        assert obstacle.sum() > 5, "obstacle nodes"


def test_real_kitti_scan_through_the_reader(tmp_path):
    """The KITTI scan of tests/data as a SemanticKITTI sequence without labels, read and
    prepared as the replay does (10 m around the sensor, 1.73 m above the road)."""
    from pathlib import Path

    seq = tmp_path / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    shutil.copy(Path(__file__).parent / "data" / "kitti" / "000000.bin", seq / "velodyne")
    identity = "1 0 0 0 0 1 0 0 0 0 1 0"
    (seq / "poses.txt").write_text(identity + "\n")
    (seq / "calib.txt").write_text(f"Tr: {identity}\n")
    reader = open_dataset(tmp_path, label_field="none")
    table = ClassTable.load(reader.info().class_table)
    lab = GeometricLabeller.from_config(SmanaConfig())
    pc = prepare_scan(reader.scan(0), table, max_range_m=10.0, min_range_m=0.5, labeller=lab)
    share = np.bincount(pc.labels, minlength=3) / pc.n_out
    road = np.abs(pc.points[:, 2] + 1.73) < 0.15
    assert pc.n_out > 50000 and share[GROUND] > 0.7 and 0.05 < share[OBSTACLE] < 0.4
    assert np.mean(pc.labels[road] == GROUND) > 0.95
