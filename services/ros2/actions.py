"""ROS 2 actions over rmw_zenoh: nav2_msgs' NavigateToPose (driven by the explorer's navigator
mode) and ComputePathToPose (answered by smana's planner), and `/goal_pose` as RViz2's "2D Goal
Pose" button sends it.

An action is three services and two topics under `<name>/_action/` (`nav2_types.py`); rmw_zenoh
carries each like any other service or topic (`rmw.py`). What a server does with them follows
rclcpp_action's server and rcl_action (ROS 2 Jazzy):

- send_goal: a well-formed goal is accepted (ACCEPTED, then EXECUTING), one that is not is
  refused (`accepted = false`) and counted;
- get_result: answered at once for a finished goal, held until the result exists for a running
  one (rmw_zenoh_cpp's clients wait for a reply without a timeout), STATUS_UNKNOWN for a goal
  the server does not know (or whose result expired: RESULT_TIMEOUT_S, rcl_action's default of
  10 s);
- cancel_goal: rcl_action's policy (one goal by id, all goals, all accepted at or before a
  stamp); an unknown id is ERROR_UNKNOWN_GOAL_ID, a finished goal ERROR_GOAL_TERMINATED;
- status: every goal the server holds, reliable and transient-local (depth 1), published on
  every change.

A second NavigateToPose goal pre-empts the first, which ends ABORTED, as Nav2's
SimpleActionServer ends it (`accept_pending_goal`: `current_handle_->abort(...)`).

What Nav2's navigator and planner server do with a goal, smana does too: a goal in any frame of
the tree smana publishes (the world frames, and the robot's base frame through the robot's
latest pose) is accepted, also one outside the navigation graph or on an obstacle; the ones that
cannot be reached are then aborted with an error code (action_goals.py's ERROR CODES) and an
`error_msg`.
Refused (and counted) is only what Nav2 could not even read: a pose that is not finite, an empty
or unknown frame, a behaviour tree name over MAX_BEHAVIOR_TREE_CHARS. ComputePathToPose plans
through unknown ground (`ros2.plan_through_unknown`, Nav2's `allow_unknown`). NavigateToPose's
feedback goes out at FEEDBACK_HZ from the robot's latest pose and the explorer's last word on the
path (which comes at the explorer's own, slower, feedback period).

`GoalBook` holds the goals and is tested without zenoh, with the rest of what a goal means (its
pose, its error codes, the explorer's word on it, its progress: `action_goals.py`);
`Ros2Actions` is the wiring. Queries are
handled on worker threads (the explorer's and the planner's answers are waited for there, never
on a zenoh callback nor on the service's loop).
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from smana.common import keys
from smana.common.messages import MessageError, PathReply, PathRequest
from smana.common.query import QueryError, request
from smana.common.service import Reject

from . import convert
from .action_endpoints import ActionEndpoints
from .action_goals import (
    FEEDBACK_HZ,
    FEEDBACK_TIMEOUT_S,
    MAX_WAITING_RESULTS,
    NAV_TF_ERROR,
    PLAN_INVALID_PLANNER,
    PLAN_TF_ERROR,
    PLAN_UNKNOWN,
    ExplorerFeedback,
    Goal,
    NoTransform,
    Progress,
    announced,
    compute_path_goal_checked,
    explorer_goal,
    explorer_refusal,
    goal_pose_checked,
    navigate_goal_checked,
    plan_error_code,
    planner_failure_code,
    planner_refusal,
    to_world,
)
from .convert import duration, goal_info
from .jobs import Jobs
from .nav2_types import (
    STATUS_ABORTED,
    STATUS_CANCELED,
    STATUS_CANCELING,
    STATUS_EXECUTING,
    STATUS_SUCCEEDED,
    TERMINAL,
)
from .rmw import SUBSCRIPTION, QoS

NAVIGATE = "nav2_msgs/action/NavigateToPose"
COMPUTE_PATH = "nav2_msgs/action/ComputePathToPose"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
QUERY_TIMEOUT_S = 5.0  # the explorer's and the planner's answers
PLANNER_RETRY_S = 0.2  # a planner not answering at all (starting) is asked again this often
ACTION_THREADS, ACTION_WAITING = 2, 32


class Ros2Actions:
    """NavigateToPose, ComputePathToPose and /goal_pose for the ros2 service (`svc`: its
    session, node, books and config)."""

    def __init__(self, svc, namespace: str):
        self.svc = svc
        rc, node = svc.config.ros2, svc.node
        self.types = node.types
        # the names the service stamps and reads (a simulated fleet's `r1/map`, ...)
        names = svc.frames
        self.world_frames, self.base_frame, self.map_frame = names.world, names.base, names.map
        self.frames = (*self.world_frames, self.base_frame)
        self.no_path_s = float(rc.navigate_no_path_s)
        self.through_unknown = bool(rc.plan_through_unknown)
        self.unknown_cost = float(svc.config.planner.unknown_cost)
        self.speed_mps = float(svc.config.explorer.follower.max_linear_mps)
        self.nav = ActionEndpoints(node, f"{namespace}/{rc.navigate_action}", NAVIGATE)
        self.plan = ActionEndpoints(node, f"{namespace}/{rc.compute_path_action}", COMPUTE_PATH)
        self.jobs = Jobs("ros2-action", ACTION_THREADS, ACTION_WAITING)
        self.counts = dict.fromkeys(
            ("goals", "accepted", "refused", "feedback", "feedback_without_pose", "canceled"), 0
        )
        self._explorer_ids: dict[str, bytes] = {}  # explorer goal id -> uuid
        # the running goal's progress as the explorer last told it (its feedback period), from
        # which `tick` sends NavigateToPose feedback at FEEDBACK_HZ
        self._progress: Progress | None = None
        self._next_feedback = 0.0
        self._nav_lock = threading.Lock()
        self._count_lock = threading.Lock()
        for endpoints in (self.nav, self.plan):
            for what in ("send_goal", "get_result", "cancel_goal"):
                key = endpoints.keys[what]
                svc._declared.append(
                    svc.session.declare_queryable(
                        key,
                        lambda q, e=endpoints, w=what, k=key: self._on_query(e, w, k, q),
                        complete=True,
                    )
                )
            endpoints.publish_status()
        goal_key, _ = node.endpoint(SUBSCRIPTION, rc.goal_pose_topic, POSE_STAMPED, QoS())
        svc.subscribe(goal_key, self.on_goal_pose)
        svc.subscribe(keys.explorer_goal_feedback(svc.robot), self.on_explorer_feedback)

    def close(self) -> None:
        self.jobs.close()

    def _count(self, what: str) -> None:
        with self._count_lock:  # workers and the loop both count
            self.counts[what] += 1

    # -- queries (zenoh's thread -> a worker) ---------------------------------------------------

    def _on_query(self, endpoints: ActionEndpoints, what: str, key: str, query) -> None:
        svc = self.svc
        with svc.books.lock:
            svc.books.received += 1
            svc.books.in_flight += 1
        if not self.jobs.submit(
            lambda: self._handle(endpoints, what, key, query),
            lambda: self._dropped(query, "stopping"),
        ):
            self._dropped(query, "stopping" if svc.stopping else "queue_full")

    def _dropped(self, query, why: str) -> None:
        self.svc.books.settle("dropped", why)
        self.svc._log_kind(why, f"action request dropped: {why}", self.svc.books.dropped[why])
        self.svc._reply_err(query, why, f"not answered: {why}", False)
        _finish(query)

    def _handle(self, endpoints: ActionEndpoints, what: str, key: str, query) -> None:
        svc = self.svc
        held = False
        try:
            size = len(query.payload) if query.payload is not None else 0
            if size > svc.max_payload_bytes:
                raise Reject("oversize", f"{size} bytes > {svc.max_payload_bytes}")
            att = query.attachment.to_bytes() if query.attachment is not None else None
            try:
                reply_att = svc.node.reply_attachment(att)
            except ValueError as exc:
                raise Reject("malformed", str(exc)) from None
            payload = query.payload.to_bytes() if query.payload is not None else b""
            msg = endpoints.decode(what, payload)

            def reply(body: bytes) -> None:
                svc._send_reply(query, key, body, None, reply_att)
                # The asker's get ends with the reply, not when the work behind it does (a
                # ComputePathToPose goal is planned on after its acceptance went out).
                _finish(query)

            if what == "send_goal":
                self._send_goal(endpoints, msg, reply)
            elif what == "cancel_goal":
                self._cancel(endpoints, msg, reply)
            else:
                held = self._get_result(endpoints, msg, query, reply)
        except _Answered as exc:  # `accepted = false` went out already
            svc._rejected(exc.kind, f"{endpoints.names[what]}: goal refused: {exc}")
        except (Reject, MessageError) as exc:
            svc._rejected(exc.kind, f"{endpoints.names[what]}: {exc}")
            svc._reply_err(query, exc.kind, str(exc), False)
        except Exception as exc:  # noqa: BLE001 - a bug: counted, logged, the worker goes on
            svc._internal(exc, endpoints.names[what])
            svc._reply_err(query, "internal", f"{type(exc).__name__}: {exc}", False)
        else:
            svc.books.settle("accepted")
        finally:
            if not held:
                _finish(query)

    def _get_result(self, endpoints: ActionEndpoints, msg, query, reply) -> bool:
        """Answer or hold; True when held (the query stays open until the goal ends)."""
        uuid = bytes(msg.goal_id.uuid)

        def respond(status: int, result) -> None:
            if result is None:
                result = self._empty_result(endpoints)
            body = endpoints.msg("GetResult_Response")(status=status, result=result)
            reply(endpoints.encode("get_result", body))

        how = endpoints.book.result(uuid, respond)
        if how == "full":
            raise Reject("queue_full", f"{MAX_WAITING_RESULTS} get_result requests wait already")
        return how == "held"

    def _empty_result(self, endpoints: ActionEndpoints, code: int = 0, why: str = ""):
        if endpoints is self.nav:
            return endpoints.msg("Result")(error_code=code, error_msg=why)
        return endpoints.msg("Result")(
            path=convert.path(self.types, np.zeros((0, 3)), self.svc._stamp(), self.map_frame),
            planning_time=duration(self.types, 0.0),
            error_code=code,
            error_msg=why,
        )

    def _goal_response(self, endpoints: ActionEndpoints, accepted: bool, stamp_ns: int) -> bytes:
        body = endpoints.msg("SendGoal_Response")(
            accepted=accepted, stamp=convert.ros_time(self.types, stamp_ns * 1e-9)
        )
        return endpoints.encode("send_goal", body)

    def _send_goal(self, endpoints: ActionEndpoints, msg, reply) -> None:
        uuid = bytes(msg.goal_id.uuid)
        self._count("goals")
        if endpoints is self.nav:
            ok, why = self.navigate(uuid, msg.goal, reply)
        else:
            ok, why = self.compute_path(uuid, msg.goal, reply)
        if not ok:
            self._count("refused")
            reply(self._goal_response(endpoints, False, 0))
            raise_refused(why)

    def _cancel(self, endpoints: ActionEndpoints, msg, reply) -> None:
        uuid = bytes(msg.goal_info.goal_id.uuid)
        stamp = msg.goal_info.stamp
        code, targets = endpoints.book.cancel(uuid, int(stamp.sec) * 10**9 + int(stamp.nanosec))
        if targets:
            endpoints.publish_status()
        T = self.types.msg
        body = T("action_msgs/srv/CancelGoal_Response")(
            return_code=code,
            goals_canceling=[goal_info(self.types, g.uuid, g.stamp_ns) for g in targets],
        )
        # The response goes first (rclcpp_action answers, then executes the cancel).
        reply(endpoints.encode("cancel_goal", body))
        for g in targets:
            if not self.jobs.submit(lambda g=g: self._carry_out_cancel(endpoints, g)):
                self._carry_out_cancel(endpoints, g)  # never left CANCELING for want of a worker

    def _carry_out_cancel(self, endpoints: ActionEndpoints, g: Goal) -> None:
        if endpoints is self.nav:
            try:
                answer = request(
                    self.svc.session,
                    keys.explorer_goal_cancel(self.svc.robot),
                    {"id": g.uuid.hex()},
                    QUERY_TIMEOUT_S,
                )
            except QueryError as exc:
                # The goal stays CANCELING: the explorer's feedback (or its silence) ends it.
                self.svc.note("cancel_failed", f"NavigateToPose cancel: {exc}")
                return
            if not (isinstance(answer, dict) and answer.get("canceled")):
                why = answer.get("reason", "") if isinstance(answer, dict) else ""
                self.svc.log.info("explorer did not cancel %s: %s", g.uuid.hex(), why)
        self._count("canceled")
        self._end(endpoints, g.uuid, STATUS_CANCELED, self._empty_result(endpoints, 0, "canceled"))

    def _end(self, endpoints: ActionEndpoints, uuid: bytes, status: int, result) -> None:
        if endpoints.book.finish(uuid, status, result):
            endpoints.publish_status()

    # -- NavigateToPose -------------------------------------------------------------------------

    def world_pose(self, frame: str, x: float, y: float, yaw: float):
        """A goal's pose in the world frame; NoTransform for one in the base frame before the
        robot's first pose."""
        if frame in self.world_frames:  # one world: map -> odom is the identity
            return x, y, yaw
        pose = self.svc._last_pose
        if pose is None:
            raise NoTransform(
                f"no transform from {frame} to {self.world_frames[0]}: no pose of the robot yet"
            )
        return to_world(x, y, yaw, (float(pose.position[0]), float(pose.position[1]), pose.yaw))

    def navigate(self, uuid: bytes, goal, reply) -> tuple[bool, str]:
        """Hand a NavigateToPose goal to the explorer; (accepted, why not)."""
        try:
            frame, x, y, yaw = navigate_goal_checked(goal, self.frames)
        except ValueError as exc:
            return False, f"value: {exc}"
        # One goal at a time, in the order the explorer takes them: the last one it accepted is
        # the one that runs, here as there.
        with self._nav_lock:
            return self._navigate(uuid, goal, reply, frame, x, y, yaw)

    def _navigate(self, uuid: bytes, goal, reply, frame: str, x: float, y: float, yaw: float):
        book = self.nav.book
        stamp_ns = time.time_ns()
        # In the book (not yet on the status topic) before the explorer is asked: its first
        # feedback may come before its answer.
        if book.add(uuid, goal, stamp_ns) is None:
            return False, "refused: goal id in use, or too many goals held"
        try:
            x, y, yaw = self.world_pose(frame, x, y, yaw)
        except NoTransform as exc:
            # Nav2's navigator accepts it, fails to transform it and aborts it
            self._count("accepted")
            reply(self._goal_response(self.nav, True, stamp_ns))
            self._end(
                self.nav, uuid, STATUS_ABORTED, self._empty_result(self.nav, NAV_TF_ERROR, str(exc))
            )
            return True, ""
        self._explorer_ids[uuid.hex()] = uuid
        body = explorer_goal(uuid.hex(), x, y, yaw, self.no_path_s)
        try:
            answer = request(
                self.svc.session, keys.explorer_goal(self.svc.robot), body, QUERY_TIMEOUT_S
            )
            why = explorer_refusal(answer)
        except QueryError as exc:
            why = f"no_explorer: {exc}"
        if why:
            book.discard(uuid)
            self._explorer_ids.pop(uuid.hex(), None)
            return False, why
        self._count("accepted")
        reply(self._goal_response(self.nav, True, stamp_ns))
        book.set_status(uuid, STATUS_EXECUTING)  # unless its feedback has ended it already
        # Nav2 ends the goal a new one pre-empts ABORTED.
        for other in book.running():
            if other.uuid != uuid:
                why = f"preempted by goal {uuid.hex()}"
                book.finish(other.uuid, STATUS_ABORTED, self._empty_result(self.nav, 0, why))
        self.nav.publish_status()
        return True, ""

    def on_goal_pose(self, payload: bytes) -> None:
        """/goal_pose (RViz2's "2D Goal Pose"): a NavigateToPose goal of a fresh id."""
        try:
            msg = self.types.deserialize(payload, POSE_STAMPED)
        except Exception as exc:  # noqa: BLE001 - any CDR that is not a PoseStamped
            raise MessageError("malformed", f"not a {POSE_STAMPED}: {type(exc).__name__}") from None
        try:
            goal_pose_checked(msg, self.frames)
        except ValueError as exc:
            raise Reject("value", f"/goal_pose: {exc}") from None
        goal = self.nav.msg("Goal")(pose=msg, behavior_tree="")
        uuid = os.urandom(16)

        def go():
            ok, why = self.navigate(uuid, goal, lambda body: None)
            if not ok:
                self.svc.note("goal_pose_refused", f"/goal_pose: {why}")

        if not self.jobs.submit(go):
            self.svc.note("goal_pose_refused", "/goal_pose: the action workers are busy")

    def on_explorer_feedback(self, payload: bytes) -> None:
        """The explorer's goal feedback (main loop): NavigateToPose feedback and its end."""
        fb = ExplorerFeedback.parse(payload)
        uuid = self._explorer_ids.get(fb.id)
        g = self.nav.book.get(uuid) if uuid is not None else None
        if g is None or g.status in TERMINAL:
            return  # another goal's, or one already ended here (pre-empted, canceled)
        now = self.nav.book.clock()
        g.seen_at = now
        if fb.pose is None:
            # the explorer has no pose yet: Nav2's navigator skips its feedback when it cannot
            # read the robot's pose, rather than send a made-up pose or a NaN distance
            self._count("feedback_without_pose")
        end = fb.end()
        if fb.pose is not None:
            self._progress = Progress(uuid, fb.pose, fb.remaining, fb.nav_time, fb.recoveries, now)
            self._send_feedback(now)  # at once (the last word too): the ticks go on from it
        if end is not None:
            if self._progress is not None and self._progress.uuid == uuid:
                self._progress = None
            self._end(self.nav, uuid, end[0], self._empty_result(self.nav, end[1], fb.reason))

    def on_pose(self, x: float, y: float) -> None:
        """The robot's pose (the service's loop): how far it has gone since the explorer's
        last feedback."""
        if self._progress is not None:
            self._progress.drove_to(x, y)

    def _send_feedback(self, now: float) -> None:
        """NavigateToPose feedback for the running goal: the robot's latest pose, and the
        explorer's remaining distance less the way driven since it said so."""
        p = self._progress
        g = self.nav.book.get(p.uuid) if p is not None else None
        if g is None or g.status not in (STATUS_EXECUTING, STATUS_CANCELING):
            return
        self._next_feedback = now + 1.0 / FEEDBACK_HZ
        pose = self.svc._last_pose
        if pose is not None:
            xy, yaw = pose.position[:2], pose.yaw
        else:
            xy, yaw = p.pose[:2], p.pose[2]
        remaining = p.remaining_m()
        fb_msg = self.nav.msg("Feedback")(
            current_pose=convert.pose_stamped(
                self.types, xy, yaw, self.svc._stamp(), self.map_frame
            ),
            navigation_time=duration(self.types, p.navigation_time_s(now)),
            estimated_time_remaining=duration(self.types, remaining / self.speed_mps),
            number_of_recoveries=p.recoveries_int16(),
            distance_remaining=remaining,
        )
        self.nav.publish_feedback(p.uuid, fb_msg)
        self._count("feedback")

    def tick(self) -> None:
        """The service's loop: results expire, a navigation goal the explorer went silent on
        is aborted."""
        for endpoints in (self.nav, self.plan):
            if endpoints.book.expire():
                endpoints.publish_status()
        for gid, uuid in list(self._explorer_ids.items()):
            if self.nav.book.get(uuid) is None:  # expired (or never accepted)
                self._explorer_ids.pop(gid, None)
        now = self.nav.book.clock()
        if self._progress is not None and now >= self._next_feedback:
            self._send_feedback(now)
        for g in self.nav.book.running():
            if now - g.seen_at > FEEDBACK_TIMEOUT_S:
                why = f"no feedback from the explorer for {FEEDBACK_TIMEOUT_S:g} s"
                self.svc.note("goal_silent", f"NavigateToPose {g.uuid.hex()}: {why}")
                self._end(self.nav, g.uuid, STATUS_ABORTED, self._empty_result(self.nav, 0, why))

    # -- ComputePathToPose ----------------------------------------------------------------------

    def compute_path(self, uuid: bytes, goal, reply) -> tuple[bool, str]:
        """Accept a ComputePathToPose goal and plan it on this worker; (accepted, why not)."""
        try:
            ends = compute_path_goal_checked(goal, self.frames)
        except ValueError as exc:
            return False, f"value: {exc}"
        book = self.plan.book
        stamp_ns = time.time_ns()
        if book.add(uuid, goal, stamp_ns) is None:
            return False, "refused: goal id in use, or too many goals held"
        self._count("accepted")
        reply(self._goal_response(self.plan, True, stamp_ns))
        book.set_status(uuid, STATUS_EXECUTING)
        self.plan.publish_status()
        t0 = time.monotonic()
        if why := planner_refusal(goal.planner_id):
            self._plan_end(uuid, None, PLAN_INVALID_PLANNER, why, t0)
            return True, ""
        try:
            gx, gy, gyaw = self.world_pose(*ends[0])
            if goal.use_start:
                sx, sy, _ = self.world_pose(*ends[1])
        except NoTransform as exc:
            self._plan_end(uuid, None, PLAN_TF_ERROR, str(exc), t0)
            return True, ""
        if not goal.use_start:
            pose = self.svc._last_pose
            if pose is None:
                self._plan_end(uuid, None, PLAN_UNKNOWN, "no robot pose yet (use_start)", t0)
                return True, ""
            sx, sy = float(pose.position[0]), float(pose.position[1])
        ask = PathRequest(
            request_id=f"ros2-{uuid.hex()[:12]}",
            start=[sx, sy],
            goal=[gx, gy],
            allow_unknown=self.through_unknown,
            unknown_cost=self.unknown_cost,
        )
        try:
            answer = self._ask_planner(ask, t0)
        except QueryError as exc:
            code = planner_failure_code(exc.kind, time.monotonic() - t0, QUERY_TIMEOUT_S)
            self._plan_end(uuid, None, code, str(exc), t0)
            return True, ""
        if not isinstance(answer, PathReply):
            self._plan_end(uuid, None, PLAN_UNKNOWN, f"planner answered {type(answer)}", t0)
        elif not answer.ok:
            why = f"{answer.error}: {answer.message}"
            self._plan_end(uuid, None, plan_error_code(answer.error, answer.message), why, t0)
        else:
            self._plan_end(uuid, answer.path, 0, "", t0, gyaw)
        return True, ""

    def _ask_planner(self, ask: PathRequest, t0: float):
        """The planner's answer within QUERY_TIMEOUT_S of `t0`. While no planner answers at all
        (it is still starting), asked again until then, as Nav2's behaviour tree waits for its
        planner server (`wait_for_service_timeout`)."""
        while True:
            left = QUERY_TIMEOUT_S - (time.monotonic() - t0)
            try:
                return request(self.svc.session, keys.path_query(self.svc.robot), ask, left)
            except QueryError as exc:
                if exc.kind != "no_reply" or left < PLANNER_RETRY_S or self.svc.stopping:
                    raise
            time.sleep(PLANNER_RETRY_S)

    def _plan_end(self, uuid: bytes, path, code: int, why: str, t0: float, yaw=None) -> None:
        """End a ComputePathToPose goal; its path's last pose faces `yaw` (the goal's), as
        Nav2's planners leave it."""
        path = np.zeros((0, 3)) if path is None else path
        result = self.plan.msg("Result")(
            path=convert.path(self.types, path, time.time(), self.map_frame, final_yaw=yaw),
            planning_time=duration(self.types, time.monotonic() - t0),
            error_code=code,
            error_msg=why,
        )
        self._end(self.plan, uuid, STATUS_SUCCEEDED if code == 0 else STATUS_ABORTED, result)

    def status_details(self) -> dict:
        with self._count_lock:
            counts = dict(self.counts)
        return {
            **counts,
            "navigate_running": announced(self.nav.book),
            "compute_path_running": announced(self.plan.book),
        }


def raise_refused(why: str) -> None:
    """A refused goal is answered (`accepted = false`) and counted rejected of its kind."""
    kind, _, message = why.partition(": ")
    raise _Answered(kind if kind in ("value", "refused", "no_explorer") else "refused", message)


class _Answered(Reject):
    """A rejection whose ROS response was already sent: no error reply follows."""


def _finish(query) -> None:
    try:
        query.drop()
    except Exception:  # noqa: BLE001 - already finished, or the session is closing
        pass
