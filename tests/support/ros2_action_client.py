"""A ROS 2 action client as rclcpp_action's behaves over rmw_zenoh, built from zenoh-ros2-sdk's
parts (its zenoh session, its key expressions, its attachment, its typestore for CDR) and the
.action texts of nav2_msgs (Jazzy) written out here, not smana's `nav2_types.py`.

The keys of `send_goal` and `get_result` carry the hashes smana computes: the SDK hashes a
service as `<pkg>/srv/<Name>` and so cannot hash an action's services (`<pkg>/action/...`);
tests/test_ros2_actions.py checks smana's construction against rosidl's known Jazzy values.
Every other hash (feedback, status, cancel) is the SDK's own."""

from __future__ import annotations

import os
import threading
import time

NAVIGATE_TO_POSE = (
    "geometry_msgs/PoseStamped pose\nstring behavior_tree\n",
    "uint16 NONE=0\nuint16 error_code\nstring error_msg\n",
    "geometry_msgs/PoseStamped current_pose\nbuiltin_interfaces/Duration navigation_time\n"
    "builtin_interfaces/Duration estimated_time_remaining\nint16 number_of_recoveries\n"
    "float32 distance_remaining\n",
)
COMPUTE_PATH_TO_POSE = (
    "geometry_msgs/PoseStamped goal\ngeometry_msgs/PoseStamped start\nstring planner_id\n"
    "bool use_start\n",
    "uint16 NONE=0\nuint16 UNKNOWN=200\nuint16 INVALID_PLANNER=201\nuint16 TF_ERROR=202\n"
    "uint16 START_OUTSIDE_MAP=203\nuint16 GOAL_OUTSIDE_MAP=204\nuint16 START_OCCUPIED=205\n"
    "uint16 GOAL_OCCUPIED=206\nuint16 TIMEOUT=207\nuint16 NO_VALID_PATH=208\n"
    "nav_msgs/Path path\nbuiltin_interfaces/Duration planning_time\nuint16 error_code\n"
    "string error_msg\n",
    "",
)
CANCEL_REQUEST = "action_msgs/GoalInfo goal_info\n"
CANCEL_RESPONSE = "int8 return_code\naction_msgs/GoalInfo[] goals_canceling\n"
DEPENDENCIES = (
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Path",
    "builtin_interfaces/msg/Duration",
    "builtin_interfaces/msg/Time",
    "unique_identifier_msgs/msg/UUID",
    "action_msgs/msg/GoalInfo",
    "action_msgs/msg/GoalStatusArray",
)


