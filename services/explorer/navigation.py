"""Goals the explorer is sent ("go to this pose", `explorer/goal`): their check, their states and
their feedback. Part of `exploration.Explorer`; no wiring.

A goal is accepted or refused at once (`parse_goal`, then `Navigating.accept_goal`, which also
refuses a goal on a node known to be an obstacle, a safety zone or not traversable). A goal that
asks `accept_unreachable` (the ROS 2 actions do: Nav2's navigator accepts every well-formed goal
and aborts the ones it cannot reach) is accepted there instead and ends "aborted" at once.

An accepted goal pre-empts the running one, which ends "preempted". While a goal runs,
exploration pauses: the explorer's own machinery drives to it (`plan` asks for a path, `control`
follows it, and it re-plans as it does for a view: the path blocked, stuck, every
`replan_period_s` as the map grows).
A goal ends:

- "succeeded": the robot is within the goal's tolerance (and faces its yaw, when it has one);
- "aborted": no path to it for `goal_timeout_s` (or the goal's own `no_path_timeout_s`), or not
  reached `goal_time_budget_s` after it was accepted, or its node became an obstacle (outside the
  graph or on an obstacle from the start, with `accept_unreachable`);
- "canceled": a cancel for it (the robot stops at once);
- "preempted": a newer goal was accepted.

An aborted goal says why in `error` as well as in words: "out_of_bounds", "goal_blocked",
"no_path", "time_budget" or "stopped" (ERRORS).

Then exploration resumes if the explorer was exploring and `resume_after_goal`; an explorer in
`mode = "navigate"` never explores and waits for the next goal. Times are robot time.
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass

import numpy as np

from smana.services.explorer import frontier as fr
from smana.services.explorer.driving import BACK_OFF_S
from smana.services.explorer.follower import wrap_angle

STATES = ("active", "succeeded", "aborted", "canceled", "preempted")
ERRORS = ("out_of_bounds", "goal_blocked", "no_path", "time_budget", "stopped")
ID_MAX_CHARS = 64
GOAL_KEYS = {"x", "y", "yaw", "tolerance_m", "id", "no_path_timeout_s", "accept_unreachable"}
NO_PATH_TIMEOUT_MAX_S = 3600.0


class GoalRefused(ValueError):
    """A goal or a cancel refused: `kind` counts it in the service's books, the message is the
    reply's reason."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind = kind


@dataclass
class GoalSpec:
    """A goal as it was asked for, checked (`parse_goal`)."""

    x: float
    y: float
    yaw: float | None
    tolerance_m: float
    id: str
    no_path_timeout_s: float | None = None  # None: the config's goal_timeout_s
    accept_unreachable: bool = False
    # (error, reason) of a goal accepted although it cannot be reached (outside the graph)
    unreachable: tuple[str, str] | None = None


@dataclass
class NavGoal:
    spec: GoalSpec
    t_accepted: float | None  # robot time; None: accepted before the first pose (set by it)
    state: str = "active"
    reason: str = ""
    error: str = ""  # why it was aborted (ERRORS), "" otherwise
    recoveries: int = 0
    t_no_path: float | None = None  # robot time since when no path to it was found
    t_ended: float | None = None

    @property
    def active(self) -> bool:
        return self.state == "active"

    @property
    def id(self) -> str:
        return self.spec.id


# A heading beyond this many radians is no heading anyone meant (1e308 wraps to noise), and a
# tolerance under a millimetre is one the robot can never meet (5e-324 m): both refused.
YAW_MAX_RAD = 100.0
TOLERANCE_MIN_M = 1e-3


def _number(body: dict, name: str, optional: bool) -> float | None:
    v = body.get(name)
    if v is None:
        if optional:
            return None
        raise GoalRefused("malformed", f"{name} is missing")
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise GoalRefused("malformed", f"{name} must be a number, got {type(v).__name__}")
    try:
        f = float(v)  # a JSON integer past 1e308 does not fit a float
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise GoalRefused(
            "value", f"{name} must be finite, got {'a huge integer' if isinstance(v, int) else v}"
        )
    return f


def check_goal_id(v) -> str:
    if not isinstance(v, str) or not 1 <= len(v) <= ID_MAX_CHARS or not v.isprintable():
        raise GoalRefused("malformed", f"id must be 1 to {ID_MAX_CHARS} printable characters")
    return v


