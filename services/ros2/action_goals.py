"""The ROS 2 actions' goals and what they mean, without zenoh (actions.py is the wiring; both
follow rclcpp_action's server and rcl_action, ROS 2 Jazzy, and Nav2's navigator and planner
server, as actions.py's docstring tells):

- `GoalBook`: one action server's goals, their statuses and results, the get_result requests
  held until a result exists, rcl_action's cancel policy;
- a goal's pose (`goal_pose_checked`, `navigate_goal_checked`, `to_world`, `NoTransform`);
- the error codes (ERROR CODES below; `plan_error_code`, `planner_failure_code`, `NAV_ERRORS`)
  and the explorer's word on a goal (`explorer_goal`, the goal query's body; `explorer_refusal`;
  `ExplorerFeedback`, its feedback read and what its end means);
- a NavigateToPose goal's progress between the explorer's feedback (`Progress`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import msgpack
import numpy as np

from smana.common.messages import MessageError

from . import convert
from .nav2_types import (
    CANCEL_GOAL_TERMINATED,
    CANCEL_NONE,
    CANCEL_UNKNOWN_GOAL_ID,
    STATUS_ABORTED,
    STATUS_ACCEPTED,
    STATUS_CANCELED,
    STATUS_CANCELING,
    STATUS_EXECUTING,
    STATUS_SUCCEEDED,
    STATUS_UNKNOWN,
    TERMINAL,
)

RESULT_TIMEOUT_S = 10.0  # rcl_action's default result_timeout
MAX_GOALS = 64  # goals held (running, or finished and not expired); one more is refused
MAX_BEHAVIOR_TREE_CHARS = 4096  # NavigateToPose's behavior_tree: a path (PATH_MAX), not a tree
MAX_WAITING_RESULTS = 16  # get_result requests held for one goal
FEEDBACK_TIMEOUT_S = 5.0  # a navigation goal without explorer feedback this long is aborted
FEEDBACK_HZ = 10.0  # Nav2's navigator sends one per behaviour-tree tick (100 Hz): 10 is enough
# ERROR CODES. smana serves Jazzy's definitions. ComputePathToPose's are Jazzy's own. Jazzy's
# NavigateToPose result defines only NONE: its navigator fills error_code with the failing
# planner's code (ComputePathToPose's 2xx: GOAL_OUTSIDE_MAP, GOAL_OCCUPIED, NO_VALID_PATH), and
# smana does the same. Where Jazzy has no code (no transform, out of time, the explorer
# stopped), Kilted's NavigateToPose codes: the same fields, so the same wire type and hash.
NAV_UNKNOWN, NAV_TF_ERROR, NAV_TIMEOUT = 9000, 9002, 9003
PLAN_ERRORS = {
    "start_blocked": 205,  # START_OCCUPIED
    "goal_blocked": 206,  # GOAL_OCCUPIED
    "unreachable": 208,  # NO_VALID_PATH
    "no_graph": 208,
}
PLAN_UNKNOWN, PLAN_INVALID_PLANNER, PLAN_TF_ERROR, PLAN_TIMEOUT = 200, 201, 202, 207
START_OUTSIDE_MAP, GOAL_OUTSIDE_MAP = 203, 204
PLANNER_IDS = ("", "smana")
# The explorer's reasons for aborting a goal (services/explorer/navigation.py ERRORS) as codes
NAV_ERRORS = {
    "out_of_bounds": GOAL_OUTSIDE_MAP,
    "goal_blocked": PLAN_ERRORS["goal_blocked"],
    "no_path": PLAN_ERRORS["unreachable"],
    "time_budget": NAV_TIMEOUT,
    "stopped": NAV_UNKNOWN,
}


def plan_error_code(error: str, message: str) -> int:
    """A planner's PathReply error as ComputePathToPose's error code."""
    if error == "out_of_bounds":
        return START_OUTSIDE_MAP if message.startswith("start") else GOAL_OUTSIDE_MAP
    return PLAN_ERRORS.get(error, PLAN_UNKNOWN)


def planner_failure_code(kind: str, elapsed_s: float, timeout_s: float) -> int:
    """ComputePathToPose's code when the planner gave no answer: nothing answered (no planner)
    or the deadline passed (zenoh's timeout reply): TIMEOUT; an error reply of its own:
    UNKNOWN."""
    late = elapsed_s >= timeout_s - 0.1
    return PLAN_TIMEOUT if kind == "no_reply" or late else PLAN_UNKNOWN


@dataclass
class Goal:
    uuid: bytes
    stamp_ns: int  # when it was accepted (GoalInfo.stamp)
    status: int
    request: object  # the action's `_Goal` message
    result: object = None
    finished_at: float | None = None
    seen_at: float = 0.0  # monotonic: accepted, or its last feedback
    waiting: list = field(default_factory=list)  # held get_result responders


class GoalBook:
    """One action server's goals, as rcl_action keeps them: their statuses, their results (kept
    `result_timeout_s` after the end), the get_result requests held until a result exists.
    Thread-safe; no zenoh: a responder is any callable taking (status, result)."""

    def __init__(
        self,
        result_timeout_s: float = RESULT_TIMEOUT_S,
        max_goals: int = MAX_GOALS,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.result_timeout_s, self.max_goals, self.clock = result_timeout_s, max_goals, clock
        self.lock = threading.RLock()
        self.goals: dict[bytes, Goal] = {}

    def add(self, uuid: bytes, request, stamp_ns: int) -> Goal | None:
        """A new goal, ACCEPTED; None when its id is taken or the book is full of goals that have
        not ended."""
        with self.lock:
            self.expire()
            if uuid in self.goals:
                return None
            if len(self.goals) >= self.max_goals:
                # the oldest ended goal makes room: its result was kept for a late get_result,
                # never at the cost of a new goal (a flood ended 64 goals, and refused valid
                # ones for the next 10 s)
                ended = [u for u, g in self.goals.items() if g.finished_at is not None]
                if not ended:
                    return None
                del self.goals[min(ended, key=lambda u: self.goals[u].finished_at)]
            goal = Goal(uuid, stamp_ns, STATUS_ACCEPTED, request, seen_at=self.clock())
            self.goals[uuid] = goal
            return goal

    def discard(self, uuid: bytes) -> None:
        """Forget a goal that was never announced (its acceptance fell through)."""
        with self.lock:
            self.goals.pop(uuid, None)

    def get(self, uuid: bytes) -> Goal | None:
        with self.lock:
            return self.goals.get(uuid)

    def running(self) -> list[Goal]:
        with self.lock:
            return [g for g in self.goals.values() if g.status not in TERMINAL]

    def set_status(self, uuid: bytes, status: int) -> bool:
        """Move a running goal to EXECUTING or CANCELING; False if it is not running."""
        with self.lock:
            g = self.goals.get(uuid)
            if g is None or g.status in TERMINAL or g.status == status:
                return False
            g.status = status
            return True

    def finish(self, uuid: bytes, status: int, result) -> bool:
        """End a running goal with its result and answer the get_result requests held for it;
        False (and nothing changes) if it is unknown or already over."""
        with self.lock:
            g = self.goals.get(uuid)
            if g is None or g.status in TERMINAL:
                return False
            g.status, g.result, g.finished_at = status, result, self.clock()
            waiting, g.waiting = g.waiting, []
        for respond in waiting:
            respond(status, result)
        return True

    def result(self, uuid: bytes, respond: Callable) -> str:
        """A get_result request: answered now ("answered": finished, or "unknown" with
        STATUS_UNKNOWN), or held until the goal ends ("held"); "full" when too many wait."""
        with self.lock:
            self.expire()
            g = self.goals.get(uuid)
            if g is not None and g.status not in TERMINAL:
                if len(g.waiting) >= MAX_WAITING_RESULTS:
                    return "full"
                g.waiting.append(respond)
                return "held"
        if g is None:
            respond(STATUS_UNKNOWN, None)
            return "unknown"
        respond(g.status, g.result)
        return "answered"

    def cancel(self, uuid: bytes, stamp_ns: int) -> tuple[int, list[Goal]]:
        """rcl_action's cancel policy -> (return code, the goals now CANCELING)."""
        with self.lock:
            zero_id = not any(uuid)
            if not zero_id and stamp_ns == 0:
                g = self.goals.get(uuid)
                if g is None:
                    return CANCEL_UNKNOWN_GOAL_ID, []
                if g.status not in (STATUS_ACCEPTED, STATUS_EXECUTING):
                    return CANCEL_GOAL_TERMINATED, []
                targets = [g]
            else:
                until = math.inf if zero_id and stamp_ns == 0 else stamp_ns
                targets = [
                    g
                    for g in self.goals.values()
                    if g.status in (STATUS_ACCEPTED, STATUS_EXECUTING)
                    and (g.stamp_ns <= until or g.uuid == uuid)
                ]
            for g in targets:
                g.status = STATUS_CANCELING
            return CANCEL_NONE, targets

    def expire(self) -> int:
        """Forget finished goals older than the result timeout."""
        with self.lock:
            now = self.clock()
            old = [
                u
                for u, g in self.goals.items()
                if g.finished_at is not None and now - g.finished_at > self.result_timeout_s
            ]
            for u in old:
                del self.goals[u]
            return len(old)

    def statuses(self) -> list[tuple[bytes, int, int]]:
        """(uuid, accepted stamp ns, status) of every goal held, oldest first."""
        with self.lock:
            return [(g.uuid, g.stamp_ns, g.status) for g in self.goals.values()]


