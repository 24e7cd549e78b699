"""The ros2 service's parts without processes: the rmw_zenoh mapping against zenoh-ros2-sdk (an
rmw_zenoh client written elsewhere) and zenoh-ext, the map copy against a dict, the costmap
values, and placing a robot's cloud in the world."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.common.messages import MapDelta  # noqa: E402
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE  # noqa: E402
from smana.common.service import Reject  # noqa: E402
from smana.services.ros2 import convert, rmw  # noqa: E402
from smana.services.ros2.bridge import CloudInput, MapCopy  # noqa: E402
from tests.support.ros2_sdk import (  # noqa: E402
    GET_PLAN_SRV,
    MESSAGE_TYPES,
    pointcloud2,
    sdk_session,
)

TYPES = rmw.RosTypes()


@pytest.fixture
def sdk(tmp_path, monkeypatch):
    pytest.importorskip("zenoh_ros2_sdk")
    with sdk_session(tmp_path, monkeypatch):
        from zenoh_ros2_sdk import get_registry

        yield get_registry()


def test_type_hashes_agree_with_the_sdk(sdk):
    from zenoh_ros2_sdk.utils import (
        compute_service_type_hash,
        get_type_hash,
        load_dependencies_recursive,
    )

    event_info = "service_msgs/msg/ServiceEventInfo"
    for t in [*MESSAGE_TYPES, "geometry_msgs/msg/Quaternion"]:
        if t == event_info:  # its `char[16]`: see below
            continue
        text = sdk.get_msg_file_path(t).read_text()
        deps = load_dependencies_recursive(t, text, sdk)
        assert get_type_hash(t, msg_definition=text, dependencies=deps) == TYPES.hash(t), t
    # Known values (ROS 2 Jazzy's) anchor both implementations. ServiceEventInfo's `char[16]`
    # is uint8 to rosidl (and to the SDK's own service hashing), not a char: read as rosidl
    # reads it, its hash is Jazzy's, and GetPlan's below agrees with the SDK.
    assert TYPES.hash("geometry_msgs/msg/Quaternion").startswith("RIHS01_8a765f66778c8ff7")
    assert TYPES.hash(event_info).startswith("RIHS01_41bcbbe07a75c9b52bc96bfd5c24d7f0")
    request, response = GET_PLAN_SRV.split("---\n")
    deps = {}
    for part, text in (("Request", request), ("Response", response)):
        deps.update(load_dependencies_recursive(f"nav_msgs/srv/GetPlan_{part}", text, sdk))
    srv = compute_service_type_hash("nav_msgs/srv/GetPlan", request, response, deps)
    assert srv == TYPES.hash("nav_msgs/srv/GetPlan")


def test_keys_tokens_and_qos_agree_with_the_sdk():
    pytest.importorskip("zenoh_ros2_sdk")
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import (
        endpoint_liveliness_keyexpr,
        node_liveliness_keyexpr,
        topic_keyexpr,
    )
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    t = "nav_msgs/msg/OccupancyGrid"
    h = TYPES.hash(t)
    assert rmw.dds_type_name(t) == ros2_to_dds_type(t)
    assert rmw.data_key(3, "/smana/r1/costmap", t, h) == topic_keyexpr(
        3, "/smana/r1/costmap", ros2_to_dds_type(t), h
    )

    class Session:  # what RosNode reads of a zenoh session
        def zid(self):
            return "0123abcd"

        def liveliness(self):
            return self

        def declare_token(self, key):
            tokens.append(key)
            return self

    tokens: list[str] = []
    node = rmw.RosNode(Session(), TYPES, 3, "smana", "/smana/r1")
    key, eid = node.endpoint(rmw.PUBLISHER, "/smana/r1/costmap", t, rmw.LATCHED_QOS)
    theirs = NodeEntity(3, "0123abcd", 0, "smana", "/smana/r1")
    assert tokens[0] == node_liveliness_keyexpr(theirs)
    qos = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
    ep = EndpointEntity(
        theirs,
        eid,
        EntityKind.PUBLISHER,
        "/smana/r1/costmap",
        rmw.dds_type_name(t),
        h,
        qos.encode(),
    )
    assert tokens[1] == endpoint_liveliness_keyexpr(ep)
    decoded = QosProfile.decode(rmw.SENSOR_QOS.token())
    assert decoded.reliability == QosReliability.BEST_EFFORT and decoded.history_depth == 5
    assert QosProfile.decode(rmw.QoS().token()) == QosProfile()


def test_attachment_is_rmw_zenohs():
    from zenoh import ext

    gid = bytes(range(16))
    ours = rmw.attachment(7, 123456789, gid)
    assert ours == ext.z_serialize((ext.Int64(7), ext.Int64(123456789), gid)).to_bytes()
    try:
        from zenoh_ros2_sdk.attachment import Attachment

        assert ours == Attachment(sequence_id=7, timestamp_ns=123456789, gid=gid).to_bytes()
    except ImportError:
        pass
    assert rmw.parse_attachment(ours) == (7, 123456789, gid)
    for bad in (None, b"", ours[:-1], ours + b"\0", ours[:16] + b"\x0f" + gid):
        with pytest.raises(ValueError):
            rmw.parse_attachment(bad)


def test_the_attachment_of_rmw_zenoh_before_its_compact_format_is_refused():
    """rmw_zenoh_cpp before 0.2.4 (Jazzy), 0.1.2 (Humble) and 0.6.0 (Rolling) named each field
    in the attachment ("sequence_number", int64, "source_timestamp", int64, "source_gid", the
    gid), in zenoh-ext's serialisation; smana reads the compact form only, and a GetPlan with the
    named one is refused `malformed`."""
    from types import SimpleNamespace

    from zenoh import ext

    from smana.common.config import SmanaConfig
    from smana.common.service_queries import Request
    from smana.services.ros2.service import Ros2Service

    gid = bytes(range(16))
    named = ext.z_serialize(
        ("sequence_number", ext.Int64(7), "source_timestamp", ext.Int64(9), "source_gid", gid)
    ).to_bytes()
    assert named.startswith(b"\x0fsequence_number") and named.endswith(b"\x10" + gid)
    with pytest.raises(ValueError, match="not an rmw_zenoh attachment"):
        rmw.parse_attachment(named)
    svc = Ros2Service(SmanaConfig.load())
    svc.types = TYPES
    svc.node = SimpleNamespace(reply_attachment=lambda a: rmw.RosNode.reply_attachment(None, a))
    with pytest.raises(Reject) as e:
        svc.on_plan(Request("plan", {}, b"", False, named))
    assert e.value.kind == "malformed" and "not an rmw_zenoh attachment" in str(e.value)


def _delta(rng, seq, res=0.1):
    n = int(rng.integers(0, 60))
    idx = rng.integers(-8, 8, size=(n, 3))
    idx = np.unique(idx, axis=0)  # one voxel at most once per delta
    return MapDelta(
        seq=seq,
        resolution_m=res,
        centres=((idx + 0.5) * res).astype(np.float32),
        labels=rng.integers(0, 9, len(idx)).astype(np.uint16),
        confidences=np.ones(len(idx), np.float32),
        occupied=rng.integers(0, 2, len(idx)).astype(np.uint8),
        values=np.zeros(len(idx), np.float32),
    )


def test_map_copy_matches_a_dict():
    rng = np.random.default_rng(3)
    copy, ref = MapCopy(), {}
    for seq in range(1, 80):
        d = _delta(rng, seq)
        copy.apply(d)
        for c, lab, occ in zip(d.centres, d.labels, d.occupied, strict=True):
            k = tuple(np.floor(c / 0.1).astype(int))
            if occ:
                ref[k] = int(lab)
            else:
                ref.pop(k, None)
        got = {
            tuple(np.floor(c / 0.1).astype(int)): int(lab)
            for c, lab in zip(copy.centres, copy.labels, strict=True)
        }
        assert got == ref
    snap = _delta(rng, 99)
    copy.reset(snap)
    assert len(copy) == int(snap.occupied.sum())  # a snapshot replaces what was there


def test_costmap_values():
    cost_lut = np.array([np.inf, 2.0, 1.0, np.inf, np.inf])  # unknown, grass, terrain, -, hedge
    labels = np.array([2, 1, 2, 4, 1, 0])
    flags = np.array([1, 1, 0, 1, 1 | FLAG_SAFETY_ZONE, 1 | FLAG_OBSTACLE], np.uint8)
    flags[0] = FLAG_KNOWN
    got = convert.costmap_values(labels, flags, cost_lut)
    assert got.tolist() == [0, 98, -1, 100, 100, 100]


class _Cfg:
    def __init__(self, **kw):
        from smana.common.config import Ros2Config

        self.ros2 = Ros2Config(**kw)


def _ros_cloud(points, labels, frame, t_s):
    return pointcloud2(TYPES, points, labels, frame, t_s)


def _tf(parent, child, xyz, yaw):
    T = TYPES.msg
    q = convert.yaw_quat(yaw)
    return T("geometry_msgs/msg/TransformStamped")(
        header=convert.header(TYPES, 0.0, parent),
        child_frame_id=child,
        transform=T("geometry_msgs/msg/Transform")(
            translation=T("geometry_msgs/msg/Vector3")(x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=T("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )


def test_cloud_input_places_a_sensor_frame_cloud():
    ci = CloudInput(_Cfg(min_range_m=0.0), labeller=None)
    pts = np.array([[1.0, 0.0, 0.0], [2.0, 1.0, -0.5], [0.5, -1.0, 0.2]], np.float32)
    msg = _ros_cloud(pts, [2, 4, 2], "lidar", 10.05)
    with pytest.raises(Reject) as e:
        ci.convert(msg)
    assert e.value.kind == "no_pose"
    # The robot drives along x at 1 m/s, turned 90 degrees; odometry at 10.0 and 10.1 s.
    q = np.array(convert.yaw_quat(math.pi / 2))
    ci.poses.add(10.0, np.array([1.0, 0.0, 0.0]), q)
    ci.poses.add(10.1, np.array([1.1, 0.0, 0.0]), q)
    with pytest.raises(Reject) as e:
        ci.convert(msg)
    assert e.value.kind == "no_transform"
    # lidar on base_link via a mount: base_link -> mount (z 0.4) -> lidar (x 0.2, yawed 90 deg)
    tfm = TYPES.msg("tf2_msgs/msg/TFMessage")(
        transforms=[
            _tf("base_link", "mount", (0.0, 0.0, 0.4), 0.0),
            _tf("mount", "lidar", (0.2, 0.0, 0.0), math.pi / 2),
        ]
    )
    assert ci.add_static(tfm) == 2
    cloud = ci.convert(msg)
    base = convert.matrix([1.05, 0.0, 0.0], q)
    on_robot = convert.chain(ci.static, "base_link", "lidar")
    want = (base @ on_robot @ np.c_[pts, np.ones(3)].T).T[:, :3]
    np.testing.assert_allclose(cloud.points, want, atol=1e-5)
    np.testing.assert_allclose(cloud.sensor_position, (base @ on_robot)[:3, 3], atol=1e-9)
    assert cloud.labels.tolist() == [2, 4, 2] and cloud.source == "lidar"
    # A cloud already in the world frame is used as it is.
    world = ci.convert(_ros_cloud(pts, [2, 4, 2], "odom", 10.05))
    np.testing.assert_allclose(world.points, pts)
    # No label field: refused, and the message says how to map it anyway.
    bare = _ros_cloud(pts, [0, 0, 0], "odom", 10.05)
    bare.fields = bare.fields[:3]
    with pytest.raises(Reject, match="label_field=none"):
        ci.convert(bare)


def test_configured_extrinsic_and_range_limits():
    ci = CloudInput(_Cfg(sensor_extrinsic=[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], max_range_m=2.0), None)
    ci.poses.add(0.4, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    ci.poses.add(0.6, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    pts = np.array([[1.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.1, 0.0, 0.0]], np.float32)
    cloud = ci.convert(_ros_cloud(pts, [2, 2, 2], "velodyne", 0.5))
    np.testing.assert_allclose(cloud.points, [[1.0, 0.0, 1.0]])  # too far and too near dropped


def test_simulated_robot_frames_chain_to_the_pose():
    from smana.common.messages import Pose

    pose = Pose.from_xyz_yaw(1.5, -2.0, 0.1, 0.7, stamp_s=12.5)
    tfm = convert.robot_frames(TYPES, pose)
    ci = CloudInput(_Cfg(), None)
    assert ci.add_static(tfm) == 2  # the same reader the robot's /tf_static goes through
    np.testing.assert_allclose(
        convert.chain(ci.static, "map", "base_link"), pose.matrix(), atol=1e-12
    )
    raw = TYPES.serialize(tfm, "tf2_msgs/msg/TFMessage")
    assert TYPES.deserialize(raw, "tf2_msgs/msg/TFMessage").transforms[1].header.stamp.sec == 12
