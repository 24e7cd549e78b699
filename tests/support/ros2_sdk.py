"""What the ROS 2 tests share: message definitions for zenoh-ros2-sdk written from rosbags'
typestore (the SDK would otherwise download them: no network at test time), and an SDK session
on a test's own router, reset between tests (the SDK keeps one session per process)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

MESSAGE_TYPES = (
    "sensor_msgs/msg/PointCloud2",
    "nav_msgs/msg/OccupancyGrid",
    "nav_msgs/msg/Path",
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/Twist",
    "tf2_msgs/msg/TFMessage",
    "service_msgs/msg/ServiceEventInfo",
    # what the actions' messages are made of (tests/support/ros2_action_client.py)
    "builtin_interfaces/msg/Duration",
    "unique_identifier_msgs/msg/UUID",
    "action_msgs/msg/GoalInfo",
    "action_msgs/msg/GoalStatusArray",
)
GET_PLAN_SRV = (
    "geometry_msgs/PoseStamped start\ngeometry_msgs/PoseStamped goal\nfloat32 tolerance\n"
    "---\nnav_msgs/Path plan\n"
)


def write_msgdefs(root: Path) -> Path:
    """One `<pkg>/msg/<Name>.msg` per type (and its dependencies), as ROS 2 packages ship them;
    nav2_msgs' Costmap and CostmapMetaData (smana's copy of Nav2's definitions);
    `nav_msgs/srv/GetPlan.srv`. The text comes from rosbags, the parsing and hashing from the
    SDK: the hashes the tests compare are computed twice, independently."""
    from smana.services.ros2.rmw import write_msg_files

    write_msg_files(root, MESSAGE_TYPES)
    from smana.services.ros2 import costmap_types  # rosbags' store has no nav2_msgs

    for typename, text in costmap_types.DEFINITIONS.items():
        pkg, _, msg = typename.split("/")
        (root / pkg / "msg").mkdir(parents=True, exist_ok=True)
        (root / pkg / "msg" / f"{msg}.msg").write_text(text)
    srv = root / "nav_msgs" / "srv" / "GetPlan.srv"
    srv.parent.mkdir(parents=True, exist_ok=True)
    srv.write_text(GET_PLAN_SRV)
    return root


@contextlib.contextmanager
def sdk_session(tmp: Path, monkeypatch):
    """The SDK's registry on local definitions and a fresh SDK session; closed afterwards."""
    monkeypatch.setenv("ZENOH_ROS2_SDK_CACHE", str(tmp / "sdk-cache"))
    # Its peer finds the test's router by the endpoint it is given: nothing else.
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", "scouting/multicast/enabled=false")
    from zenoh_ros2_sdk import message_registry, session

    session.ZenohSession._instance = None
    message_registry._registry = None
    message_registry.get_registry(str(write_msgdefs(tmp / "msgs")))
    try:
        yield
    finally:
        inst = session.ZenohSession._instance
        if inst is not None:
            with contextlib.suppress(Exception):
                inst.session.close()
        session.ZenohSession._instance = None
        message_registry._registry = None


def rmw_zenoh_session_config(
    out: Path, host: Path, user_file: Path, endpoint: str, mtls: bool = True, timeout_ms=30000
) -> Path:
    """The session config docs/ros2.md gives an rmw_zenoh node on the secured profile, written to
    `out`: rmw_zenoh's default (the SDK's copy of DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5) with the
    router's `endpoint`, the CA, certificate and key of the host folder `host` (`certs/<r>/`) in
    `transport/link/tls`, `enable_mtls` as given (rmw_zenoh's default is false), and the user
    and password of `user_file` (`credentials/<r>.ros2peer.txt`) in `transport/auth/usrpwd`.
    Unlike rmw_zenoh's, a link the router refuses fails the open after `timeout_ms` instead of
    being retried for ever."""
    import json

    import json5
    from zenoh_ros2_sdk import session as sdk

    from smana.common.zenoh_config import read_credentials

    conf = json5.loads(sdk._DEFAULT_SESSION_CONFIG_PATH.read_text())
    conf["connect"]["endpoints"] = [endpoint]
    conf["connect"]["timeout_ms"]["peer"] = timeout_ms
    conf["connect"]["exit_on_failure"]["peer"] = True
    conf["transport"]["link"]["tls"].update(
        root_ca_certificate=str(host / "ca.pem"),
        connect_certificate=str(host / "host.pem"),
        connect_private_key=str(host / "host.key"),
        enable_mtls=mtls,
    )
    ((user, password),) = read_credentials(str(user_file)).items()
    conf["transport"]["auth"]["usrpwd"].update(user=user, password=password)
    out.write_text(json.dumps(conf, indent=1))
    return out


def pointcloud2(types, points, labels=None, frame="velodyne", t_s=0.5):
    """A PointCloud2 (rosbags message of `types`, a `services.ros2.rmw.RosTypes`) of x, y, z
    float32 and, when given, a uint32 `label`, as a LiDAR driver publishes them."""
    from smana.services.ros2 import convert

    names = ["x", "y", "z"] + (["label"] if labels is not None else [])
    rec = np.zeros(len(points), [(n, "<f4" if n != "label" else "<u4") for n in names])
    rec["x"], rec["y"], rec["z"] = np.asarray(points, np.float32).T
    if labels is not None:
        rec["label"] = labels
    field = types.msg("sensor_msgs/msg/PointField")
    fields = [
        field(name=n, offset=4 * i, datatype=7 if n != "label" else 6, count=1)
        for i, n in enumerate(names)
    ]
    step = 4 * len(names)
    return types.msg("sensor_msgs/msg/PointCloud2")(
        header=convert.header(types, t_s, frame),
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * len(points),
        data=rec.view(np.uint8),
        is_dense=True,
    )