def goal_pose_checked(pose_stamped, frames) -> tuple[str, float, float, float]:
    """(frame, x, y, yaw) of a goal's PoseStamped; ValueError for a pose that is not finite, a
    degenerate quaternion, a place beyond 1000 km, or a frame not in `frames`."""
    frame = pose_stamped.header.frame_id.lstrip("/")
    if not frame:  # Nav2 cannot transform a pose of no frame either
        raise ValueError(f"goal has no frame_id: smana's frames are {list(frames)}")
    if frame not in frames:
        raise ValueError(f"goal in frame {frame!r}: smana's frames are {list(frames)}")
    pos, q = convert.pose_of(pose_stamped.pose)
    if np.abs(pos).max() > 1e6:
        raise ValueError("goal further than 1000 km")
    yaw = math.atan2(2.0 * (q[3] * q[2] + q[0] * q[1]), 1.0 - 2.0 * (q[1] ** 2 + q[2] ** 2))
    return frame, float(pos[0]), float(pos[1]), yaw


def navigate_goal_checked(goal, frames) -> tuple[str, float, float, float]:
    """(frame, x, y, yaw) of a NavigateToPose goal; ValueError for what Nav2 could not even
    read: its pose (`goal_pose_checked`), or a behaviour tree name over
    MAX_BEHAVIOR_TREE_CHARS."""
    frame, x, y, yaw = goal_pose_checked(goal.pose, frames)
    if len(goal.behavior_tree) > MAX_BEHAVIOR_TREE_CHARS:
        raise ValueError(
            f"behavior_tree of {len(goal.behavior_tree)} characters: a file name of at "
            f"most {MAX_BEHAVIOR_TREE_CHARS} (smana runs none: it is ignored)"
        )
    return frame, x, y, yaw