def parse_goal(
    body, bounds_min_xy, bounds_max_xy, default_tolerance_m: float, max_tolerance_m: float
) -> GoalSpec:
    """A goal query's map, checked: x and y finite and inside the navigation graph's bounds, yaw
    finite within +-YAW_MAX_RAD or None, tolerance_m in [TOLERANCE_MIN_M, max_tolerance_m] or None
    (the default), id 1 to 64 printable characters or None (one is made up), no_path_timeout_s in
    [0, NO_PATH_TIMEOUT_MAX_S] or None, accept_unreachable a bool or None. GoalRefused otherwise;
    unknown keys are refused too (a misspelt "tolerance" must not pass for the default). With
    `accept_unreachable`, a goal outside the bounds is not refused: its spec carries why it
    cannot be reached (`unreachable`)."""
    if not isinstance(body, dict):
        raise GoalRefused("malformed", "a goal is a map {x, y, yaw, tolerance_m, id}")
    extra = sorted(str(k) for k in body if k not in GOAL_KEYS)
    if extra:
        raise GoalRefused("malformed", f"unknown key(s) {', '.join(extra)}")
    x, y = _number(body, "x", False), _number(body, "y", False)
    yaw = _number(body, "yaw", True)
    tol = _number(body, "tolerance_m", True)
    no_path = _number(body, "no_path_timeout_s", True)
    accept = body.get("accept_unreachable")
    if accept is not None and not isinstance(accept, bool):
        raise GoalRefused("malformed", "accept_unreachable must be true or false")
    if yaw is not None and abs(yaw) > YAW_MAX_RAD:
        raise GoalRefused("value", f"yaw must be within +-{YAW_MAX_RAD:g} rad, got {yaw:g}")
    if no_path is not None and not 0.0 <= no_path <= NO_PATH_TIMEOUT_MAX_S:
        raise GoalRefused(
            "value",
            f"no_path_timeout_s must be in [0, {NO_PATH_TIMEOUT_MAX_S:g}] s, got {no_path:g}",
        )
    lo, hi = bounds_min_xy, bounds_max_xy
    unreachable = None
    if not (lo[0] <= x < hi[0] and lo[1] <= y < hi[1]):
        why = (
            f"({x:g}, {y:g}) is outside the navigation graph "
            f"[{lo[0]:g}, {hi[0]:g}) x [{lo[1]:g}, {hi[1]:g})"
        )
        if not accept:
            raise GoalRefused("out_of_bounds", why)
        unreachable = ("out_of_bounds", why)
    if tol is None:
        tol = float(default_tolerance_m)
    elif not TOLERANCE_MIN_M <= tol <= max_tolerance_m:
        raise GoalRefused(
            "value",
            f"tolerance_m must be in [{TOLERANCE_MIN_M:g}, {max_tolerance_m:g}] m, got {tol:g}",
        )
    gid = body.get("id")
    gid = uuid.uuid4().hex[:12] if gid is None else check_goal_id(gid)
    yaw = None if yaw is None else wrap_angle(yaw)
    return GoalSpec(x, y, yaw, tol, gid, no_path, bool(accept), unreachable)


def parse_cancel(body) -> str | None:
    """A cancel query's map: {"id": str} or {"id": None} (or {}: the current goal)."""
    if not isinstance(body, dict):
        raise GoalRefused("malformed", "a cancel is a map {id}")
    extra = sorted(str(k) for k in body if k != "id")
    if extra:
        raise GoalRefused("malformed", f"unknown key(s) {', '.join(extra)}")
    gid = body.get("id")
    return None if gid is None else check_goal_id(gid)


