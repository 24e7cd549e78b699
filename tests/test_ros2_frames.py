"""The frame names the ros2 service publishes and accepts (`Ros2Config.frames`): the prefix that
keeps robots' tf trees apart on one /tf, its validation and its "auto" rule, the tf topic's; every
frame smana stamps carries it (in process, on a recording publisher); and two ros2 processes of
a fleet publish two disjoint trees on one /tf, read by a ROS 2 subscriber of zenoh-ros2-sdk."""

from __future__ import annotations

import threading

import msgpack
import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.common import keys  # noqa: E402
from smana.common.config import ConfigError, Ros2Config, SmanaConfig  # noqa: E402
from smana.common.messages import Pose, encode  # noqa: E402
from smana.common.query import request  # noqa: E402
from tests.conftest import wait_for  # noqa: E402

FLEET = 'fleet.robots=["r1", "r2"]'


def test_frames_are_plain_for_one_robot_and_prefixed_in_a_simulated_fleet():
    rc = Ros2Config()
    alone = rc.frames("r1")
    assert (alone.prefix, alone.map, alone.odom, alone.base) == ("", "map", "odom", "base_link")
    assert alone.world == ("map", "odom")
    assert rc.frames("r1", ["r1"]).prefix == ""  # a fleet of one shares no /tf
    fleet = rc.frames("r2", ["r1", "r2"])
    assert (fleet.map, fleet.odom, fleet.base) == ("r2/map", "r2/odom", "r2/base_link")
    assert fleet.world == ("r2/map", "r2/odom")
    # A real robot's frames are the robot's: "auto" adds nothing, even in a fleet...
    assert rc.frames("r2", ["r1", "r2"], robot_input=True).prefix == ""
    # ...and a prefix the user sets applies everywhere, to every name the config gives.
    rc = Ros2Config(frame_prefix="bot_a/", base_frame="chassis", world_frames=["odom"])
    for robot_input in (False, True):
        f = rc.frames("r1", robot_input=robot_input)
        assert (f.map, f.odom, f.base, f.world) == (
            "bot_a/map",
            "bot_a/odom",
            "bot_a/chassis",
            ("bot_a/odom",),
        )
    assert Ros2Config(frame_prefix="").frames("r1", ["r1", "r2"]).prefix == ""


def test_the_config_decides_from_its_robots_and_its_input():
    from smana.services.ros2.service import frames_of

    assert frames_of(SmanaConfig.load(None, ["general.robot=r2", FLEET])).map == "r2/map"
    # a base serving several robots (the multi-robot profile) shares one ROS graph too
    multi = SmanaConfig.load(None, ["general.robot=r1", 'deploy.robots=["r1", "r2"]'])
    assert frames_of(multi).base == "r1/base_link"
    real = SmanaConfig.load(None, ["general.robot=r2", FLEET, "deploy.sim.enabled=false"])
    assert frames_of(real).map == "map"
    assert frames_of(SmanaConfig.load()).map == "map"


@pytest.mark.parametrize(
    "prefix", ["/r1/", "r1//", "r 1/", "r1\\", "*/", "é/", "a" * 65, "$r/", "#r/"]
)
def test_a_frame_prefix_that_is_no_tf_prefix_is_refused(prefix):
    with pytest.raises(ConfigError, match="ros2.frame_prefix"):
        Ros2Config(frame_prefix=prefix)
    with pytest.raises(ConfigError, match="ros2.frame_prefix"):
        SmanaConfig.load(None, [f'ros2.frame_prefix="{prefix}"'])


@pytest.mark.parametrize("prefix", ["auto", "", "r1/", "robot_1-a.b/", "fleet/r1/", "r1_"])
def test_a_tf_frame_prefix_is_taken(prefix):
    assert Ros2Config(frame_prefix=prefix).frame_prefix == prefix


def test_the_tf_topic_is_the_shared_one_unless_the_service_logs_in():
    rc = Ros2Config()
    assert rc.tf_topic_for("r1") == "/tf"
    assert rc.tf_topic_for("r1", secured=True) == "/smana/r1/tf"
    assert Ros2Config(tf_topic="/r1/tf").tf_topic_for("r1", secured=True) == "/r1/tf"
    assert rc.tf_static_topic == "/tf_static"
    for key in ("tf_topic", "tf_static_topic"):
        for bad in ("tf", "/tf/", "//tf", ""):
            with pytest.raises(ConfigError, match=f"ros2.{key}"):
                Ros2Config(**{key: bad})


