"""What the ROS 2 tests share: message definitions for zenoh-ros2-sdk written from rosbags'
typestore (the SDK would otherwise download them: no network at test time), and an SDK session
on a test's own router, reset between tests (the SDK keeps one session per process)."""

from __future__ import annotations

import contextlib
from pathlib import Path

MESSAGE_TYPES = (
    "sensor_msgs/msg/PointCloud2",
    "nav_msgs/msg/OccupancyGrid",
    "nav_msgs/msg/Path",
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/Twist",
    "tf2_msgs/msg/TFMessage",
    "service_msgs/msg/ServiceEventInfo",
)
GET_PLAN_SRV = (
    "geometry_msgs/PoseStamped start\ngeometry_msgs/PoseStamped goal\nfloat32 tolerance\n"
    "---\nnav_msgs/Path plan\n"
)


def write_msgdefs(root: Path) -> Path:
    """One `<pkg>/msg/<Name>.msg` per type (and its dependencies), as ROS 2 packages ship them;
    `nav_msgs/srv/GetPlan.srv`. The text comes from rosbags, the parsing and hashing from the
    SDK: the hashes the tests compare are computed twice, independently."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for typename in MESSAGE_TYPES:
        text, _ = store.generate_msgdef(typename, ros_version=2)
        name = typename
        for i, block in enumerate(text.split("=" * 80 + "\n")):
            if i:
                head, block = block.split("\n", 1)
                name = head.removeprefix("MSG: ")
            pkg, msg = name.replace("/msg/", "/").split("/")
            path = root / pkg / "msg" / f"{msg}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(block.rstrip("\n") + "\n")
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
