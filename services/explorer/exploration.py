"""The exploration loop without wiring: when to choose a new view, how to get there, when to stop.

`Explorer` holds the latest navigation-grid box, the robot's pose history and the current goal.
The service feeds it grids and poses, asks `wants_plan` each tick, runs `plan` with a path-cost
function (the planner over Zenoh) and sends what `control` returns to the robot. Everything here
is deterministic given its inputs, so a closed loop with a toy world runs in a unit test.

Decisions, in the order they are checked:
- no goal yet / goal reached (after a short dwell so the map catches up) -> plan;
- the remaining path crosses a node that became an obstacle or safety zone -> stop, plan;
- no progress along the path for `stuck_timeout_s` -> forget that goal for a while, plan;
- the goal's own view gain fell under `min_gain_m2` (seen on the way) -> plan;
- every `replan_period_s` -> plan, and switch only to a view better by `switch_margin_share`
  (nearest_frontier: keep the goal while it is still worth a look);
- no view worth it: spin once on the spot to look around, then give up after
  `done_after_empty` empty plans; or the time budget is over -> done.

Two ways to choose (`strategy`): "nbv", the paper's next-best view (`frontier.select_view` with
`frontier.ViewScore`), and "nearest_frontier", Yamauchi's baseline: the frontier node nearest by
travel over free nodes whose view is worth a look (`_nearest_frontier`).

Its parameters are the [explorer] config section as it is (`ExplorerConfig`, with its
[explorer.view] and [explorer.follower] tables); the names above are its keys.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from smana.common.config.explorer import ExplorerConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.follower import PurePursuit, wrap_angle
from smana.services.explorer.team import Team

# path_cost(start_xy, goal_xy) -> (cost, path (K, 2|3)) or None when there is no path
PathFn = Callable[[np.ndarray, np.ndarray], "tuple[float, np.ndarray] | None"]
# claim(goal_xy) -> (granted, the member holding a goal too near, that goal) (fleet members)
ClaimFn = Callable[[np.ndarray], "tuple[bool, str | None, np.ndarray | None]"]
MAX_CLAIMS_PER_PLAN = 3  # refused this often in one plan: wait for the next one
BACK_OFF_S = 2.0  # stuck: reverse this long at creep speed (when clear behind) before going on
BACK_OFF_M = 0.4  # how far behind the robot must be clear of known obstacles to reverse
GOAL_SEEN_CHECK_S = 1.0  # in a fleet, how often the goal's gain is checked between plans


@dataclass
class GridBox:
    """A dense box of the navigation graph, indexed [ix, iy]; node (ix, iy) covers
    [origin + i * res, origin + (i + 1) * res) on each axis."""

    origin_xy: np.ndarray
    resolution_m: float
    labels: np.ndarray
    flags: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.labels.shape

    def cell_of(self, xy) -> tuple[int, int]:
        ij = np.floor((np.asarray(xy, float)[:2] - self.origin_xy) / self.resolution_m)
        return int(ij[0]), int(ij[1])

    def cells_of(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, xy.shape[-1])[:, :2]
        return np.floor((xy - self.origin_xy) / self.resolution_m).astype(np.int64)

    def centres(self, cells: np.ndarray) -> np.ndarray:
        return self.origin_xy + (np.asarray(cells, float) + 0.5) * self.resolution_m

    def inside(self, cells: np.ndarray) -> np.ndarray:
        cells = np.asarray(cells).reshape(-1, 2)
        return (
            (cells[:, 0] >= 0)
            & (cells[:, 1] >= 0)
            & (cells[:, 0] < self.shape[0])
            & (cells[:, 1] < self.shape[1])
        )


@dataclass
class Goal:
    choice: fr.ViewChoice
    path_xy: np.ndarray
    t_set: float
    path_length_m: float


@dataclass
class PlanOutcome:
    reason: str
    chosen: fr.ViewChoice | None
    switched: bool
    n_frontier: int
    n_candidates: int
    candidates_xy: np.ndarray
    gains_m2: np.ndarray


class Explorer:
    """Next-best-view exploration state machine (see the module docstring)."""

    def __init__(
        self,
        config: ExplorerConfig,
        traversable_lut: np.ndarray,
        n_labels: int,
        cost_per_m_lower_bound: float = 1.0,
        cost_per_m_flat: float = 1.0,
        team: Team | None = None,
    ):
        """`config` is the [explorer] section as it is. `cost_per_m_lower_bound`: every path costs
        at least this much per metre of straight-line distance (from the planner's t_f and the
        class costs; 1.0 is always safe): it lets `select_view` skip hopeless path queries.
        `cost_per_m_flat`: the planner's cost of a metre on the cheapest flat ground, the unit
        path costs are scored in (both from `frontier.path_cost_scale`; 1.0 and 1.0 is a planner
        whose cost is the path length). `team`: the other fleet members (services/explorer/team.py),
        None for a robot alone."""
        if not (cost_per_m_flat > 0 and cost_per_m_lower_bound >= 0):
            raise ValueError("need cost_per_m_flat > 0 and cost_per_m_lower_bound >= 0")
        self.config = config
        self.team = team
        self._yield = False  # a member with the right of way held us too long: re-plan
        self._back_off_until: float | None = None  # reversing out of where it got stuck
        self._t_goal_check = -math.inf
        self.n_claims_refused = 0
        self.n_yields = 0
        self.cost_per_m_lower_bound = float(cost_per_m_lower_bound)
        self.cost_per_m_flat = float(cost_per_m_flat)
        self.traversable_lut = np.asarray(traversable_lut, bool)
        self.grid: GridBox | None = None
        self._fov: fr.FovModel | None = None
        self.follower = PurePursuit(config.follower)
        self.goal: Goal | None = None
        self._resumed_goal = False  # a goal from a checkpoint: its path found at the next pose
        self.pose: tuple[float, float, float] | None = None
        self.t_start: float | None = None
        self.t_now = 0.0
        self.distance_m = 0.0
        self.label_counts = np.zeros(max(n_labels, 1), np.int64)
        self.trajectory: list[tuple[float, float, float, float]] = []
        self._last_cell: tuple[int, int] | None = None
        self._t_last_plan = -math.inf
        self._t_arrived: float | None = None
        self._empty_plans = 0
        self._spin: dict | None = None
        self._spun_at: list[np.ndarray] = []
        self._blacklist: list[tuple[np.ndarray, float]] = []
        self._progress_mark: tuple[float, float] | None = None  # (t, remaining length)
        self.done_reason: str | None = None
        self.n_plans = 0
        self.n_goals = 0
        self.n_replans_blocked = 0
        self.n_stuck = 0
        self.last_outcome: PlanOutcome | None = None
        self.explored_m2 = 0.0
        self.frontier_size = 0
        # (t, explored m^2, frontier nodes, distance m) at every plan: the run's progress curve
        self.history: list[tuple[float, float, int, float]] = []

    # -- inputs ---------------------------------------------------------------------------------

    def update_grid(self, grid: GridBox) -> None:
        if self._fov is None or self._fov.resolution_m != grid.resolution_m:
            self._fov = fr.FovModel.build(grid.resolution_m, self.config.view)
            self.score = fr.ViewScore(
                self._fov.view_area_m2,
                self.cost_per_m_flat * self.config.view.max_range_m,
                self.config.path_cost_weight,
            )
        self.grid = grid

    def update_pose(self, x: float, y: float, yaw: float, t: float) -> None:
        """Track distance and the labels of the nodes travelled on (once per node entered)."""
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw) and math.isfinite(t)):
            raise ValueError("pose with non-finite values")
        if self.t_start is None and self.grid is not None:
            # the budget runs from the first pose with a map in hand: a stack still starting up
            # (numba compiling on a cold cache, a late navgraph) does not eat into it
            self.t_start = t
        if self.pose is not None:
            step = math.hypot(x - self.pose[0], y - self.pose[1])
            # a localisation jump is not travel: cap what one update may add
            if step < 1.0:
                self.distance_m += step
        self.pose = (x, y, yaw)
        self.t_now = t
        if self._resumed_goal and self.goal is not None:
            self._resumed_goal = False
            self.follower.skip_to_nearest(x, y)
            self._progress_mark = (t, self.follower.remaining_length_m())
        if not self.trajectory or t - self.trajectory[-1][0] >= 0.1:
            self.trajectory.append((t, x, y, yaw))
        if self.grid is not None:
            cell = self.grid.cell_of((x, y))
            if cell != self._last_cell and self.grid.inside(np.array(cell)).all():
                label = int(self.grid.labels[cell]) if self.grid.flags[cell] & fr.KNOWN else 0
                if label < self.label_counts.size:
                    self.label_counts[label] += 1
                self._last_cell = cell

    def resume(self, state: dict, trajectory: np.ndarray) -> None:
        """Carry on from a saved state (a restarted explorer in the same run): the distance,
        labels travelled, counters, progress history and trajectory so far, and the time budget
        already spent (measured from when the budget started, else the trajectory's first pose)."""
        self.distance_m = float(state.get("distance_m") or 0.0)
        for k, v in (state.get("label_counts") or {}).items():
            if 0 <= int(k) < self.label_counts.size:
                self.label_counts[int(k)] = int(v)
        self.n_goals = int(state.get("n_goals") or 0)
        self.n_plans = int(state.get("n_plans") or 0)
        self.history = [tuple(h) for h in state.get("history") or []]
        traj = np.asarray(trajectory, float).reshape(-1, 4)
        self.trajectory = [tuple(r) for r in traj]
        if state.get("t_start_s") is not None:
            self.t_start = float(state["t_start_s"])
        elif len(traj):
            self.t_start = float(traj[0, 0])
        self._resume_goal(state)

    def _resume_goal(self, state: dict) -> None:
        """The goal and its path as they were saved (a spare that takes over keeps driving to
        the same view); the robot has moved on meanwhile, so the path is followed from the point
        nearest the robot's first pose. A checkpoint without a goal's node (older) keeps none."""
        g, path = state.get("goal"), state.get("path")
        if state.get("done") or not g or not path or "cell" not in g:
            return
        xy = np.asarray(g["xy"], float)
        choice = fr.ViewChoice(
            np.asarray(g["cell"], np.int64),
            xy,
            float(g["yaw"]),
            float(g["gain_m2"]),
            float(g["path_cost"]),
            float(g["score"]),
            None,
            0,
            0,
        )
        path_xy = np.asarray(path, float).reshape(-1, 2)
        self.follower.set_path(path_xy, final_yaw=choice.yaw)
        t_set = float(g.get("t_set_s") or state.get("t_s") or 0.0)
        self.goal = Goal(choice, path_xy, t_set, self.follower.remaining_length_m())
        if state.get("t_last_plan_s") is not None:  # the next periodic plan comes when it would
            self._t_last_plan = float(state["t_last_plan_s"])
        self._progress_mark = None  # set again at the first pose: no stall from the pause
        self._resumed_goal = True

    # -- decisions ------------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.done_reason is not None

    def elapsed_s(self) -> float:
        return 0.0 if self.t_start is None else self.t_now - self.t_start

    def wants_plan(self) -> str | None:
        """Why a plan is needed now, or None. Also ends the run when the budget is spent."""
        if self.done or self.pose is None or self.grid is None:
            return None
        t = self.t_now
        if self.elapsed_s() >= self.config.time_budget_s:
            self.finish("time_budget")
            return None
        if self._spin is not None:
            return None
        if self.goal is None:
            if self._empty_plans and t - self._t_last_plan < self.config.empty_retry_s:
                return None
            if self._t_arrived is not None and t - self._t_arrived < self.config.dwell_s:
                return None
            return "no_goal"
        if self._path_blocked():
            self.n_replans_blocked += 1
            return "blocked"
        if self._stuck():
            self.n_stuck += 1
            self._forget(self.goal.choice.xy)
            # wedged against a corner the graph did not show (a hedge's edge between nodes):
            # every next path starts into it again, so reverse out first
            self._back_off_until = t + BACK_OFF_S
            return "stuck"
        if self.team is not None:
            if self._yield:
                self._yield = False
                self.n_yields += 1
                self._forget(self.goal.choice.xy, seconds=10.0)
                return "yield"
            if t - self._t_goal_check >= GOAL_SEEN_CHECK_S:
                # another member may have seen our view for us: do not drive there for nothing
                self._t_goal_check = t
                if self._goal_exhausted():
                    return "goal_seen"
        if t - self._t_last_plan >= self.config.replan_period_s:
            return "periodic"
        return None

    def plan(
        self, path_cost: PathFn, reason: str = "no_goal", claim: ClaimFn | None = None
    ) -> PlanOutcome:
        """Choose the next view (or keep the current one) and hand its path to the follower.

        `path_cost(start_xy, goal_xy)` returns (cost, path (K, 2|3)) or None when unreachable.
        `claim(goal_xy)` (a fleet member's, with `team`): asks the coordinator for a new goal
        before the robot heads for it; a refusal names the member whose goal is too near, and
        the choice is made again without the views near it.
        """
        assert self.grid is not None and self.pose is not None
        self.n_plans += 1
        self._t_last_plan = self.t_now
        g = self.grid
        x, y, _ = self.pose
        free = fr.traversable_mask(g.labels, g.flags, self.traversable_lut)
        unknown = fr.unknown_mask(g.flags)
        comp, reach, starts = self._starts(free, (x, y))
        here = g.cell_of((x, y))
        self.explored_m2 = float(free.sum()) * g.resolution_m**2
        front = fr.frontier_cells(reach, unknown)
        self.frontier_size = len(front)
        self.history.append((self.t_now, self.explored_m2, self.frontier_size, self.distance_m))
        keep_goal = reason == "periodic" and self.goal is not None and not self._goal_exhausted()

        def goal_cost(goal_xy):
            gc = g.cell_of(goal_xy)
            start = starts[int(comp[gc])]
            start_xy = np.array([x, y]) if start == here else g.centres(np.array(start))
            reply = path_cost(start_xy, goal_xy)
            if reply is None:
                return None
            cost, path = reply
            # the hop from the robot to the start node comes first
            hop = np.hypot(x - start_xy[0], y - start_xy[1])
            if hop > 1e-6:
                path = np.vstack([[x, y], np.asarray(path, float)[:, :2]])
            return cost + hop, path

        opaque = fr.opaque_mask(g.flags) if self.config.view.occlusion else None
        if self.config.strategy == "nearest_frontier":
            if keep_goal:
                # Yamauchi's robot drives to its frontier and chooses again once there (or once
                # the frontier has gone): a periodic plan changes nothing
                cells, choice = np.zeros((0, 2), np.int64), None
                best_gain = np.zeros(0)
            else:
                cells, best_gain, choice = self._nearest_frontier(
                    free, front, starts, (x, y), unknown, opaque, goal_cost
                )
        else:
            spacing = max(1, int(round(self.config.candidate_spacing_m / g.resolution_m)))
            all_cells = self._drop_blacklisted(fr.sample_candidates(front, spacing))
            for _ in range(MAX_CLAIMS_PER_PLAN):
                cells, best_gain, choice = self._next_best_view(
                    all_cells, unknown, opaque, (x, y), goal_cost
                )
                if choice is None or claim is None or self._keeps(keep_goal, choice):
                    break
                granted, holder, holder_xy = claim(choice.xy)
                if granted:
                    break
                self.n_claims_refused += 1
                self.team.add_goal(holder, holder_xy)
                choice = None  # refused every time: no new goal from this plan
        xy = g.centres(cells) if len(cells) else np.zeros((0, 2))
        outcome = PlanOutcome(reason, choice, False, len(front), len(cells), xy, best_gain)
        self.last_outcome = outcome
        if choice is None:
            if keep_goal:
                return outcome  # nothing new, keep going to the current goal
            self._set_goal(None)
            if self.team is not None and len(self.team.goals):
                # what is left may be another member's to see: wait for its goals to change
                # instead of spinning or giving up
                self._empty_plans = max(self._empty_plans, 1)
                return outcome
            self._empty_plans += 1
            if self._maybe_spin():
                return outcome
            if self._empty_plans >= self.config.done_after_empty:
                self.finish("no_view_worth_it" if len(cells) else "no_frontier")
            return outcome
        self._empty_plans = 0
        if self._keeps(keep_goal, choice):
            return outcome
        outcome.switched = self.goal is not None
        self._set_goal(choice)
        return outcome

    def _keeps(self, keep_goal: bool, choice: fr.ViewChoice) -> bool:
        """A periodic plan keeps the current goal unless the new view is better by the margin."""
        return keep_goal and choice.score <= self._current_score() + self.config.switch_margin_share

    def _next_best_view(self, cells, unknown, opaque, xy, goal_cost):
        """The paper's choice among candidate cells: (cells kept, their best gains, the choice or
        None). In a fleet, views near another member's goal are left out and the unknown area
        around it counts for nothing (that member will see it)."""
        g = self.grid
        gain_unknown = unknown
        if self.team is not None:
            if len(cells):
                cells = cells[self.team.apart(g.centres(cells))]
            claimed = self.team.claimed(g.origin_xy, g.resolution_m, unknown.shape)
            gain_unknown = unknown & ~claimed
        gains, yaws = fr.view_gains(gain_unknown, opaque, cells, self._fov)
        best_gain = gains.max(axis=1) if len(cells) else np.zeros(0)
        choice = fr.select_view(
            g.centres(cells) if len(cells) else np.zeros((0, 2)),
            cells,
            best_gain,
            yaws,
            np.asarray(xy, float),
            goal_cost,
            self.score,
            self.config.min_gain_m2,
            self.cost_per_m_lower_bound,
            max_queries=self.config.max_queries,
        )
        return cells, best_gain, choice

    def control(self) -> tuple[float, float]:
        """Velocity command (v m/s, w rad/s) for the current tick."""
        if self.done or self.pose is None:
            return 0.0, 0.0
        x, y, yaw = self.pose
        if self._spin is not None:
            turned = self._spin["turned"] + abs(wrap_angle(yaw - self._spin["last_yaw"]))
            self._spin.update(turned=turned, last_yaw=yaw)
            if turned >= 2 * math.pi - 0.2 or self.t_now - self._spin["t0"] > 30.0:
                self._spin = None
                self._empty_plans = 0
                self._t_last_plan = -math.inf
                return 0.0, 0.0
            return 0.0, self.config.follower.max_angular_radps * 0.6
        if self._back_off_until is not None:
            if self.t_now < self._back_off_until:
                p = np.array([x, y])
                behind = p - BACK_OFF_M * np.array([math.cos(yaw), math.sin(yaw)])
                # clear of known obstacles, and of fleet members: reversing is blind to them
                member = self.team is not None and self.team.ahead(x, y, yaw + math.pi, self.t_now)
                if self._segment_clear(p, behind, OBSTACLE_ONLY) and not member:
                    return -self.config.creep_speed_mps, 0.0
            self._back_off_until = None
            if self.goal is not None:  # the new path starts where the robot now is
                self._progress_mark = (self.t_now, self.follower.remaining_length_m())
        if self.goal is None:
            return self._make_way(x, y, yaw)
        cmd = self.follower.command(x, y, yaw, self._segment_clear)
        if cmd.done:
            self._forget(self.goal.choice.xy, seconds=self.config.dwell_s + 5.0)
            self._set_goal(None)
            self._t_arrived = self.t_now
            return 0.0, 0.0
        v, w = cmd.linear_mps, cmd.angular_radps
        if self.team is not None and v > 0:
            stop, give_way = self.team.hold(x, y, yaw, self.t_now)
            if stop:
                v = 0.0  # turning on the spot stays allowed: it may point the robot away
            self._yield |= give_way
        if self.grid is not None and v > self.config.creep_speed_mps:
            here = np.array(self.grid.cell_of((x, y)))
            if self.grid.inside(here).all() and _blocking(self.grid.flags[here[0], here[1]]):
                w *= self.config.creep_speed_mps / v  # same arc, slower
                v = self.config.creep_speed_mps
        return v, w

    def _make_way(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        """Idle in a fleet: step away from a member that comes close (team.py), slowly, and
        only onto ground known to be clear."""
        away = None if self.team is None else self.team.make_way(x, y, self.t_now)
        if away is None:
            return 0.0, 0.0
        err = wrap_angle(math.atan2(away[1], away[0]) - yaw)
        fc = self.config.follower
        w = max(-fc.max_angular_radps, min(fc.max_angular_radps, 2.0 * err))
        if abs(err) > 0.5:
            return 0.0, w
        p = np.array([x, y])
        if not self._segment_clear(p, p + 0.5 * away):
            return 0.0, 0.0
        return self.config.creep_speed_mps, w

    # -- state ----------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        g = self.goal
        return {
            "t_s": self.t_now,
            "t_start_s": self.t_start,
            "strategy": self.config.strategy,
            "elapsed_s": self.elapsed_s(),
            "mode": self.mode,
            "done": self.done,
            "done_reason": self.done_reason,
            "goal": None
            if g is None
            else {
                "xy": [float(v) for v in g.choice.xy],
                "cell": [int(v) for v in g.choice.cell],
                "t_set_s": g.t_set,
                "yaw": g.choice.yaw,
                "gain_m2": g.choice.gain_m2,
                "path_cost": g.choice.path_cost,
                "score": g.choice.score,
            },
            "path": [] if g is None else np.round(g.path_xy, 3).tolist(),
            "frontier_size": self.frontier_size,
            "explored_m2": self.explored_m2,
            "distance_m": self.distance_m,
            "label_counts": {str(i): int(c) for i, c in enumerate(self.label_counts) if c},
            "n_plans": self.n_plans,
            "t_last_plan_s": self._t_last_plan if math.isfinite(self._t_last_plan) else None,
            "n_goals": self.n_goals,
            "n_blocked": self.n_replans_blocked,
            "n_stuck": self.n_stuck,
            "n_claims_refused": self.n_claims_refused,
            "n_yields": self.n_yields,
            "n_team_stops": 0 if self.team is None else self.team.n_stops,
            "pose": None if self.pose is None else list(self.pose),
        }

    @property
    def mode(self) -> str:
        if self.done:
            return "done"
        if self._spin is not None:
            return "spinning"
        if self.goal is not None:
            return "following"
        return "waiting"

    # -- internals ------------------------------------------------------------------------------

    def finish(self, reason: str) -> None:
        self.done_reason = reason
        self._set_goal(None)
        self._spin = None

    def _set_goal(self, choice: fr.ViewChoice | None) -> None:
        if choice is None:
            self.goal = None
            self.follower = PurePursuit(self.config.follower)
            self._progress_mark = None
            return
        path = _path_xy(choice.path, choice.xy, self.pose)
        self.follower.set_path(path, final_yaw=choice.yaw)
        self.goal = Goal(choice, path, self.t_now, self.follower.remaining_length_m())
        self._progress_mark = (self.t_now, self.follower.remaining_length_m())
        self._t_arrived = None
        self.n_goals += 1

    def _starts(self, free: np.ndarray, xy) -> tuple[np.ndarray, np.ndarray, dict]:
        """Where paths may start: for every component of free nodes that comes within
        `start_search_radius_m` of the robot, its node nearest the robot (the robot's own node when
        free). Returns (component labels, reachable mask, {component id: start node}).

        The nodes right around the robot are often unseen (the camera does not look straight
        down) or became safety zone, so the robot's own node can be cut off from all it has seen;
        it then drives a short straight hop to the start node first. Paths never cross unknown
        space beyond that hop: an unseen obstacle may stand beside the robot, out of view. A hop
        must not cross an obstacle node: a robot caught in a safety zone that just appeared
        around it backs out on the open side, not through the obstacle to a nearer node."""
        from scipy import ndimage  # here, not at import: off the explorer's start

        g = self.grid
        comp, _ = ndimage.label(free, structure=fr.EIGHT_CONNECTED)
        cell = np.array(g.cell_of(xy))
        r = int(math.ceil(self.config.start_search_radius_m / g.resolution_m))
        lo = np.maximum(cell - r, 0)
        hi = np.minimum(cell + r + 1, g.shape)
        starts: dict[int, tuple[int, int]] = {}
        if (hi > lo).all():
            sub = np.argwhere(free[lo[0] : hi[0], lo[1] : hi[1]]) + lo
            d = np.hypot(*(sub - cell).T) if len(sub) else np.zeros(0)
            p = np.asarray(xy, float)[:2]
            for k in np.argsort(d, kind="stable"):
                if d[k] > r:
                    break
                cid = int(comp[sub[k, 0], sub[k, 1]])
                if cid in starts:
                    continue
                if d[k] > 0 and not self._segment_clear(p, g.centres(sub[k]), OBSTACLE_ONLY):
                    continue
                starts[cid] = (int(sub[k, 0]), int(sub[k, 1]))
        reach = np.isin(comp, list(starts)) if starts else np.zeros(g.shape, bool)
        return comp, reach, starts

    def _path_blocked(self) -> bool:
        g = self.grid
        rem = self.follower.remaining
        if len(rem) == 0:
            return False
        cells = g.cells_of(rem)
        cells = cells[g.inside(cells)]
        bad = _blocking(g.flags[cells[:, 0], cells[:, 1]])
        # skip the node the robot is on: leaving a safety zone it was put in must stay possible
        here = g.cell_of(self.pose[:2])
        mine = (cells[:, 0] == here[0]) & (cells[:, 1] == here[1])
        return bool((bad & ~mine).any())

    def _segment_clear(self, p: np.ndarray, q: np.ndarray, bits: int | None = None) -> bool:
        """No known obstacle or safety-zone node (or nodes with `bits`) on the segment p-q, the
        node of p excepted."""
        g = self.grid
        if g is None:
            return True
        n = max(2, int(math.ceil(np.hypot(*(q - p)) / (0.5 * g.resolution_m))) + 1)
        pts = p + (q - p) * np.linspace(0.0, 1.0, n)[:, None]
        cells = g.cells_of(pts)
        cells = cells[g.inside(cells)]
        here = np.array(g.cell_of(p))
        cells = cells[(cells != here).any(axis=1)]
        return not _blocking(g.flags[cells[:, 0], cells[:, 1]], bits).any()

    def _stuck(self) -> bool:
        if self._progress_mark is None:
            return False
        t0, rem0 = self._progress_mark
        rem = self.follower.remaining_length_m()
        if rem < rem0 - 0.1:
            self._progress_mark = (self.t_now, rem)
            return False
        return self.t_now - t0 > self.config.stuck_timeout_s

    def _goal_exhausted(self) -> bool:
        return self._goal_gain() < self.config.min_gain_m2

    def _goal_gain(self) -> float:
        g = self.grid
        cell = self.goal.choice.cell.reshape(1, 2)
        opaque = fr.opaque_mask(g.flags)
        gains, _ = fr.view_gains(
            fr.unknown_mask(g.flags),
            opaque if self.config.view.occlusion else None,
            cell,
            self._fov,
        )
        return float(gains.max()) if gains.size else 0.0

    def _current_score(self) -> float:
        # the cost left is the planned cost scaled by the share of the path still ahead
        total = max(self.goal.path_length_m, 1e-6)
        left = self.goal.choice.path_cost * self.follower.remaining_length_m() / total
        return float(self.score(self._goal_gain(), left))

    def _nearest_frontier(self, free, front, starts, xy, unknown, opaque, goal_cost):
        """Yamauchi's choice: the frontier node nearest by travel (metres over free nodes from the
        robot, class costs ignored) among those whose view is worth a look (`min_gain_m2`, the
        same test the next-best view applies, so both strategies stop on the same criterion),
        facing its most unknown heading. Returns (cells whose gain was computed, their gains,
        the choice or None). Gains are computed in growing batches in distance order: the
        nearest worthy node is usually among the first few."""
        g = self.grid
        cells = self._drop_blacklisted(front)
        src = np.array(list(starts.values()), np.int64).reshape(-1, 2)
        hop = np.hypot(*(g.centres(src) - np.asarray(xy, float)).T) if len(src) else np.zeros(0)
        dist = fr.travel_distance_m(free, src, hop, g.resolution_m)
        d = dist[cells[:, 0], cells[:, 1]] if len(cells) else np.zeros(0)
        order = np.argsort(d, kind="stable")
        order = order[np.isfinite(d[order])]
        seen_cells, seen_gains = [], []
        n_queries, lo, batch = 0, 0, 16
        while lo < len(order) and n_queries < self.config.max_queries:
            idx = order[lo : lo + batch]
            gains, yaws = fr.view_gains(unknown, opaque, cells[idx], self._fov)
            best = gains.max(axis=1)
            seen_cells.append(cells[idx])
            seen_gains.append(best)
            for k in np.flatnonzero(best >= self.config.min_gain_m2):
                if n_queries >= self.config.max_queries:
                    break
                n_queries += 1
                goal_xy = g.centres(cells[idx[k]])
                reply = goal_cost(goal_xy)
                if reply is None or not math.isfinite(reply[0]):
                    continue
                choice = fr.ViewChoice(
                    cells[idx[k]].copy(),
                    goal_xy,
                    float(yaws[k]),
                    float(best[k]),
                    float(reply[0]),
                    -float(d[idx[k]]),  # nearer is better
                    reply[1],
                    n_queries,
                    len(order),
                )
                return np.concatenate(seen_cells), np.concatenate(seen_gains), choice
            lo += batch
            batch *= 2
        if not seen_cells:
            return np.zeros((0, 2), np.int64), np.zeros(0), None
        return np.concatenate(seen_cells), np.concatenate(seen_gains), None

    def _forget(self, xy, seconds: float | None = None) -> None:
        until = self.t_now + (self.config.blacklist_s if seconds is None else seconds)
        self._blacklist.append((np.asarray(xy, float).copy(), until))

    def _drop_blacklisted(self, cells: np.ndarray) -> np.ndarray:
        self._blacklist = [(c, until) for c, until in self._blacklist if until > self.t_now]
        if not self._blacklist or len(cells) == 0:
            return cells
        xy = self.grid.centres(cells)
        keep = np.ones(len(cells), bool)
        for c, _ in self._blacklist:
            keep &= np.hypot(*(xy - c).T) > self.config.blacklist_radius_m
        return cells[keep]

    def _maybe_spin(self) -> bool:
        """Turn once on the spot where nothing was found: the camera sees 57 degrees, and what is
        behind the robot may hold a frontier. Only once per place."""
        x, y, yaw = self.pose
        here = np.array([x, y])
        if any(np.hypot(*(here - p)) < 1.0 for p in self._spun_at):
            return False
        self._spun_at.append(here)
        self._spin = {"t0": self.t_now, "turned": 0.0, "last_yaw": yaw}
        return True


OBSTACLE_ONLY = fr.OBSTACLE


def _blocking(flags: np.ndarray, bits: int | None = None) -> np.ndarray:
    """Known nodes the robot must not enter: obstacles and their safety zone (or `bits`)."""
    bits = fr.OBSTACLE | fr.SAFETY_ZONE if bits is None else bits
    return ((flags & fr.KNOWN) != 0) & ((flags & bits) != 0)


def _path_xy(path, goal_xy: np.ndarray, pose) -> np.ndarray:
    """The planner's path as (K, 2), ending on the goal; a missing path becomes a straight line."""
    if path is None or len(path) == 0:
        pts = np.array([pose[:2], goal_xy], float)
    else:
        pts = np.asarray(path, float)[:, :2]
    if np.hypot(*(pts[-1] - goal_xy)) > 1e-6:
        pts = np.vstack([pts, goal_xy])
    return pts