def compute_path_goal_checked(goal, frames) -> list[tuple[str, float, float, float]]:
    """[goal's (frame, x, y, yaw), and the start's with `use_start`] of a ComputePathToPose
    goal; ValueError as `goal_pose_checked`."""
    ends = [goal_pose_checked(goal.goal, frames)]
    if goal.use_start:
        ends.append(goal_pose_checked(goal.start, frames))
    return ends


def planner_refusal(planner_id: str) -> str:
    """Why a ComputePathToPose goal's planner is not smana's ("" when it is)."""
    if planner_id in PLANNER_IDS:
        return ""
    return f"planner_id {planner_id!r}: smana's planner is '' or 'smana'"


def explorer_goal(gid: str, x: float, y: float, yaw: float, no_path_timeout_s: float) -> dict:
    """The explorer's goal query (`explorer/goal`) for a NavigateToPose goal: as Nav2, accepted,
    and aborted with a code when it cannot be reached."""
    return {
        "x": x,
        "y": y,
        "yaw": yaw,
        "tolerance_m": None,
        "id": gid,
        "accept_unreachable": True,
        "no_path_timeout_s": no_path_timeout_s,
    }


def explorer_refusal(answer) -> str:
    """Why the explorer's answer to a goal query is not an acceptance ("" when it is one)."""
    if isinstance(answer, dict) and answer.get("accepted"):
        return ""
    why = answer.get("reason", "") if isinstance(answer, dict) else repr(answer)
    return f"refused: explorer: {why}"