class ActionClient:
    """One action `name` (e.g. /smana/test/navigate_to_pose) of type `action` on the SDK's
    session to the router on `router_port`, or on `sdk`, an SDK session of the caller's (a
    `ZenohSession`: one per identity when a test logs in twice)."""

    def __init__(
        self, router_port: int, name: str, action: str, texts, service_hashes: dict, sdk=None
    ):
        from zenoh_ros2_sdk import get_registry
        from zenoh_ros2_sdk.keyexpr import topic_keyexpr
        from zenoh_ros2_sdk.session import ZenohSession
        from zenoh_ros2_sdk.utils import (
            compute_service_type_hash,
            get_type_hash,
            load_dependencies_recursive,
            ros2_to_dds_type,
        )

        self.sdk = sdk or ZenohSession.get_instance(router_port=router_port)
        self.session, self.action = self.sdk.session, action
        registry = get_registry()
        deps: dict[str, str] = {}
        for t in DEPENDENCIES:
            registry.load_message_type(t)
            text = registry.get_msg_file_path(t).read_text()
            deps[t] = text
            deps.update(load_dependencies_recursive(t, text, registry))
        goal, result, feedback = texts
        pkg, _, base = action.split("/")
        own = {
            f"{action}_Goal": goal,
            f"{action}_Result": result,
            f"{action}_Feedback": feedback or "uint8 structure_needs_at_least_one_member\n",
            f"{action}_FeedbackMessage": f"unique_identifier_msgs/UUID goal_id\n"
            f"{pkg}/action/{base}_Feedback feedback\n",
            f"{action}_SendGoal_Request": f"unique_identifier_msgs/UUID goal_id\n"
            f"{pkg}/action/{base}_Goal goal\n",
            f"{action}_SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp\n",
            f"{action}_GetResult_Request": "unique_identifier_msgs/UUID goal_id\n",
            f"{action}_GetResult_Response": f"int8 status\n{pkg}/action/{base}_Result result\n",
            "action_msgs/srv/CancelGoal_Request": CANCEL_REQUEST,
            "action_msgs/srv/CancelGoal_Response": CANCEL_RESPONSE,
        }
        from rosbags.typesys import get_types_from_msg

        self._keys: dict[str, str] = {}
        for typename, text in own.items():
            # The SDK's store is a rosbags one; rosbags files `<pkg>/srv/<T>` as
            # `<pkg>/srv/msg/<T>`, so each type is looked up by the key it got.
            found = get_types_from_msg(text, typename)
            self.sdk.store.register(found)
            (self._keys[typename],) = found
        deps.update({k: v for k, v in own.items() if not k.endswith(("_Request", "_Response"))})
        fb_type = f"{action}_FeedbackMessage"
        self.hashes = {
            "send_goal": service_hashes["send_goal"],
            "get_result": service_hashes["get_result"],
            "cancel_goal": compute_service_type_hash(
                "action_msgs/srv/CancelGoal", CANCEL_REQUEST, CANCEL_RESPONSE, deps
            ),
            "feedback": get_type_hash(fb_type, own[fb_type], deps),
            "status": get_type_hash(
                "action_msgs/msg/GoalStatusArray", deps["action_msgs/msg/GoalStatusArray"], deps
            ),
        }
        types = {
            "send_goal": f"{action}_SendGoal",
            "get_result": f"{action}_GetResult",
            "cancel_goal": "action_msgs/srv/CancelGoal",
            "feedback": fb_type,
            "status": "action_msgs/msg/GoalStatusArray",
        }
        self.types = types
        self.keys = {
            what: topic_keyexpr(
                0, f"{name}/_action/{what}", ros2_to_dds_type(types[what]), self.hashes[what]
            )
            for what in types
        }
        self.gid = os.urandom(16)
        self._seq = 0
        self._lock = threading.Lock()
        self.feedback: list = []  # (uuid, Feedback)
        self.feedback_times: list = []  # (uuid, monotonic time it arrived)
        self.statuses: list = []  # GoalStatusArray
        self._subs = [
            self.session.declare_subscriber(self.keys["feedback"], self._on_feedback),
            self.session.declare_subscriber(self.keys["status"], self._on_status),
        ]

    def _key(self, typename: str) -> str:
        """The store key of a type (a service's parts are under `<pkg>/srv/msg/`)."""
        return self._keys.get(typename, typename)

    def msg(self, typename: str):
        return self.sdk.store.types[self._key(typename)]

    def decode(self, raw: bytes, typename: str):
        return self.sdk.store.deserialize_cdr(raw, self._key(typename))

    def _on_feedback(self, sample) -> None:
        m = self.decode(sample.payload.to_bytes(), self.types["feedback"])
        with self._lock:
            self.feedback.append((bytes(m.goal_id.uuid), m.feedback))
            self.feedback_times.append((bytes(m.goal_id.uuid), time.monotonic()))

    def _on_status(self, sample) -> None:
        m = self.decode(sample.payload.to_bytes(), self.types["status"])
        with self._lock:
            self.statuses.append(m)

    def status_of(self, uuid: bytes) -> int | None:
        with self._lock:
            if not self.statuses:
                return None
            for s in self.statuses[-1].status_list:
                if bytes(s.goal_info.goal_id.uuid) == uuid:
                    return int(s.status)
        return None

    def feedback_gaps(self, uuid: bytes) -> list[float]:
        """Seconds between consecutive feedback messages of a goal."""
        with self._lock:
            t = [at for u, at in self.feedback_times if u == uuid]
        return [b - a for a, b in zip(t, t[1:], strict=False)]

    def feedback_of(self, uuid: bytes) -> list:
        with self._lock:
            return [f for u, f in self.feedback if u == uuid]

    def call(self, what: str, request, timeout_s: float = 10.0, raw: bytes | None = None):
        """One service call with rmw_zenoh's attachment; the decoded response, or the error
        reply's bytes (an `Err`)."""
        import numpy as np
        from zenoh_ros2_sdk.attachment import Attachment

        with self._lock:
            self._seq += 1
            seq = self._seq
        payload = (
            raw
            if raw is not None
            else bytes(
                self.sdk.store.serialize_cdr(request, self._key(self.types[what] + "_Request"))
            )
        )
        att = Attachment(sequence_id=seq, timestamp_ns=time.time_ns(), gid=self.gid).to_bytes()
        replies = list(self.session.get(self.keys[what], payload=payload, attachment=att,
                                        timeout=timeout_s))  # fmt: skip
        if not replies:
            raise TimeoutError(f"{what}: no reply in {timeout_s} s")
        r = replies[0]
        if r.ok is None:
            return Err(r.err.payload.to_bytes())
        back = r.ok.attachment.to_bytes()
        assert np.frombuffer(back[:8], "<i8")[0] == seq and back[-16:] == self.gid, "attachment"
        return self.decode(r.ok.payload.to_bytes(), self.types[what] + "_Response")

    def uuid_msg(self, uuid: bytes):
        import numpy as np

        return self.msg("unique_identifier_msgs/msg/UUID")(
            uuid=np.frombuffer(uuid, np.uint8).copy()
        )

    def send_goal(self, uuid: bytes | None = None, timeout_s: float = 10.0, **goal):
        """-> (uuid, SendGoal response)."""
        uuid = uuid or os.urandom(16)
        g = self.msg(f"{self.action}_Goal")(**goal)
        req = self.msg(f"{self.action}_SendGoal_Request")(goal_id=self.uuid_msg(uuid), goal=g)
        return uuid, self.call("send_goal", req, timeout_s)

    def get_result(self, uuid: bytes, timeout_s: float = 60.0):
        req = self.msg(f"{self.action}_GetResult_Request")(goal_id=self.uuid_msg(uuid))
        return self.call("get_result", req, timeout_s)

    def cancel(self, uuid: bytes, sec: int = 0, nanosec: int = 0, timeout_s: float = 10.0):
        info = self.msg("action_msgs/msg/GoalInfo")(
            goal_id=self.uuid_msg(uuid),
            stamp=self.msg("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec),
        )
        return self.call(
            "cancel_goal", self.msg("action_msgs/srv/CancelGoal_Request")(goal_info=info), timeout_s
        )

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


class Err(bytes):
    """An error reply's payload."""


def pose_stamped(client: ActionClient, x: float, y: float, yaw: float = 0.0, frame="map"):
    import math

    m = client.msg
    return m("geometry_msgs/msg/PoseStamped")(
        header=m("std_msgs/msg/Header")(
            stamp=m("builtin_interfaces/msg/Time")(sec=0, nanosec=0), frame_id=frame
        ),
        pose=m("geometry_msgs/msg/Pose")(
            position=m("geometry_msgs/msg/Point")(x=x, y=y, z=0.0),
            orientation=m("geometry_msgs/msg/Quaternion")(
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        ),
    )
