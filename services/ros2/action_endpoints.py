"""One ROS 2 action's rmw_zenoh endpoints on a `RosNode` (`ActionEndpoints`): its three
services (send_goal, get_result, cancel_goal: complete queryables, declared by actions.py), its
feedback and status publishers, and its goals (`action_goals.GoalBook`)."""

from __future__ import annotations

import threading

from smana.common.service import Reject

from .action_goals import GoalBook
from .convert import goal_info, uuid_msg
from .nav2_types import action_names
from .rmw import LATCHED_QOS, SERVICE, QoS


class ActionEndpoints:
    """One action's rmw_zenoh endpoints on a `RosNode`: its three services (complete
    queryables) and its feedback and status publishers."""

    def __init__(self, node, name: str, action: str):
        self.action, self.types = action, node.types
        self.names = action_names(action)
        self.keys: dict[str, str] = {}
        for what in ("send_goal", "get_result", "cancel_goal"):
            self.keys[what], _ = node.endpoint(SERVICE, f"{name}/_action/{what}", self.names[what])
        self.feedback = node.publisher(f"{name}/_action/feedback", self.names["feedback"], QoS())
        self.status = node.publisher(f"{name}/_action/status", self.names["status"], LATCHED_QOS)
        self.book = GoalBook()
        self.lock = threading.Lock()  # the publishers' sequence numbers

    def msg(self, suffix: str):
        return self.types.msg(f"{self.action}_{suffix}")

    def decode(self, what: str, payload: bytes):
        typename = self.names[what] + "_Request"
        try:
            return self.types.deserialize(payload, typename)
        except Exception as exc:  # noqa: BLE001 - any CDR that is not this type
            raise Reject("malformed", f"not a {typename}: {type(exc).__name__}") from None

    def encode(self, what: str, msg) -> bytes:
        return self.types.serialize(msg, self.names[what] + "_Response")

    def publish_status(self) -> None:
        T = self.types.msg
        statuses = [
            T("action_msgs/msg/GoalStatus")(
                goal_info=goal_info(self.types, uuid, stamp_ns), status=status
            )
            for uuid, stamp_ns, status in self.book.statuses()
        ]
        with self.lock:
            self.status.put(T("action_msgs/msg/GoalStatusArray")(status_list=statuses))

    def publish_feedback(self, uuid: bytes, feedback) -> None:
        msg = self.msg("FeedbackMessage")(goal_id=uuid_msg(self.types, uuid), feedback=feedback)
        with self.lock:
            self.feedback.put(msg)
