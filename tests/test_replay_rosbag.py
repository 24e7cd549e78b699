"""ROS bag reader on bags written here with `rosbags`: ROS 1, ROS 2 (sqlite3 and MCAP storage)
and a bare MCAP file; label fields of several integer types; odometry interpolation; errors."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from smana.common.messages import matrix_to_quat, quat_to_matrix  # noqa: E402
from smana.common.ros import PoseTrack  # noqa: E402
from smana.services.replay.readers import DatasetError, detect_format, open_dataset  # noqa: E402

TS1 = get_typestore(Stores.ROS1_NOETIC)
TS2 = get_typestore(Stores.ROS2_HUMBLE)
N_SCANS, N_POINTS = 4, 300
FIELD_CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def odom_pose(t):
    """The ground-truth trajectory the odometry samples: x = t, yaw = 0.5 t."""
    yaw = 0.5 * t
    m = np.eye(4)
    m[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    m[:3, 3] = t, 0.2 * t, 0.3
    return m


def stamp(ts, t):
    return ts.types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))


def header(ts, t, frame, ros1):
    h = ts.types["std_msgs/msg/Header"]
    if ros1:
        return h(seq=0, stamp=stamp(ts, t), frame_id=frame)
    return h(stamp=stamp(ts, t), frame_id=frame)


def make_cloud(
    ts,
    t,
    points,
    labels,
    label_field="label",
    label_dtype="u2",
    extra_pad=0,
    frame="os1",
    ros1=False,
    big_endian=False,
    conf=None,
):
    """A PointCloud2 with x, y, z (f4), intensity, the label field, padding at row ends."""
    order = ">" if big_endian else "<"
    names = ["x", "y", "z", "intensity", label_field]
    formats = ["f4", "f4", "f4", "f4", label_dtype]
    if conf is not None:
        names.append("confidence")
        formats.append("f4")
    dt = np.dtype({"names": names, "formats": [order + f for f in formats]})
    arr = np.zeros(len(points), dt)
    arr["x"], arr["y"], arr["z"] = points.T
    arr[label_field] = labels
    if conf is not None:
        arr["confidence"] = conf
    height = 2
    width = len(points) // height
    row = width * dt.itemsize + extra_pad
    data = np.zeros(height * row, np.uint8)
    raw = arr.tobytes()
    for r in range(height):
        chunk = raw[r * width * dt.itemsize : (r + 1) * width * dt.itemsize]
        data[r * row : r * row + len(chunk)] = np.frombuffer(chunk, np.uint8)
    pf = ts.types["sensor_msgs/msg/PointField"]
    fields = [
        pf(name=n, offset=dt.fields[n][1], datatype=FIELD_CODES[f], count=1)
        for n, f in zip(names, formats, strict=True)
    ]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=header(ts, t, frame, ros1),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=dt.itemsize,
        row_step=row,
        data=data,
        is_dense=True,
    )


def make_odom(ts, t, ros1=False):
    m = odom_pose(t)
    q = matrix_to_quat(m[:3, :3])
    g = ts.types
    pose = g["geometry_msgs/msg/Pose"](
        position=g["geometry_msgs/msg/Point"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
        orientation=g["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    twist = g["geometry_msgs/msg/Twist"](
        linear=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return g["nav_msgs/msg/Odometry"](
        header=header(ts, t, "odom", ros1),
        child_frame_id="base_link",
        pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=g["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def scan_data(seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(N_SCANS):
        pts = rng.uniform(-8, 8, (N_POINTS, 3)).astype(np.float32)
        labels = rng.integers(0, 35, N_POINTS)
        out.append((1.05 + 0.1 * k, pts, labels))  # cloud stamps between odometry samples
    return out


def write_bag(path, kind, scans, cloud_kw=None, odom=True, extra_topics=()):
    """kind: ros1 | sqlite3 | mcap. Odometry at 20 Hz over [0, 2] s."""
    ros1 = kind == "ros1"
    ts = TS1 if ros1 else TS2
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        cloud_t = "sensor_msgs/msg/PointCloud2"
        c_cloud = writer.add_connection("/os1/points", cloud_t, typestore=ts)
        extra = [writer.add_connection(n, cloud_t, typestore=ts) for n in extra_topics]
        msgs = []
        if odom:
            c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
            for t in np.arange(0, 2.0001, 0.05):
                msgs.append((t, c_odom, ser(make_odom(ts, t, ros1), "nav_msgs/msg/Odometry")))
        for t, pts, labels in scans:
            msg = make_cloud(ts, t, pts, labels, ros1=ros1, **(cloud_kw or {}))
            msgs.append((t, c_cloud, ser(msg, cloud_t)))
            for c in extra:
                msgs.append((t, c, ser(msg, cloud_t)))
        for t, conn, raw in sorted(msgs, key=lambda m: m[0]):
            writer.write(conn, int(t * 1e9), raw)
    return path


BAG_PATHS = {"ros1": "run.bag", "sqlite3": "run_sqlite", "mcap": "run_mcap"}


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_bag_scans_and_interpolated_odometry(tmp_path, kind):
    scans = scan_data()
    path = write_bag(tmp_path / BAG_PATHS[kind], kind, scans)
    assert detect_format(path) == "rosbag"
    with open_dataset(path) as reader:
        assert len(reader) == N_SCANS and reader.skipped == []
        assert reader.rate_hz == pytest.approx(10.0)
        for k, scan in enumerate(reader):
            t, pts, labels = scans[k]
            assert scan.stamp_s == pytest.approx(t)
            np.testing.assert_array_equal(scan.points, pts)
            np.testing.assert_array_equal(scan.labels, labels)
            # Linear interpolation of a constant-rate trajectory: exact up to float error.
            np.testing.assert_allclose(scan.pose, odom_pose(t), atol=1e-6)
        # Random access, including going backwards.
        np.testing.assert_array_equal(reader.scan(2).points, scans[2][1])
        np.testing.assert_array_equal(reader.scan(0).points, scans[0][1])


def test_bare_mcap_file(tmp_path):
    scans = scan_data()
    folder = write_bag(tmp_path / "bag", "mcap", scans)
    mcap = next(folder.glob("*.mcap"))
    bare = mcap.rename(tmp_path / "recording.mcap")
    with open_dataset(bare) as reader:
        assert len(reader) == N_SCANS
        np.testing.assert_array_equal(reader.scan(1).labels, scans[1][2])
        np.testing.assert_allclose(reader.scan(1).pose, odom_pose(scans[1][0]), atol=1e-6)


@pytest.mark.parametrize("dtype", ["u1", "i2", "u4", "i4"])
def test_label_field_of_any_integer_type_and_name(tmp_path, dtype):
    scans = [(t, p, lab % 100) for t, p, lab in scan_data()]
    kw = {"label_field": "semantic", "label_dtype": dtype, "extra_pad": 8, "big_endian": True}
    path = write_bag(tmp_path / "b.bag", "ros1", scans, cloud_kw=kw)
    with open_dataset(path, label_field="semantic") as reader:
        for k, scan in enumerate(reader):
            np.testing.assert_array_equal(scan.labels, scans[k][2])
            np.testing.assert_array_equal(scan.points, scans[k][1])


def test_confidence_field_is_used(tmp_path):
    scans = scan_data()
    conf = np.linspace(0.3, 1.0, N_POINTS).astype(np.float32)
    path = write_bag(tmp_path / "b.bag", "ros1", scans, cloud_kw={"conf": conf})
    with open_dataset(path) as reader:
        np.testing.assert_array_equal(reader.scan(0).confidences, conf)


def test_fixed_pose_without_odometry(tmp_path):
    path = write_bag(tmp_path / "b.bag", "ros1", scan_data(), odom=False)
    with pytest.raises(DatasetError, match="no nav_msgs/Odometry topic: give a fixed pose"):
        open_dataset(path)
    with open_dataset(path, fixed_pose=(1.0, 2.0, 0.5, np.pi / 2)) as reader:
        pose = reader.scan(3).pose
        np.testing.assert_allclose(pose[:3, 3], [1, 2, 0.5])
        np.testing.assert_allclose(pose[:3, 0], [0, 1, 0], atol=1e-12)


def test_world_frame_cloud_is_brought_back_to_the_sensor_frame(tmp_path):
    scans = scan_data()
    world_scans = []
    for t, pts, lab in scans:
        m = odom_pose(t)
        world_scans.append((t, (pts @ m[:3, :3].T + m[:3, 3]).astype(np.float32), lab))
    path = write_bag(tmp_path / "b.bag", "ros1", world_scans, cloud_kw={"frame": "odom"})
    with open_dataset(path) as reader:
        np.testing.assert_allclose(reader.scan(1).points, scans[1][1], atol=1e-4)


def test_missing_label_field_names_the_fields(tmp_path):
    path = write_bag(tmp_path / "b.bag", "ros1", scan_data())
    with pytest.raises(DatasetError) as exc:
        open_dataset(path, label_field="class")
    msg = str(exc.value)
    assert "label field 'class' missing from the PointCloud2" in msg
    assert "x, y, z, intensity, label" in msg and "b.bag" in msg


def test_scans_outside_the_odometry_span_are_skipped(tmp_path):
    scans = scan_data() + [(3.0, np.zeros((10, 3), np.float32), np.zeros(10, int))]
    path = write_bag(tmp_path / "b.bag", "ros1", scans)
    with open_dataset(path) as reader:
        assert len(reader) == N_SCANS
        assert reader.skipped[0].name == "/os1/points#4"
        assert "no odometry within 0.2 s of stamp 3.000" in reader.skipped[0].reason


def test_topic_choice_errors(tmp_path):
    path = write_bag(tmp_path / "b.bag", "ros1", scan_data(), extra_topics=["/other/points"])
    with pytest.raises(DatasetError, match="several PointCloud2 topics, name one: /os1/points"):
        open_dataset(path)
    with pytest.raises(DatasetError, match=r"no topic '/nope' \(topics: "):
        open_dataset(path, cloud_topic="/nope")
    with pytest.raises(DatasetError, match="topic '/odom' is nav_msgs/msg/Odometry, expected"):
        open_dataset(path, cloud_topic="/odom")
    with open_dataset(path, cloud_topic="/other/points") as reader:
        assert len(reader) == N_SCANS


def test_not_a_bag(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="cannot open bag"):
        open_dataset(tmp_path / "x.bag")
    (tmp_path / "y.mcap").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="cannot open bag"):
        open_dataset(tmp_path / "y.mcap")


def test_pose_track_slerp_matches_constant_rate_rotation():
    stamps = np.array([0.0, 1.0])
    yaws = np.array([0.0, 1.2])
    quats = np.stack([[0, 0, np.sin(y / 2), np.cos(y / 2)] for y in yaws])
    track = PoseTrack(stamps, np.zeros((2, 3)), quats)
    assert track.at(0.25, max_gap_s=0.1) is None  # 1 s between samples: a hole in the odometry
    m = track.at(0.25, max_gap_s=0.6)
    np.testing.assert_allclose(
        m[:3, :3], quat_to_matrix(np.array([0, 0, np.sin(0.15), np.cos(0.15)]))
    )
    assert track.at(1.5, max_gap_s=0.4) is None