class Navigating:
    """The part of `Explorer` that drives to the goals it is sent. It uses the state
    `Explorer.__init__` sets (`config`, `grid`, `pose`, `goal`, `follower`, `nav`, `exploring`,
    `nav_changes`, ...)."""

    @property
    def nav_active(self) -> bool:
        return self.nav is not None and self.nav.active

    def accept_goal(self, spec: GoalSpec) -> NavGoal:
        """Start driving to `spec` (exploration pauses); the running goal ends "preempted".
        GoalRefused, with nothing changed, when the goal's node is known and not traversable,
        unless the goal accepts that: then it is accepted and ends "aborted" at once, as one
        outside the graph does (`spec.unreachable`)."""
        unreachable = spec.unreachable
        if unreachable is None:
            try:
                self._check_goal_node(spec.x, spec.y)
            except GoalRefused as exc:
                if not spec.accept_unreachable:
                    raise
                unreachable = (exc.kind, str(exc))
        if self.nav_active:
            self._end_nav("preempted", f"pre-empted by goal {spec.id}")
        self._set_goal(None)  # the view (or the old goal's path) is dropped
        self._spin = None
        self.nav = NavGoal(spec, self.t_now if self.pose is not None else None)
        self._t_last_plan = -math.inf  # plan at once
        self.nav_changes.append(self.nav_feedback())
        if unreachable is not None:
            self._end_nav("aborted", unreachable[1], unreachable[0])
        return self.nav

    def cancel_goal(self, gid: str | None) -> NavGoal:
        """Cancel the running goal (`gid` None or its id): the robot stops at the next command.
        GoalRefused when there is none or `gid` names another."""
        if not self.nav_active:
            last = "" if self.nav is None else f" (goal {self.nav.id} {self.nav.state})"
            raise GoalRefused("no_goal", f"no goal is running{last}")
        if gid is not None and gid != self.nav.id:
            raise GoalRefused("unknown_goal", f"goal {gid} is not the running one")
        self._end_nav("canceled", "canceled")
        return self.nav

    def abort_goal(self, reason: str) -> None:
        """End the running goal "aborted" (the explorer is stopping), if one runs."""
        if self.nav_active:
            self._end_nav("aborted", reason, "stopped")

    def nav_feedback(self) -> dict:
        """The feedback of the current (or last) goal, as `explorer/goal/feedback` carries it."""
        n = self.nav
        s = n.spec
        pose = [float(v) for v in self.pose] if self.pose is not None else None
        if n.active and self.goal is not None and self.follower.active:
            # along the path from the robot's nearest point on it
            p = self.follower.remaining
            to_path = 0.0 if pose is None else math.hypot(pose[0] - p[0, 0], pose[1] - p[0, 1])
            remaining = self.follower.remaining_length_m() + to_path
        elif pose is not None:
            remaining = math.hypot(s.x - pose[0], s.y - pose[1])
        else:
            remaining = math.nan
        end = n.t_ended if n.t_ended is not None else self.t_now
        since = end if n.t_accepted is None else n.t_accepted
        return {
            "id": n.id,
            "state": n.state,
            "goal": [s.x, s.y, s.yaw],
            "pose": pose,
            "distance_remaining_m": float(remaining),
            "navigation_time_s": max(0.0, float(end - since)),
            "recoveries": n.recoveries,
            "reason": n.reason,
            "error": n.error,
        }

    def nav_state(self) -> dict | None:
        """The goal's part of the explorer's state: None, or its id, state and reason."""
        if self.nav is None:
            return None
        return {"id": self.nav.id, "state": self.nav.state, "reason": self.nav.reason}

    # -- inside the loop ------------------------------------------------------------------------

    def _nav_wants_plan(self) -> str | None:
        """`wants_plan` while a goal runs: ends it when reached or out of time, else says why a
        path is needed now (or None)."""
        n, t = self.nav, self.t_now
        s = n.spec
        if self._nav_reached():
            self._end_nav("succeeded", "")
            return None
        if t - n.t_accepted > self.config.goal_time_budget_s:
            why = f"not reached in {self.config.goal_time_budget_s:g} s"
            self._end_nav("aborted", why, "time_budget")
            return None
        no_path_s = self.config.goal_timeout_s
        if s.no_path_timeout_s is not None:
            no_path_s = s.no_path_timeout_s
        if n.t_no_path is not None and t - n.t_no_path >= no_path_s:
            self._end_nav("aborted", f"no path for {no_path_s:g} s", "no_path")
            return None
        if self._goal_node_blocked(s.x, s.y):
            self._end_nav("aborted", "the goal's node is an obstacle now", "goal_blocked")
            return None
        if self._spin is not None or self._back_off_until is not None:
            return None
        if self.goal is None:
            if t - self._t_last_plan < self.config.empty_retry_s:
                return None
            return "goal"
        if self._path_blocked():
            self.n_replans_blocked += 1
            return "blocked"
        if self._stuck():
            n.recoveries += 1
            self.n_stuck += 1
            self._back_off_until = t + BACK_OFF_S
            return "stuck"
        if t - self._t_last_plan >= self.config.replan_period_s:
            return "periodic"  # the map grew: a better (or the only) path may be there now
        return None

    def _plan_nav(self, path_cost, reason: str):
        """A path to the goal from where the robot is: from the start node of the goal's
        component when it has one, else from the nearest (the path then crosses unknown nodes,
        with `goal_through_unknown`). No path: the robot stops and the plan is tried again."""
        g, n = self.grid, self.nav
        x, y, _ = self.pose
        free = fr.traversable_mask(g.labels, g.flags, self.traversable_lut)
        comp, _, starts = self._starts(free, (x, y))
        gxy = np.array([n.spec.x, n.spec.y])
        gc = np.array(g.cell_of(gxy))
        start = None
        if g.inside(gc).all() and int(comp[gc[0], gc[1]]) in starts:
            start = starts[int(comp[gc[0], gc[1]])]
        elif starts:
            start = next(iter(starts.values()))  # the nearest: they are found nearest first
        here = g.cell_of((x, y))
        if start is None or start == here:
            start_xy = np.array([x, y])
        else:
            start_xy = g.centres(np.array(start))
        reply = path_cost(start_xy, gxy, allow_unknown=self.config.goal_through_unknown)
        if reply is None:
            if n.t_no_path is None:
                n.t_no_path = self.t_now
            self._set_goal(None, count=False)
            return None
        n.t_no_path = None
        cost, path = reply
        path = np.asarray(path, float)[:, :2]
        if math.hypot(x - start_xy[0], y - start_xy[1]) > 1e-6:
            path = np.vstack([[x, y], path])
        choice = fr.ViewChoice(gc, gxy, n.spec.yaw, 0.0, float(cost), 0.0, path, 1, 0)
        mark = self._progress_mark
        self._set_goal(choice, count=False, tolerance_m=n.spec.tolerance_m)
        if mark is not None and reason in ("periodic", "blocked"):
            # a new path every replan_period_s must not hide a robot that makes no progress
            self._progress_mark = mark
        return choice

    def _nav_arrived(self) -> None:
        """The follower says the path's end is reached (and faced)."""
        self._set_goal(None, count=False)
        if self._nav_reached():
            self._end_nav("succeeded", "")
        else:
            self._t_last_plan = -math.inf  # not quite there (a path's end off the goal): again

    def _nav_reached(self) -> bool:
        if self.pose is None:
            return False
        x, y, yaw = self.pose
        s = self.nav.spec
        if math.hypot(s.x - x, s.y - y) > s.tolerance_m:
            return False
        tol = self.config.follower.final_yaw_tolerance_rad
        return s.yaw is None or abs(wrap_angle(s.yaw - yaw)) <= tol + 1e-9

    def _end_nav(self, state: str, reason: str, error: str = "") -> None:
        assert state in STATES[1:] and (error in ERRORS if state == "aborted" else not error)
        n = self.nav
        n.state, n.reason, n.error, n.t_ended = state, reason, error, self.t_now
        self._set_goal(None, count=False)
        self._spin = None
        self._back_off_until = None if state in ("canceled", "preempted") else self._back_off_until
        # exploration goes on after a goal only if it went on before and is meant to
        self.exploring = self.exploring and self.config.resume_after_goal
        self._t_last_plan = -math.inf
        self.nav_changes.append(self.nav_feedback())

    def _check_goal_node(self, x: float, y: float) -> None:
        if self._goal_node_blocked(x, y):
            raise GoalRefused(
                "goal_blocked",
                f"({x:g}, {y:g}) is on a known obstacle, its safety zone or ground the robot "
                "may not enter",
            )

    def _goal_node_blocked(self, x: float, y: float) -> bool:
        """The node under (x, y) is known and not traversable (an obstacle, its safety zone or
        a class the robot may not enter)."""
        g = self.grid
        if g is None:
            return False
        c = np.array(g.cell_of((x, y)))
        if not g.inside(c).all():
            return False
        flags, label = g.flags[c[0], c[1]], g.labels[c[0], c[1]]
        if not flags & fr.KNOWN:
            return False
        free = fr.traversable_mask(np.array([[label]]), np.array([[flags]]), self.traversable_lut)
        return not bool(free[0, 0])
