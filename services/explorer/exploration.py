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
- no view worth it: spin once on the spot to look around; after `done_after_empty` empty plans,
  look again at what cuts the robot off from free ground it has seen (`recovery.py`, up to
  `recoveries` times), then give up: `closed_in` when that ground is larger than what it can
  reach (its own map closed it in), else `no_view_worth_it` / `no_frontier`; or the time budget
  is over -> done.

Two ways to choose (`strategy`): "nbv", the paper's next-best view (`frontier.select_view` with
`frontier.ViewScore`), and "nearest_frontier", Yamauchi's baseline: the frontier node nearest by
travel over free nodes whose view is worth a look (`_nearest_frontier`).

The choice of a view lives in `choosing.py`, the driving in `driving.py`, the goals it is sent
("go to this pose": exploration pauses meanwhile) in `navigation.py`; `Explorer` is put together
from the three and is what the service and the benches use.

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
from smana.services.explorer.choosing import Choosing
from smana.services.explorer.driving import BACK_OFF_S, Driving
from smana.services.explorer.follower import PurePursuit
from smana.services.explorer.guard import Guard
from smana.services.explorer.navigation import (
    GoalRefused,
    GoalSpec,
    NavGoal,
    Navigating,
    check_goal_id,
)
from smana.services.explorer.recovery import Recovering
from smana.services.explorer.team import Team

# path_cost(start_xy, goal_xy) -> (cost, path (K, 2|3)) or None when there is no path
PathFn = Callable[[np.ndarray, np.ndarray], "tuple[float, np.ndarray] | None"]
# claim(goal_xy) -> (granted, the member holding a goal too near, that goal) (fleet members)
ClaimFn = Callable[[np.ndarray], "tuple[bool, str | None, np.ndarray | None]"]
MAX_CLAIMS_PER_PLAN = 3  # refused this often in one plan: wait for the next one
GOAL_SEEN_CHECK_S = 1.0  # in a fleet, how often the goal's gain is checked between plans


@dataclass
class GridBox:
    """A dense box of the navigation graph, indexed [ix, iy]; node (ix, iy) covers
    [origin + i * res, origin + (i + 1) * res) on each axis."""

    origin_xy: np.ndarray
    resolution_m: float
    labels: np.ndarray
    flags: np.ndarray
    heights: np.ndarray | None = None  # the nodes' heights (NaN unknown); None: not given

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

    @classmethod
    def around_known(cls, grid, pad_m: float) -> GridBox | None:
        """The dense box of `grid` (a NavGrid) the explorer works on: its allocated tiles,
        padded by `pad_m` and two nodes (unknown space beyond the tiles is unknown space, and
        frontiers face it); None while the grid is empty."""
        box = grid.known_box()
        if box is None:
            return None
        pad = int(math.ceil(pad_m / grid.resolution_m)) + 2
        ix0, iy0, ix1, iy1 = box
        ix0, iy0 = max(0, ix0 - pad), max(0, iy0 - pad)
        ix1, iy1 = min(grid.shape[0], ix1 + pad), min(grid.shape[1], iy1 + pad)
        labels, heights, flags = grid.box(ix0, iy0, ix1, iy1)
        origin = grid.origin_xy + np.array([ix0, iy0]) * grid.resolution_m
        return cls(origin, grid.resolution_m, labels, flags, heights)


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


