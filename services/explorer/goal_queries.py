"""The explorer's goal queries and goal feedback as plain maps (no zenoh: service.py puts them on
the wire; navigation.py has the contract): a goal (`explorer/goal`) accepted, or refused with
its reply; a cancel (`explorer/goal/cancel`); and the feedback due on `explorer/goal/feedback`,
every change of a goal's state, then its progress once every `goal_feedback_period_s` while it
runs. A query by a wildcard selector (`smana/r1/**`, a tool listing everything) reaches the
queryables too: only a query on the exact key drives the robot, whatever the router lets through
(refused `selector`)."""

from __future__ import annotations

from smana.common.config.explorer import ExplorerConfig
from smana.common.config.navgraph import NavgraphConfig
from smana.common.messages import MessageError
from smana.services.explorer.navigation import (
    GoalRefused,
    GoalSpec,
    NavGoal,
    check_goal_id,
    parse_cancel,
    parse_goal,
)


def _exact(key: str, expected: str) -> None:
    if key != expected:
        raise GoalRefused("selector", f"{key} is not {expected}")


def _refused(exc: GoalRefused, reply: dict) -> GoalRefused:
    exc.reply = reply
    return exc


class GoalQueries:
    """The goals `core` (an `exploration.Explorer`) is sent, as queries and feedback."""

    def __init__(self, core, config: ExplorerConfig, navgraph: NavgraphConfig):
        self.core = core
        self.config = config
        self.navgraph = navgraph
        self.next_feedback = 0.0

    def goal(self, body, key: str, expected: str) -> tuple[GoalSpec, dict]:
        """A goal query's body (its map, or the MessageError decoding it raised) on `key`:
        accepted (it pre-empts the running one) with its reply, or GoalRefused with nothing
        changed, its `reply` the refusal's map (which echoes the goal's id only when it is a
        valid one)."""
        gid = body.get("id") if isinstance(body, dict) else None
        try:
            gid = check_goal_id(gid)
        except GoalRefused:
            gid = None
        try:
            _exact(key, expected)
            if isinstance(body, MessageError):
                raise GoalRefused("malformed", str(body))
            if self.core.done:
                raise GoalRefused(
                    "finished", f"the explorer is finishing ({self.core.done_reason})"
                )
            nav = self.navgraph
            spec = parse_goal(
                body,
                nav.bounds_min_xy,
                nav.bounds_max_xy,
                self.config.follower.goal_tolerance_m,
                self.config.goal_max_tolerance_m,
            )
            self.core.accept_goal(spec)
        except GoalRefused as exc:
            reply = {"accepted": False, "id": gid or "", "reason": str(exc), "kind": exc.kind}
            raise _refused(exc, reply) from None
        return spec, {"accepted": True, "id": spec.id, "reason": ""}

    def cancel(self, body, key: str, expected: str) -> tuple[NavGoal, dict]:
        """A cancel query's body (as `goal` takes it) on `key`: the running goal canceled (the
        robot stops at once) with the reply, or GoalRefused, its `reply` the refusal's map."""
        gid = None
        try:
            _exact(key, expected)
            if isinstance(body, MessageError):
                raise GoalRefused("malformed", str(body))
            gid = parse_cancel(body)
            nav = self.core.cancel_goal(gid)
        except GoalRefused as exc:
            raise _refused(exc, {"canceled": False, "id": gid, "reason": str(exc)}) from None
        return nav, {"canceled": True, "id": nav.id, "reason": ""}

    def feedback(self, now: float) -> list[dict]:
        """The feedback due at `now` (monotonic seconds): every change of a goal's state since
        the last call, then (while one runs) its progress once a period."""
        out = list(self.core.nav_changes)
        self.core.nav_changes.clear()
        if self.core.nav_active and now >= self.next_feedback:
            self.next_feedback = now + self.config.goal_feedback_period_s
            out.append(self.core.nav_feedback())
        return out
