"""Dataset readers on tiny fixture datasets written here: formats, pose conventions, and every
malformed case giving its clear error or skip reason."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from smana.common.classes import ClassTable, ClassTableError
from smana.services.replay.readers import DatasetError, detect_format, open_dataset
from smana.services.replay.readers.folder import write_ply

TR = np.array(  # LiDAR -> camera, KITTI-like axes with an offset
    [[0.0, -1.0, 0.0, 0.1], [0.0, 0.0, -1.0, -0.2], [1.0, 0.0, 0.0, -0.3], [0, 0, 0, 1.0]]
)


def pose_xyz_yaw(x, y, z, yaw, pitch=0.0):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array(
        [[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]
    )
    m[:3, 3] = x, y, z
    return m


def row(m):
    return " ".join(repr(float(v)) for v in m[:3, :4].reshape(-1))


def make_kitti(root, n=3, n_points=500, cloud_dir="velodyne", label_dir="labels", seed=0):
    """A SemanticKITTI-style sequence; returns (seq dir, LiDAR poses, points, raw labels)."""
    rng = np.random.default_rng(seed)
    seq = root
    (seq / cloud_dir).mkdir(parents=True)
    (seq / label_dir).mkdir()
    lidar_poses = [pose_xyz_yaw(k * 0.5, 0.2 * k, 0.1, 0.3 * k, 0.05 * k) for k in range(n)]
    pts, labs = [], []
    for k in range(n):
        p = rng.uniform(-5, 5, (n_points, 3)).astype(np.float32)
        sem = rng.choice([0, 1, 3, 4, 7, 10, 40, 72], n_points).astype(np.uint32)
        inst = rng.integers(0, 50, n_points).astype(np.uint32)
        np.column_stack([p, rng.random(n_points, dtype=np.float32)]).tofile(
            seq / cloud_dir / f"{k:06d}.bin"
        )
        (sem | (inst << 16)).tofile(seq / label_dir / f"{k:06d}.label")
        pts.append(p)
        labs.append(sem)
    (seq / "poses.txt").write_text(
        "".join(row(TR @ m @ np.linalg.inv(TR)) + "\n" for m in lidar_poses)
    )
    (seq / "calib.txt").write_text(
        "".join(f"P{i}: {row(np.eye(4))}\n" for i in range(4)) + f"Tr: {row(TR)}\n"
    )
    return seq, np.array(lidar_poses), pts, labs


# -- class tables -----------------------------------------------------------------------------


def test_dataset_tables_map_their_ids():
    rellis = ClassTable.load("rellis3d")
    raw = np.array([0, 1, 3, 4, 7, 10, 23, 31, 33, 2, 99])
    labels, n_unclaimed = rellis.map_dataset_labels(raw)
    names = [rellis[int(i)].name for i in labels]
    assert names == [
        "void",
        "dirt",
        "grass",
        "tree",
        "sky",
        "asphalt",
        "concrete",
        "puddle",
        "mud",
        "unknown",
        "unknown",
    ]
    assert n_unclaimed == 2
    for name in ("dirt", "asphalt", "concrete"):
        assert rellis.by_name(name).cost < rellis.by_name("grass").cost
    for name in ("grass", "mud", "puddle"):
        assert rellis.by_name(name).traversable and rellis.by_name(name).cost > 1
    for name in (
        "tree",
        "bush",
        "fence",
        "building",
        "pole",
        "person",
        "vehicle",
        "barrier",
        "log",
        "rubble",
        "water",
    ):
        assert rellis.by_name(name).obstacle
    assert rellis.by_name("sky").kind == rellis.by_name("void").kind == "ignored"

    kitti = ClassTable.load("semantickitti")
    labels, _ = kitti.map_dataset_labels(np.array([10, 252, 40, 60, 72, 0, 1]))
    assert [kitti[int(i)].name for i in labels] == [
        "car",
        "car",
        "road",
        "road",
        "terrain",
        "unlabeled",
        "unlabeled",
    ]


def test_table_without_maps_from_keeps_ids():
    garden = ClassTable.load("garden3drms")
    assert not garden.maps_dataset_ids
    labels, n_bad = garden.map_dataset_labels(np.array([1, 2, 3, 8, 300]))
    assert labels.tolist() == [1, 2, 0, 8, 0] and n_bad == 2


@pytest.mark.parametrize(
    "maps_from, match",
    [([1, 1.5], "maps_from"), ("3", "maps_from"), ([70000], "maps_from")],
)
def test_maps_from_is_validated(maps_from, match):
    data = {
        "class": [
            {"id": 0, "name": "unknown", "kind": "unknown"},
            {"id": 1, "name": "a", "kind": "obstacle", "maps_from": maps_from},
        ]
    }
    with pytest.raises(ClassTableError, match=match):
        ClassTable.from_dict(data)


def test_maps_from_claimed_twice_is_an_error():
    data = {
        "class": [
            {"id": 0, "name": "unknown", "kind": "unknown", "maps_from": [5]},
            {"id": 1, "name": "a", "kind": "obstacle", "maps_from": [5]},
        ]
    }
    with pytest.raises(ClassTableError, match="two classes"):
        ClassTable.from_dict(data)


# -- SemanticKITTI / RELLIS-3D ----------------------------------------------------------------


def test_semantickitti_reads_points_labels_and_lidar_poses(tmp_path):
    seq, poses, pts, labs = make_kitti(tmp_path / "sequences" / "08")
    assert detect_format(tmp_path) == "semantickitti"
    reader = open_dataset(tmp_path, sequence="08")
    assert len(reader) == 3 and reader.skipped == [] and reader.rate_hz == pytest.approx(10)
    for k, scan in enumerate(reader):
        np.testing.assert_array_equal(scan.points, pts[k])
        np.testing.assert_array_equal(scan.labels, labs[k])  # instance bits stripped
        np.testing.assert_allclose(scan.pose, poses[k], atol=1e-9)
        assert scan.stamp_s == pytest.approx(k / 10)
    assert open_dataset(seq).scan(2).name == "000002.bin"  # the sequence folder itself


def test_semantickitti_times_txt_sets_stamps(tmp_path):
    seq, *_ = make_kitti(tmp_path)
    (seq / "times.txt").write_text("0.0\n0.2\n0.4\n")
    reader = open_dataset(seq)
    assert [s.stamp_s for s in reader] == [0.0, 0.2, 0.4]
    assert reader.rate_hz == pytest.approx(5.0)


def test_rellis_layout_is_detected_under_its_root(tmp_path):
    make_kitti(
        tmp_path / "Rellis-3D" / "00003",
        cloud_dir="os1_cloud_node_kitti_bin",
        label_dir="os1_cloud_node_semantickitti_label_id",
    )
    assert detect_format(tmp_path) == "rellis3d"
    reader = open_dataset(tmp_path)
    assert reader.format == "rellis3d" and len(reader) == 3
    assert reader.default_class_table == "rellis3d"


def test_rellis_without_calib_takes_poses_as_lidar_poses(tmp_path):
    seq, poses, *_ = make_kitti(
        tmp_path,
        cloud_dir="os1_cloud_node_kitti_bin",
        label_dir="os1_cloud_node_semantickitti_label_id",
    )
    (seq / "calib.txt").unlink()
    (seq / "poses.txt").write_text("".join(row(m) + "\n" for m in poses))
    reader = open_dataset(seq, "rellis3d")
    np.testing.assert_allclose(reader.scan(1).pose, poses[1], atol=1e-9)


def test_missing_label_file_skips_the_scan(tmp_path):
    seq, *_ = make_kitti(tmp_path)
    (seq / "labels" / "000001.label").unlink()
    reader = open_dataset(seq)
    assert [s.name for s in reader] == ["000000.bin", "000002.bin"]
    assert len(reader.skipped) == 1
    assert "000001.bin" in reader.skipped[0].name
    assert (
        "no label file" in reader.skipped[0].reason and "000001.label" in reader.skipped[0].reason
    )
    np.testing.assert_allclose(reader.scan(1).pose[:3, 3], [1.0, 0.4, 0.1], atol=1e-9)
    with pytest.raises(DatasetError, match="no label file"):
        open_dataset(seq, strict=True)


def test_truncated_scan_and_label_count_mismatch_are_skipped(tmp_path):
    seq, *_ = make_kitti(tmp_path, n=4)
    with (seq / "velodyne" / "000000.bin").open("ab") as f:
        f.write(b"\0" * 6)
    (seq / "labels" / "000002.label").write_bytes(b"\0" * 40)
    reader = open_dataset(seq)
    reasons = {s.name.split("/")[-1]: s.reason for s in reader.skipped}
    assert "not a multiple of 16" in reasons["000000.bin"]
    assert "10 labels for 500 points" in reasons["000002.bin"]
    assert [s.name for s in reader] == ["000001.bin", "000003.bin"]


def test_pose_count_mismatch_is_an_error(tmp_path):
    seq, *_ = make_kitti(tmp_path)
    lines = (seq / "poses.txt").read_text().splitlines()
    (seq / "poses.txt").write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(DatasetError, match=r"poses\.txt: 2 poses for 3 scans"):
        open_dataset(seq)


@pytest.mark.parametrize(
    "content, match",
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", "line 1: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 x 0\n", "line 1: not a list of numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n", "non-finite"),
        ("", "empty"),
    ],
)
def test_malformed_pose_file_names_the_line(tmp_path, content, match):
    seq, *_ = make_kitti(tmp_path, n=1)
    (seq / "poses.txt").write_text(content)
    with pytest.raises(DatasetError, match=match) as exc:
        open_dataset(seq)
    assert "poses.txt" in str(exc.value)


def test_non_rigid_pose_is_an_error(tmp_path):
    seq, *_ = make_kitti(tmp_path, n=1)
    (seq / "poses.txt").write_text("2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="not a rigid transform"):
        open_dataset(seq)


def test_calibration_problems(tmp_path):
    seq, *_ = make_kitti(tmp_path / "a")
    (seq / "calib.txt").write_text(f"P0: {row(np.eye(4))}\n")
    with pytest.raises(DatasetError, match="no 'Tr'"):
        open_dataset(seq)
    (seq / "calib.txt").unlink()
    with pytest.raises(DatasetError, match="calib.txt: calibration file is missing"):
        open_dataset(seq)
    (seq / "calib.txt").write_text("Tr 1 2 3\n")
    with pytest.raises(DatasetError, match="KEY: 12 numbers"):
        open_dataset(seq)


def test_layout_problems(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        open_dataset(tmp_path / "nope", "semantickitti")
    make_kitti(tmp_path / "sequences" / "00")
    make_kitti(tmp_path / "sequences" / "01")
    with pytest.raises(DatasetError, match="several sequences, name one: 00, 01"):
        open_dataset(tmp_path)
    with pytest.raises(DatasetError, match="not a semantickitti sequence"):
        open_dataset(tmp_path, sequence="07")
    shutil.rmtree(tmp_path / "sequences" / "00" / "labels")
    with pytest.raises(DatasetError, match="label folder is missing"):
        open_dataset(tmp_path, sequence="00")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="cannot tell the dataset format"):
        detect_format(tmp_path / "empty")
    with pytest.raises(ValueError, match="labels come from .label files; only 'none' applies"):
        open_dataset(tmp_path, sequence="01", label_field="class")


def test_gap_in_scan_numbering_is_an_error(tmp_path):
    seq, *_ = make_kitti(tmp_path)
    (seq / "velodyne" / "000001.bin").rename(seq / "velodyne" / "000007.bin")
    with pytest.raises(DatasetError, match="expected 000001.bin"):
        open_dataset(seq)


def test_every_scan_skipped_is_an_error(tmp_path):
    seq, *_ = make_kitti(tmp_path, n=2)
    for f in (seq / "labels").iterdir():
        f.unlink()
    with pytest.raises(DatasetError, match="every scan was skipped"):
        open_dataset(seq)


# -- folder of PLY / NPZ ----------------------------------------------------------------------


def make_npz_folder(root, n=3, n_points=200, with_pose_file=True, tum=False):
    rng = np.random.default_rng(1)
    root.mkdir(parents=True, exist_ok=True)
    poses = [pose_xyz_yaw(k, -k, 0.5, 0.2 * k) for k in range(n)]
    data = []
    for k in range(n):
        p = rng.normal(size=(n_points, 3)).astype(np.float32)
        lab = rng.integers(0, 9, n_points).astype(np.uint8)
        conf = rng.uniform(0.3, 1, n_points).astype(np.float32)
        np.savez(root / f"scan_{k:03d}.npz", points=p, labels=lab, confidences=conf)
        data.append((p, lab, conf))
    if with_pose_file:
        if tum:
            from smana.common.messages import matrix_to_quat

            lines = [
                f"{0.25 * k} {m[0, 3]} {m[1, 3]} {m[2, 3]} "
                + " ".join(map(str, matrix_to_quat(m[:3, :3])))
                for k, m in enumerate(poses)
            ]
            (root / "poses.txt").write_text("# t x y z qx qy qz qw\n" + "\n".join(lines) + "\n")
        else:
            (root / "poses.txt").write_text("".join(row(m) + "\n" for m in poses))
    return np.array(poses), data


@pytest.mark.parametrize("tum", [False, True])
def test_npz_folder_with_pose_file(tmp_path, tum):
    poses, data = make_npz_folder(tmp_path, tum=tum)
    assert detect_format(tmp_path) == "folder"
    reader = open_dataset(tmp_path)
    assert len(reader) == 3
    for k, scan in enumerate(reader):
        np.testing.assert_array_equal(scan.points, data[k][0])
        np.testing.assert_array_equal(scan.labels, data[k][1])
        np.testing.assert_array_equal(scan.confidences, data[k][2])
        np.testing.assert_allclose(scan.pose, poses[k], atol=1e-9)
    if tum:
        assert reader.scan(2).stamp_s == 0.5 and reader.rate_hz == pytest.approx(4.0)


def test_npz_carrying_its_own_pose(tmp_path):
    m = pose_xyz_yaw(1, 2, 3, 0.4)
    np.savez(tmp_path / "a.npz", points=np.zeros((5, 3)), labels=np.arange(5), pose=m, stamp_s=12.5)
    scan = open_dataset(tmp_path).scan(0)
    np.testing.assert_allclose(scan.pose, m)
    assert scan.stamp_s == 12.5


@pytest.mark.parametrize(
    "arrays, reason",
    [
        ({"points": np.zeros((4, 3))}, "needs 'points' and 'labels'"),
        ({"points": np.zeros((4, 2)), "labels": np.zeros(4, int)}, "expected (N, 3)"),
        ({"points": np.zeros((4, 3)), "labels": np.zeros(3, int)}, "shape (3,) for 4 points"),
        ({"points": np.zeros((4, 3)), "labels": np.zeros(4)}, "expected integers"),
    ],
)
def test_malformed_npz_is_skipped_with_its_reason(tmp_path, arrays, reason):
    make_npz_folder(tmp_path, n=2, with_pose_file=False)
    np.savez(tmp_path / "scan_bad.npz", pose=np.eye(4), **arrays)
    for f in ("scan_000.npz", "scan_001.npz"):  # give the good ones a pose of their own
        d = dict(np.load(tmp_path / f))
        np.savez(tmp_path / f, pose=np.eye(4), **d)
    reader = open_dataset(tmp_path)
    assert len(reader) == 2
    assert reader.skipped[0].name.endswith("scan_bad.npz")
    assert reason in reader.skipped[0].reason


def test_npz_without_any_pose_is_skipped(tmp_path):
    make_npz_folder(tmp_path, n=2, with_pose_file=False)
    with pytest.raises(DatasetError, match="every scan was skipped: no pose"):
        open_dataset(tmp_path)


def test_corrupt_npz_is_skipped(tmp_path):
    make_npz_folder(tmp_path, n=2)
    (tmp_path / "scan_001.npz").write_bytes(b"not a zip")
    reader = open_dataset(tmp_path)
    assert len(reader) == 1 and "not a readable NPZ" in reader.skipped[0].reason


@pytest.mark.parametrize("binary", [True, False])
def test_ply_folder(tmp_path, binary):
    rng = np.random.default_rng(2)
    poses = [pose_xyz_yaw(k, 0, 0, 0.1) for k in range(2)]
    data = []
    for k in range(2):
        p = rng.normal(size=(50, 3)).astype(np.float32)
        lab = rng.integers(0, 9, 50)
        conf = rng.random(50).astype(np.float32)
        write_ply(tmp_path / f"{k}.ply", p, lab, conf, binary=binary)
        data.append((p, lab, conf))
    (tmp_path / "poses.txt").write_text("".join(row(m) + "\n" for m in poses))
    reader = open_dataset(tmp_path)
    for k, scan in enumerate(reader):
        np.testing.assert_allclose(scan.points, data[k][0], rtol=1e-6)
        np.testing.assert_array_equal(scan.labels, data[k][1])
        np.testing.assert_allclose(scan.confidences, data[k][2], rtol=1e-6)
        np.testing.assert_allclose(scan.pose, poses[k])


def test_ply_problems(tmp_path):
    write_ply(tmp_path / "0.ply", np.zeros((10, 3)), np.zeros(10, int))
    with pytest.raises(DatasetError, match=r"poses.txt: missing \(PLY scans carry no pose\)"):
        open_dataset(tmp_path)
    (tmp_path / "poses.txt").write_text((row(np.eye(4)) + "\n") * 4)
    # no label property
    (tmp_path / "1.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
        b"property float y\nproperty float z\nproperty uchar class\nend_header\n" + b"\0" * 26
    )
    # truncated
    good = (tmp_path / "0.ply").read_bytes()
    (tmp_path / "2.ply").write_bytes(good[:-7])
    (tmp_path / "3.ply").write_bytes(b"solid cube\n")
    reader = open_dataset(tmp_path)
    reasons = {s.name.split("/")[-1]: s.reason for s in reader.skipped}
    assert len(reader) == 1
    assert reasons["1.ply"] == (
        "integer vertex property 'label' missing (properties: x, y, z, class); "
        "--label-field none labels the points by geometry"
    )
    assert "truncated" in reasons["2.ply"]
    assert "no 'ply' magic" in reasons["3.ply"]
    # the label property can be named
    assert len(open_dataset(tmp_path, label_field="class")) == 1


def test_folder_problems(tmp_path):
    make_npz_folder(tmp_path, n=3)
    (tmp_path / "poses.txt").write_text("0 1 2 3 4\n")
    with pytest.raises(DatasetError, match="5 columns: expected 12"):
        open_dataset(tmp_path)
    make_npz_folder(tmp_path / "b", n=3)
    lines = (tmp_path / "b" / "poses.txt").read_text().splitlines()
    (tmp_path / "b" / "poses.txt").write_text(lines[0] + "\n")
    with pytest.raises(DatasetError, match="1 poses for 3 scans"):
        open_dataset(tmp_path / "b")
    write_ply(tmp_path / "b" / "x.ply", np.zeros((1, 3)), np.zeros(1, int))
    with pytest.raises(DatasetError, match="both .ply and .npz"):
        open_dataset(tmp_path / "b")