class Explorer(Choosing, Driving, Navigating, Recovering):
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
        # the planner's step rule (planner.max_step_m): nodes it joins are reachable together
        self.max_step_m = math.inf
        self._fov: fr.FovModel | None = None
        self.follower = PurePursuit(config.follower)
        self.goal: Goal | None = None
        # a goal it was sent (navigation.py): the running one, or the last one, ended
        self.nav: NavGoal | None = None
        self.nav_changes: list[dict] = []  # feedback at each change of a goal's state, to send
        self.exploring = config.mode == "explore"
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
        self._looked_at: list[np.ndarray] = []  # where it went to look again (recovery.py)
        self.n_recoveries = 0
        self._looking = False  # the goal is a look again (no view gain of its own)
        self._blacklist: list[tuple[np.ndarray, float]] = []
        self._progress_mark: tuple[float, float] | None = None  # (t, remaining length)
        self.done_reason: str | None = None
        self.n_plans = 0
        self.n_goals = 0
        self.n_replans_blocked = 0
        self.n_stuck = 0
        self.n_turns_avoided = 0  # control ticks that crept instead of turning into an obstacle
        self.guard = Guard(config.guard)  # every command's last check, against the safety scan
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
        if self.nav is not None and self.nav.t_accepted is None:
            self.nav.t_accepted = t  # a goal sent before the first pose: its time starts now
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
        if g and g.get("navigate"):
            self._end_goal_of_the_last_process(g)
            return
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

    def _end_goal_of_the_last_process(self, g: dict) -> None:
        """A goal the last process was sent and was driving to is not resumed (its sender may
        have moved on): it ends "aborted" at once, and the first feedback says so, so that its
        sender (a NavigateToPose client, `smana goto`) hears it now, not after a silence."""
        try:
            gid = check_goal_id(g["navigate"])
            x, y = (float(v) for v in g["xy"][:2])
            yaw = g.get("yaw")
            yaw = None if yaw is None else float(yaw)
        except (GoalRefused, KeyError, TypeError, ValueError):
            return  # a checkpoint this process cannot read: nobody to tell
        spec = GoalSpec(x, y, yaw, self.config.follower.goal_tolerance_m, gid)
        self.nav = NavGoal(spec, None)
        self._end_nav("aborted", "the explorer restarted: a goal is not resumed", "stopped")

    # -- decisions ------------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return self.done_reason is not None

    def elapsed_s(self) -> float:
        return 0.0 if self.t_start is None else self.t_now - self.t_start

    def wants_plan(self) -> str | None:
        """Why a plan is needed now, or None. Also ends the run when the budget is spent."""
        if self.done or self.pose is None:
            return None
        if self.nav_active:
            return self._nav_wants_plan()  # exploration pauses while a goal runs
        if self.grid is None or not self.exploring:
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
        if self.nav_active:
            self._t_last_plan = self.t_now
            chosen = self._plan_nav(path_cost, reason)
            return PlanOutcome(reason, chosen, False, 0, 0, np.zeros((0, 2)), np.zeros(0))
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
        keep_goal = reason == "periodic" and self.goal is not None
        keep_goal = keep_goal and (self._looking or not self._goal_exhausted())

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
                beyond = self._seen_beyond(free, reach)
                # a finished run's pockets behind hedges, seen whole, are no reason to drive on:
                # a robot looks again when it seems closed in or a frontier lies beyond its reach
                closed_in = self._closed_in(beyond, reach)
                stuck = closed_in or self._unexplored_beyond(beyond, unknown, reach)
                if stuck and self._maybe_look_again(beyond, reach, goal_cost):
                    self._empty_plans = 0
                    return outcome
                if closed_in:
                    self.finish("closed_in")
                else:
                    self.finish("no_view_worth_it" if len(cells) else "no_frontier")
            return outcome
        self._empty_plans = 0
        self.n_recoveries = 0  # a view again: the looks were worth it
        if self._keeps(keep_goal, choice):
            return outcome
        outcome.switched = self.goal is not None
        self._set_goal(choice)
        return outcome

    # -- state ----------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        g = self.goal
        return {
            "t_s": self.t_now,
            "t_start_s": self.t_start,
            "strategy": self.config.strategy,
            "elapsed_s": self.elapsed_s(),
            "mode": self.mode,
            "exploring": self.exploring,
            "nav_goal": self.nav_state(),
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
                # a goal it was sent: not resumed by a restarted explorer (its sender is told)
                "navigate": self.nav.id if self.nav_active else None,
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
            "n_turns_avoided": self.n_turns_avoided,
            "guard": self.guard.summary(),
            "n_recoveries": self.n_recoveries,
            "n_looks": len(self._looked_at),
            "n_claims_refused": self.n_claims_refused,
            "n_yields": self.n_yields,
            "n_team_stops": 0 if self.team is None else self.team.n_stops,
            "pose": None if self.pose is None else list(self.pose),
        }

    def progress(self) -> str:
        """One line of where exploration is, for the service's status."""
        progress = (
            f"{self.mode} explored {self.explored_m2:.1f} m2, {self.distance_m:.1f} m, "
            f"frontier {self.frontier_size}"
        )
        if self.goal is not None:
            progress += f", goal ({self.goal.choice.xy[0]:.1f}, {self.goal.choice.xy[1]:.1f})"
        if self.nav is not None:
            progress += f", sent goal {self.nav.id} {self.nav.state}"
        return progress

    @property
    def mode(self) -> str:
        if self.done:
            return "done"
        if self._spin is not None:
            return "spinning"
        if self.nav_active:
            return "navigating"
        if self.goal is not None:
            return "following"
        return "waiting"

    # -- internals ------------------------------------------------------------------------------

    def finish(self, reason: str) -> None:
        if self.nav_active:
            self._end_nav("aborted", f"the explorer stopped ({reason})", "stopped")
        self.done_reason = reason
        self._set_goal(None)
        self._spin = None

    def _set_goal(
        self, choice: fr.ViewChoice | None, count: bool = True, tolerance_m: float | None = None
    ) -> None:
        """Drive to `choice` (None: stop). `count`: a view of exploration's (n_goals);
        `tolerance_m`: how near its end is near enough (None: the follower's)."""
        self._looking = False
        if choice is None:
            self.goal = None
            self.follower = PurePursuit(self.config.follower)
            self._progress_mark = None
            return
        path = _path_xy(choice.path, choice.xy, self.pose)
        self.follower.set_path(path, final_yaw=choice.yaw, tolerance_m=tolerance_m)
        self.goal = Goal(choice, path, self.t_now, self.follower.remaining_length_m())
        self._progress_mark = (self.t_now, self.follower.remaining_length_m())
        self._t_arrived = None
        self.n_goals += count


def _path_xy(path, goal_xy: np.ndarray, pose) -> np.ndarray:
    """The planner's path as (K, 2), ending on the goal; a missing path becomes a straight line."""
    if path is None or len(path) == 0:
        pts = np.array([pose[:2], goal_xy], float)
    else:
        pts = np.asarray(path, float)[:, :2]
    if np.hypot(*(pts[-1] - goal_xy)) > 1e-6:
        pts = np.vstack([pts, goal_xy])
    return pts