@dataclass
class ExplorerFeedback:
    """The explorer's goal feedback (`explorer/goal/feedback`), read and checked."""

    id: str
    state: str
    pose: list | None  # x, y, yaw; None: the explorer has no pose yet
    remaining: float  # metres, NaN without a pose
    nav_time: float
    recoveries: int
    reason: str
    error: str

    @classmethod
    def parse(cls, payload: bytes) -> ExplorerFeedback:
        """MessageError ("malformed", "value") for a payload that is not one."""
        try:
            fb = msgpack.unpackb(payload, strict_map_key=False)
            gid, state = str(fb["id"]), str(fb["state"])
            raw_pose = fb.get("pose")
            pose = None if raw_pose is None else [float(v) for v in raw_pose][:3]
            remaining = fb.get("distance_remaining_m")
            remaining = math.nan if remaining is None else float(remaining)
            nav_time = float(fb.get("navigation_time_s") or 0.0)
            recoveries = int(fb.get("recoveries") or 0)
            reason = str(fb.get("reason") or "")
            error = str(fb.get("error") or "")
        except (ValueError, TypeError, KeyError, AttributeError, msgpack.UnpackException) as exc:
            raise MessageError("malformed", f"explorer goal feedback: {exc}") from None
        if pose is not None and (len(pose) != 3 or not all(math.isfinite(v) for v in pose)):
            raise MessageError("value", "explorer goal feedback: pose must be 3 finite numbers")
        if pose is not None and not math.isfinite(remaining):
            raise MessageError("value", "explorer goal feedback: a pose without a finite distance")
        return cls(gid, state, pose, remaining, nav_time, recoveries, reason, error)

    def end(self) -> tuple[int, int] | None:
        """(status, error code) the goal ends with, None while it runs."""
        return {
            "succeeded": (STATUS_SUCCEEDED, 0),
            "aborted": (STATUS_ABORTED, NAV_ERRORS.get(self.error, NAV_UNKNOWN)),
            "preempted": (STATUS_ABORTED, 0),
            "canceled": (STATUS_CANCELED, 0),
        }.get(self.state)


def to_world(x: float, y: float, yaw: float, base) -> tuple[float, float, float]:
    """A pose in the robot's base frame, in the world frame, the robot being at `base` = (x, y,
    yaw) there (a planar robot: tf's odom -> base_link)."""
    bx, by, byaw = base
    c, s = math.cos(byaw), math.sin(byaw)
    return bx + c * x - s * y, by + s * x + c * y, math.remainder(byaw + yaw, math.tau)


class NoTransform(ValueError):
    """A goal in the robot's base frame before any pose of the robot: tf has no transform yet."""


@dataclass
class Progress:
    """A NavigateToPose goal's progress as the explorer last reported it (`at`, monotonic), and
    the way the robot has driven since."""

    uuid: bytes
    pose: list  # x, y, yaw
    remaining: float
    nav_time: float
    recoveries: int
    at: float
    travelled: float = 0.0
    last_xy: tuple | None = None

    def drove_to(self, x: float, y: float) -> None:
        """The robot's pose: the way it has driven since the explorer's last word."""
        if self.last_xy is not None:
            self.travelled += math.hypot(x - self.last_xy[0], y - self.last_xy[1])
        self.last_xy = (x, y)

    def remaining_m(self) -> float:
        """The explorer's remaining distance less the way driven since it said so."""
        return max(0.0, self.remaining - self.travelled)

    def navigation_time_s(self, now: float) -> float:
        return self.nav_time + (now - self.at)

    def recoveries_int16(self) -> int:
        """The recoveries as NavigateToPose's int16 field holds them."""
        return max(-(2**15), min(self.recoveries, 2**15 - 1))


def announced(book: GoalBook) -> int:
    """Goals running that a client was told of (not one still waiting for the explorer)."""
    return sum(g.status in (STATUS_EXECUTING, STATUS_CANCELING) for g in book.running())
