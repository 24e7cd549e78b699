"""What a run keeps of the explorer, and what a restarted explorer reads back from the same run
directory (no zenoh): the plan log (one entry per goal it chose itself: the report counts them),
the books of its path queries, its state as it publishes it (`state_message`), and the files of
`<run_dir>/explorer/`: state.json and trajectory.csv, written every `CHECKPOINT_PERIOD_S`, when
its goal changes and when it stops, and graph.npz (its copy of the graph) at the end."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from smana.common.messages import json_default
from smana.common.navgrid import NavGrid

CHECKPOINT_PERIOD_S = 10.0  # state and trajectory saved for a restarted explorer to carry on


@dataclass
class PathBooks:
    """The path queries the explorer asked the planner, and how they ended."""

    queries: int = 0
    ok: int = 0
    errors: dict[str, int] = field(default_factory=dict)

    def failed(self, kind: str) -> bool:
        """Count a query that gave no path; True when it is worth a warning: an unreachable
        candidate is ordinary, a planner that does not answer is not (told at 1, 10, 100)."""
        self.errors[kind] = self.errors.get(kind, 0) + 1
        return kind == "no_reply" and self.errors[kind] in (1, 10, 100)


def plan_entry(core, outcome, reason: str) -> dict | None:
    """The plan log's entry for a plan that set the core's goal to the view it chose (None for
    one that did not, or that drives to a goal it was sent)."""
    goal = core.goal
    mine = outcome.chosen is not None and goal is not None and goal.choice is outcome.chosen
    if not mine or core.nav_active:
        return None
    c = outcome.chosen
    return {
        "t_s": core.t_now,
        "strategy": core.config.strategy,
        "reason": reason,
        "goal": c.xy.tolist(),
        "yaw": c.yaw,
        "gain_m2": c.gain_m2,
        "path_cost": c.path_cost,
        "score": c.score,
        "queries": c.n_queries,
        "frontier": outcome.n_frontier,
    }


def state_message(core, label_names: dict[str, str], pose_noise_sd_m: float) -> dict:
    """`explorer/state`: the core's state, the last plan's candidates and their gains, the class
    names and the localisation's noise as the pose filter estimates it (standard deviations)."""
    st = core.state_dict()
    out = core.last_outcome
    if out is not None and len(out.candidates_xy):
        st["candidates"] = np.round(out.candidates_xy, 3).tolist()
        st["candidate_gains_m2"] = np.round(out.gains_m2, 3).tolist()
    else:
        st["candidates"], st["candidate_gains_m2"] = [], []
    st["label_names"] = label_names
    st["pose_noise_sd_m"] = round(pose_noise_sd_m, 4)
    return st


class RunRecord:
    """The explorer's part of a run directory (`None`: no run directory, nothing kept)."""

    def __init__(self, run_dir: str | Path | None, now: float):
        self.folder = None if run_dir is None else Path(run_dir) / "explorer"
        self.plans: list[dict] = []
        self.paths = PathBooks()
        self.final = False  # the final save is done: nothing is written after it
        self.goal_saved = None  # the goal the last checkpoint holds
        self.next_checkpoint = now + CHECKPOINT_PERIOD_S

    def read(self) -> tuple[dict, np.ndarray] | None:
        """The state and trajectory an earlier process of the run saved, None when it saved
        none. OSError, ValueError (and KeyError, TypeError from a state that is not one) when
        they cannot be read."""
        if self.folder is None or not (self.folder / "state.json").is_file():
            return None
        state = json.loads((self.folder / "state.json").read_text())
        traj = np.zeros((0, 4))
        if (self.folder / "trajectory.csv").is_file():
            traj = np.loadtxt(self.folder / "trajectory.csv", delimiter=",", skiprows=1, ndmin=2)
        return state, traj

    def resume(self, state: dict) -> None:
        """Carry on the plan log and the path queries' books of the state read back."""
        self.plans = list(state.get("plans") or [])
        self.paths = PathBooks(
            int(state.get("path_queries") or 0),
            int(state.get("path_ok") or 0),
            {str(k): int(v) for k, v in (state.get("path_errors") or {}).items()},
        )

    def log_plan(self, entry: dict | None) -> None:
        if entry is not None:
            self.plans.append(entry)

    def checkpoint_due(self, now: float, goal) -> bool:
        """A checkpoint every period, and whenever the goal changes: a spare that takes over
        drives on to the same view, not to one of a checkpoint ago."""
        if now < self.next_checkpoint and goal is self.goal_saved:
            return False
        self.next_checkpoint = now + CHECKPOINT_PERIOD_S
        self.goal_saved = goal
        return True

    def writes(self, final: bool) -> bool:
        """Whether a save (the final one when `final`) writes anything: not without a run
        directory, nor after the final save."""
        if self.final or self.folder is None:
            self.final = self.final or final
            return False
        self.final = final
        return True

    def write(
        self, state: dict, history, trajectory, wall_time_s: float, grid: NavGrid, final: bool
    ) -> None:
        """State and trajectory (and, when `final`, the grid) into the folder: for the report,
        and for a restarted explorer to carry on. `state` is `state_message`'s."""
        out = self.folder
        out.mkdir(parents=True, exist_ok=True)
        state["plans"] = self.plans
        state["history"] = history
        state["path_queries"] = self.paths.queries
        state["path_ok"] = self.paths.ok
        state["path_errors"] = self.paths.errors
        state["wall_time_s"] = wall_time_s
        # trajectory first, state last, each replaced whole: a kill between them leaves a state
        # that describes a trajectory at least as long as the one on disk
        tmp = out / "trajectory.csv.tmp"
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t_s", "x_m", "y_m", "yaw_rad"])
            w.writerows(trajectory)
        tmp.replace(out / "trajectory.csv")
        tmp = out / "state.json.tmp"
        tmp.write_text(json.dumps(state, indent=1, default=json_default))
        tmp.replace(out / "state.json")
        box = grid.known_box()
        if final and box is not None:
            labels, heights, flags = grid.box(*box)
            origin = grid.origin_xy + np.array(box[:2]) * grid.resolution_m
            np.savez_compressed(
                out / "graph.npz",
                origin_xy=origin,
                resolution_m=grid.resolution_m,
                labels=labels,
                heights=heights,
                flags=flags,
            )