def test_a_tf_topic_the_secured_policy_would_drop_is_warned_of():
    from smana.services.ros2.service import tf_topic_dropped

    login = "zenoh.credentials_file=creds.txt"
    assert tf_topic_dropped(SmanaConfig.load(None, [login])) is None  # auto: /smana/r1/tf
    assert tf_topic_dropped(SmanaConfig.load(None, [login, "ros2.tf_topic=/smana/r1/tf2"])) is None
    assert tf_topic_dropped(SmanaConfig.load(None, ["ros2.tf_topic=/tf"])) is None  # no policy
    for topic in ("/tf", "/r1/tf", "/smana/r2/tf"):
        why = tf_topic_dropped(SmanaConfig.load(None, [login, f"ros2.tf_topic={topic}"]))
        assert why.startswith(f"ros2.tf_topic {topic} is outside /smana/r1"), why


def _types():
    from smana.services.ros2.rmw import RosTypes

    return RosTypes()


def test_a_robots_cloud_is_read_in_the_prefixed_frames():
    """With a prefix set for a real robot: a cloud in `r1/odom` is in smana's world, one in the
    plain `odom` is not; a sensor frame hangs below `r1/base_link`."""
    from smana.common.service import Reject
    from smana.services.ros2 import convert
    from smana.services.ros2.bridge import CloudInput
    from tests.support.ros2_sdk import pointcloud2

    types = _types()
    config = SmanaConfig.load(None, ['ros2.frame_prefix="r1/"', "ros2.min_range_m=0.0"])
    ci = CloudInput(config, None, config.ros2.frames("r1", robot_input=True))
    for t in (0.4, 0.6):
        ci.poses.add(t, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    pts = np.array([[2.0, 0.0, 0.5]], np.float32)
    world = ci.convert(pointcloud2(types, pts, [1], "r1/odom", 0.5))
    np.testing.assert_allclose(world.points, pts)  # as it is
    with pytest.raises(Reject) as e:
        ci.convert(pointcloud2(types, pts, [1], "odom", 0.5))
    assert e.value.kind == "no_transform" and "'r1/base_link'" in str(e.value)
    mount = types.msg("geometry_msgs/msg/TransformStamped")(
        header=convert.header(types, 0.0, "r1/base_link"),
        child_frame_id="r1/lidar",
        transform=types.msg("geometry_msgs/msg/Transform")(
            translation=types.msg("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=1.0),
            rotation=types.msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )
    assert ci.add_static(types.msg("tf2_msgs/msg/TFMessage")(transforms=[mount])) == 1
    placed = ci.convert(pointcloud2(types, pts, [1], "r1/lidar", 0.5))
    np.testing.assert_allclose(placed.points, [[3.0, 0.0, 1.5]])


def test_every_frame_the_service_stamps_carries_the_prefix(monkeypatch):
    """Robot r2 of a simulated fleet, in process on a recording publisher: /tf, odometry (and its
    child frame), path, goal, map, both costmaps and GetPlan's answer are all in r2's frames."""
    from smana.common.navgrid import FLAG_KNOWN
    from smana.common.query import QueryError
    from smana.common.service_queries import Request
    from smana.services.ros2 import convert
    from smana.services.ros2 import service as ros2_service
    from smana.services.ros2.rmw import attachment

    svc = ros2_service.Ros2Service(SmanaConfig.load(None, ["general.robot=r2", FLEET]))
    assert svc.tf_topic == "/tf"
    svc.types, svc.pubs = _types(), {"tf": None}  # what setup() makes, with the tf publisher
    sent: dict[str, list] = {}
    svc._send = lambda what, msg: sent.setdefault(what, []).append(msg)

    svc.on_pose(Pose.from_xyz_yaw(1.0, 2.0, 0.0, 0.5, stamp_s=10.0))
    state = {"goal": {"xy": [3.0, 1.0], "yaw": 0.2}, "path": [[1.0, 2.0], [3.0, 1.0]], "t_s": 10}
    svc.on_explorer_state(msgpack.packb(state))
    svc.map.centres = np.array([[1.0, 1.0, 0.1]], np.float32)
    svc.map.labels, svc.map.resolution_m = np.array([2], np.uint16), 0.1
    cells = np.array([[10, 10], [11, 10]])
    svc.grid.apply_patch(cells, [2, 2], np.zeros(2), np.array([FLAG_KNOWN] * 2, np.uint8))

    def no_planner(*args, **kwargs):
        raise QueryError("timeout", "no planner here")

    monkeypatch.setattr(ros2_service, "request", no_planner)
    svc.node = type("Node", (), {"reply_attachment": staticmethod(lambda a: a)})()
    ask = svc.types.msg("nav_msgs/srv/GetPlan_Request")(
        start=convert.pose_stamped(svc.types, (0.0, 0.0), 0.0, 1.0, "r2/map"),
        goal=convert.pose_stamped(svc.types, (1.0, 0.0), 0.0, 1.0, "r2/map"),
        tolerance=0.0,
    )
    payload = svc.types.serialize(ask, "nav_msgs/srv/GetPlan_Request")
    reply = svc.on_plan(Request("plan", {}, payload, False, attachment(1, 0, bytes(16))))
    plan = svc.types.deserialize(reply.payload, "nav_msgs/srv/GetPlan_Response").plan

    (tf,) = sent["tf"]
    assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [
        ("r2/map", "r2/odom"),
        ("r2/odom", "r2/base_link"),
    ]
    (odom,) = sent["odom"]
    assert (odom.header.frame_id, odom.child_frame_id) == ("r2/map", "r2/base_link")
    (path,) = sent["path"]
    assert {path.header.frame_id, *(p.header.frame_id for p in path.poses)} == {"r2/map"}
    assert sent["goal"][0].header.frame_id == "r2/map"
    headers = {
        "map": svc._map_message().header,
        "costmap": svc._costmap_message().header,
        "costmap_raw": svc._costmap_raw_message().header,
        "plan": plan.header,
    }
    assert {k: h.frame_id for k, h in headers.items()} == dict.fromkeys(headers, "r2/map")


def _tf_tree(messages) -> dict[str, tuple[str, np.ndarray]]:
    """{child: (parent, translation)} of the last transform of each child."""
    tree = {}
    for m in messages:
        for t in m.transforms:
            v = t.transform.translation
            tree[t.child_frame_id] = (t.header.frame_id, np.array([v.x, v.y, v.z]))
    return tree


@pytest.mark.multiprocess
def test_two_robots_of_a_fleet_publish_two_disjoint_tf_trees(zenoh_stack, tmp_path, monkeypatch):
    """Two ros2 processes (robots r1 and r2 of `fleet.robots`, simulation), each fed its robot's
    pose; a ROS 2 subscriber of zenoh-ros2-sdk on /tf: r1/map -> r1/odom -> r1/base_link at r1's
    pose and r2/map -> r2/odom -> r2/base_link at r2's, no frame shared, no plain `map`."""
    from zenoh_ros2_sdk import ROS2Subscriber

    from tests.support.ros2_sdk import sdk_session

    s = zenoh_stack
    places = {"r1": (1.0, 2.0), "r2": (-3.0, 4.0)}
    for robot in places:
        s.start(
            f"ros2-{robot}",
            *("-m", "smana.services.ros2", *s.zenoh_args(), "--robot", robot),
            *("--set", FLEET, "--set", "ros2.robot_input=off"),
        )
    for robot in places:
        s.wait_alive("ros2", timeout_s=180, robot=robot)
        details = request(s.session, keys.status(robot, "ros2"), None, 5.0).details
        assert details["frames"] == {
            "map": f"{robot}/map",
            "odom": f"{robot}/odom",
            "base": f"{robot}/base_link",
            "tf_topic": "/tf",
        }, details
    pubs = {r: s.publisher(keys.pose(r)) for r in places}
    got: list = []
    lock = threading.Lock()

    def keep(msg):
        with lock:
            got.append(msg)

    with sdk_session(tmp_path, monkeypatch):
        sub = ROS2Subscriber("/tf", "tf2_msgs/msg/TFMessage", keep, router_port=s.port)
        seq = [0]

        def both_trees() -> bool:
            seq[0] += 1
            for robot, (x, y) in places.items():
                pose = Pose.from_xyz_yaw(x, y, 0.0, 0.3, 100.0 + 0.1 * seq[0], seq[0])
                pubs[robot].put(encode(pose))
            with lock:
                tree = _tf_tree(got)
            return {"r1/base_link", "r2/base_link"} <= set(tree)

        try:
            assert wait_for(both_trees, 60, step_s=0.1), (s.log("ros2-r1")[-2000:], len(got))
        finally:
            sub.close()
    with lock:
        tree = _tf_tree(got)
    edges = {child: parent for child, (parent, _) in tree.items()}
    assert edges == {
        "r1/odom": "r1/map",
        "r1/base_link": "r1/odom",
        "r2/odom": "r2/map",
        "r2/base_link": "r2/odom",
    }
    frames = {r: {f for e in edges.items() for f in e if f.startswith(f"{r}/")} for r in places}
    assert frames["r1"].isdisjoint(frames["r2"])
    for robot, (x, y) in places.items():
        np.testing.assert_allclose(tree[f"{robot}/base_link"][1], [x, y, 0.0])
        np.testing.assert_allclose(tree[f"{robot}/odom"][1], 0.0)  # map -> odom: the identity
