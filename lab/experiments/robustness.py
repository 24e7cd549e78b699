"""`smana experiment robustness`: does the closed loop keep exploring when labels and poses are
wrong, as a segmentation network and a drifting odometry make them?

The whole stack (`smana up`, run by the exploration experiment's runner: its starts, failure
accounting and resumable rows) explores a 16 m cluttered garden, where coverage needs driving,
with NBV and the class table's grass cost, on the same ten worlds in every arm:

- the default back-end (`mapper.backend`'s default, octree-max) with label noise `off` (true
  labels), `medium` and `high` (the paper's levels: p = 0.8 and 0.7) and `realistic` (a
  published network's confusions, persistent errors, boundary bleed: `[sim.perception]`), each
  with pose noise: 0.10 m white noise on x and y and 0.02 rad on yaw, per published pose, plus a
  drift (a random walk) of 0.01 m/sqrt(s) on x and y and 0.002 rad/sqrt(s) on yaw (after 300 s
  of robot time: 0.17 m and 0.035 rad, one standard deviation);
- its noise-free reference, `clean`: true labels and no pose noise (what "its own noise-free
  usable coverage" is measured on);
- octree-bayes and tsdf at `high` and `realistic`, with the same pose noise.

Measured per run against the world's ground truth (the run's report, metrics.json):
- usable coverage: the share of the reachable traversable area that the final navigation graph
  knows as traversable (`exploration.usable_share`), beside the false-obstacle area (reachable
  ground the graph calls an obstacle or a safety zone) and the false-free area (obstacles the
  graph calls traversable: the dangerous one), each in m2 and as a share of the reachable area;
- collisions (the report's contacts), the true distance driven, the explorer's done_reason;
- distance and robot time to 90 % of the run's own final usable area: the first plan at which
  the explorer's usable count (`explored_m2`: known nodes of a traversable class, neither
  obstacle nor safety zone) reached 90 % of its value at the end. A speed, not a level: the level
  is the usable coverage;
- whether the run stopped short: FAILED (`smana up` exit 1 on what its robot did: it did not
  move, knew under half the reachable area as usable, was closed in by its own map, ...), did not
  move (under 0.1 m), or ended `closed_in`. A robot that did not move is a failure with its
  measured coverage, never missing data. A run that did not run to its report (no metrics.json:
  a crash, a timeout) is not a measurement: listed, and the command exits 1.

Rules, fixed before the runs, on seeds 51 to 60 (worlds the docs use nowhere else, and that the
development did not look at: its pilots and trials ran seeds 21 to 25, 31 and 41 to 45,
`--first-seed`):
1. at `high` label noise with pose noise, the default back-end reaches at least 90 % of its own
   noise-free usable coverage (the `clean` run of the same seed), with 0 collisions, without
   FAILED and having moved, in at least 9 of the 10 seeds;
2. at `realistic`, the same with at least 80 %;
3. in every run of every arm, the false-free area is under 1 % of the reachable area.
These are counts over seeds, not tests: "met", "not met", or "inconclusive" while the seeds that
ran can still go either way (a seed whose reference did not run counts against). Every arm's row
is reported, whatever it shows; no verdict uses octree-bayes or tsdf.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from . import exploration as ex

SEEDS = tuple(range(51, 61))  # worlds and starts no other experiment, and no pilot, used
SIZE_M = 16.0
GRASS_COST_FACTOR = 2.0  # the class table's own grass cost (x2 terrain's)
POSE_NOISE = (0.10, 0.02)  # white, per published pose: x and y (m), yaw (rad)
POSE_DRIFT = (0.01, 0.002)  # random walk: x and y (m/sqrt(s)), yaw (rad/sqrt(s))
LEVELS = ("off", "medium", "high", "realistic")  # sim.noise, with pose noise
CLEAN = "clean"  # true labels, no pose noise: the reference
OTHER_BACKENDS = ("octree-bayes", "tsdf")
OTHER_LEVELS = ("high", "realistic")
TARGETS = {"high": 0.90, "realistic": 0.80}  # share of the noise-free usable coverage
PASS_SEEDS, OF_SEEDS = 9, 10  # rules 1 and 2: in at least 9 of 10 seeds
FALSE_FREE_MAX = 0.01  # rule 3: false-free area under 1 % of the reachable area, every run
# Robot time a run may take (the explorer's time_budget_s, which bounds its wall time too). In
# the pilot (seed 21) the noise-free runs ended `no_view_worth_it` after 230 and 240 s,
# octree-max under high noise after 200 and 327 s, at realistic after 254 s; tsdf at realistic
# drove to the end of 360 s
BUDGET_S = 360.0
TIME_TO_SHARE = 0.90  # time and distance to 90 % of the run's final usable area


def default_backend() -> str:
    from smana.common.config import MapperConfig

    return MapperConfig().backend


@dataclass(frozen=True)
class Condition:
    """One arm: a back-end and a perception (a LEVELS label noise with pose noise, or CLEAN)."""

    backend: str
    perception: str

    @property
    def name(self) -> str:
        # short: a run's robot is exp<pid>-s<seed>-<arm>, a key chunk of at most 32 characters
        return f"{self.backend.removeprefix('octree-').replace('-', '_')}_{self.perception}"

    @property
    def label_noise(self) -> str:
        return "off" if self.perception == CLEAN else self.perception

    @property
    def pose_noise(self) -> tuple[float, float, float, float]:
        """(xy m, yaw rad, xy drift m/sqrt(s), yaw drift rad/sqrt(s))."""
        return (0.0,) * 4 if self.perception == CLEAN else (*POSE_NOISE, *POSE_DRIFT)

    def sets(self) -> tuple[str, ...]:
        xy, yaw, dxy, dyaw = self.pose_noise
        drift = (
            # only when there is one (the default is none): a checkout from before the drift
            # existed runs the noise-free arm too (--python, a baseline)
            (f"sim.pose_drift_xy_m_per_sqrt_s={dxy}", f"sim.pose_drift_yaw_rad_per_sqrt_s={dyaw}")
            if dxy or dyaw
            else ()
        )
        return (
            f'mapper.backend="{self.backend}"',
            f'sim.noise="{self.label_noise}"',
            f"sim.pose_noise_xy_m={xy}",
            f"sim.pose_noise_yaw_rad={yaw}",
            *drift,
        )

    def arm(self) -> ex.Arm:
        return ex.Arm(self.name, GRASS_COST_FACTOR, sets=self.sets())


def conditions() -> tuple[Condition, ...]:
    b = default_backend()
    return (
        Condition(b, CLEAN),
        *(Condition(b, level) for level in LEVELS),
        *(Condition(o, level) for o in OTHER_BACKENDS for level in OTHER_LEVELS),
    )


def _by_name() -> dict[str, Condition]:
    return {c.name: c for c in conditions()}


def experiment_config(quick: bool = False) -> ex.ExplorationExperimentConfig:
    """Full: SEEDS, the 16 m garden, BUDGET_S of robot time a run, 2 runs at once. Quick: one
    seed of the exploration quick form (6 m garden, small camera, 20 s), the default back-end at
    `realistic`: it tests the tooling, never the question."""
    arms = tuple(c.arm() for c in conditions())
    if quick:
        s = ex.ExplorationExperimentConfig.quick()
        s.seeds = SEEDS[:1]
        s.arms = (Condition(default_backend(), "realistic").arm(),)
        return s
    return ex.ExplorationExperimentConfig(
        seeds=SEEDS,
        arms=arms,
        size_m=SIZE_M,
        budget_s=BUDGET_S,
        extra=(
            *ex.ExplorationExperimentConfig.extra,
            *graph_bounds(SIZE_M),
            "deploy.standby_delay_s=3600",  # no hot spares: nothing restarts them in a run
        ),
    )


def graph_bounds(size_m: float) -> tuple[str, str]:
    """The navigation graph over the garden and 2 m round it, not the default 100 m: smaller
    patches and copies."""
    half = size_m / 2 + 2.0
    return f"navgraph.bounds_min_xy=[{-half}, {-half}]", f"navgraph.bounds_max_xy=[{half}, {half}]"


# -- rows ----------------------------------------------------------------------------------------


def time_to_share(history, end_m2: float | None, share: float = TIME_TO_SHARE):
    """(robot time s from the first history row, that row's absolute time) for the first row
    (t, explored_m2, frontier, distance_m) at which explored_m2 reached `share` of `end_m2` (the
    explorer's final count; the last row's without it); (None, None) with no history or nothing
    usable."""
    rows = [r for r in history or [] if len(r) >= 4]
    if not rows:
        return None, None
    end = end_m2 if end_m2 else rows[-1][1]
    if not end or end <= 0:
        return None, None
    for r in rows:
        if r[1] >= share * end:
            return float(r[0] - rows[0][0]), float(r[0])
    return None, None


def true_distance_by(run_dir: Path, t_s: float | None) -> float | None:
    """Metres the robot truly drove up to robot time `t_s`, from the recorder's true poses (the
    explorer's odometer adds up the pose noise: hundreds of metres at 0.10 m a pose)."""
    import numpy as np

    if t_s is None:
        return None
    try:
        traj = np.loadtxt(run_dir / "trajectory_truth.csv", delimiter=",", skiprows=1, ndmin=2)
    except (OSError, ValueError):
        return None
    if len(traj) < 2:
        return 0.0 if len(traj) else None
    steps = np.hypot(np.diff(traj[:, 1]), np.diff(traj[:, 2]))
    return float(np.interp(t_s, traj[:, 0], np.concatenate([[0.0], np.cumsum(steps)])))


def run_fields(row: dict, run_dir: Path) -> dict:
    """What one run's row holds beyond the exploration runner's: its arm's conditions, and from
    its metrics.json and explorer state the module docstring's measures."""
    from smana.deploy.report.measures import MOVED_M

    c = _by_name().get(row["arm"]) or Condition("?", "?")
    m = ex.load_json(run_dir / "metrics.json")
    state = ex.load_json(run_dir / "explorer" / "state.json")
    e = m.get("exploration") or {}
    ee = m.get("explorer") or {}
    warnings = m.get("warnings") or []
    measured = bool(e)  # it ran to its report
    dist = e.get("distance_m")
    t90, at = time_to_share(state.get("history"), ee.get("explored_m2"))
    outcome = bool(m) and ex.outcome_failure(row["exit_code"], m)
    return {
        "backend": c.backend,
        "perception": c.perception,
        "label_noise": c.label_noise,
        "pose_noise": list(c.pose_noise),
        "measured": measured,
        # the report's own verdict: FAILED (exit 1) on what the robot did
        "run_failed": measured and row["exit_code"] != 0,
        "outcome_only": measured and outcome,
        "run_warnings": "; ".join(warnings),
        "moved": None if dist is None else dist >= MOVED_M,
        "usable_share": e.get("usable_share"),
        "usable_area_m2": e.get("usable_area_m2"),
        "false_obstacle_share": e.get("false_obstacle_share"),
        "false_obstacle_area_m2": e.get("false_obstacle_area_m2"),
        "false_free_share": e.get("false_free_share"),
        "false_free_area_m2": e.get("false_free_area_m2"),
        "reachable_area_m2": e.get("reachable_area_m2"),
        "collisions": e.get("collisions"),
        "close_calls": e.get("close_calls"),
        # what the explorer's guard did (none from code before it)
        "guard_slowed": (ee.get("guard") or {}).get("slowed"),
        "guard_stopped": (ee.get("guard") or {}).get("stopped"),
        "trajectory_source": e.get("trajectory_source"),
        "time_to_90_s": t90,
        "distance_to_90_m": true_distance_by(run_dir, at),
    }


def finished(row: dict, run_dir: Path) -> bool:
    """The runner's `keep`: fills the row's fields (`run_fields`) and keeps a run that ran to its
    report (FAILED or not: a robot that failed is a result); a rerun into the same --out skips
    it."""
    row.update(run_fields(row, run_dir))
    row["ok"] = row["measured"]
    return row["measured"]


def rows_from_data(path: Path) -> list[dict]:
    """The rows of a data file (`<out>/data/robustness.json`), [] without one."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    return [r for r in data.get("rows") or [] if r.get("measured")]


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `robustness` subcommand of `smana experiment`."""
    names = ", ".join(c.name for c in conditions())
    e = sub.add_parser(
        "robustness",
        help="exploring under label noise off/medium/high/realistic with pose noise and drift, "
        "three back-ends, 10 seeds in a 16 m garden (hours: see --help)",
        description="Closed-loop exploration (one `smana up` per arm and seed) under perception "
        "noise: usable coverage, false-obstacle and false-free area, time to 90 %, collisions, "
        "runs that stopped short; the rules fixed before the runs (docs/experiments.md, "
        "'Beyond the paper: robustness').",
        epilog=f"Arms: {names}. " + DURATION + " Resumable: rerun the same command with the "
        "same --out, and the runs that ran to their report are kept (row.json beside each, or "
        "a row of <out>/data/robustness.json). Exits 1 if a run did not run to its report (a "
        "run `smana up` ended FAILED on what its robot did is a result, not an error).",
    )
    ex.add_common_args(
        e,
        quick_help="one run of 20 s in a 6 m garden (the default back-end, realistic noise)",
    )
    e.add_argument("--arms", help=f"comma-separated arms (default: all nine: {names})")
    e.add_argument(
        "--first-seed",
        type=int,
        help=f"the first seed (default {SEEDS[0]}, the rules' seeds; a pilot or a trial of a "
        "change takes others, so that the rules' seeds stay unseen until the runs)",
    )
    e.add_argument(
        "--python",
        metavar="PATH",
        help="run each `smana up` with this Python (another checkout's virtual environment: "
        "a baseline of older code); each run's report is then written again by this code, so "
        "that every run is measured the same way",
    )
    # the shared flags' defaults are the exploration experiment's: say this one's
    own = {
        "seeds": f"number of seeds, from {SEEDS[0]} up (default {len(SEEDS)}; quick 1)",
        "size": f"side of the garden, m (default {SIZE_M:g}; quick 6)",
        "budget": f"time budget per run, s of robot time (default {BUDGET_S:.0f}; quick 20)",
    }
    for action in e._actions:
        action.help = own.get(action.dest, action.help)


DURATION = (
    "Duration measured in trials on a 2-core machine shared with other work (seeds 41 to 45, "
    "octree-max, two runs at once): 98 to 373 s of wall a run, 260 s on average (a robot "
    "that ends early takes less; tsdf at realistic drove to the end of its 360 s in the first "
    "pilot). The 90 runs, 2 at once: about 3 to 4 hours by that measure. --quick, measured "
    "once: 32 s."
)


def _arms(args) -> tuple[ex.Arm, ...] | None:
    from smana.common.cli import UsageError

    if not getattr(args, "arms", None):
        return None
    known = _by_name()
    names = [v.strip() for v in args.arms.split(",") if v.strip()]
    if not names or any(v not in known for v in names):
        raise UsageError(f"--arms: expected some of {', '.join(known)}, got {args.arms!r}")
    return tuple(known[v].arm() for v in names)


def check_args(args, parser=None) -> None:
    """Refuse a bad --set or --arms now, not in every run (one line)."""
    from smana.common.config import SmanaConfig

    for c in conditions():
        SmanaConfig.load(overrides=[*ex.WORLD_SETS, *c.sets(), *args.extra])
    _arms(args)
    python = getattr(args, "python", None)
    if python and not (os.path.isfile(python) and os.access(python, os.X_OK)):
        from smana.common.cli import UsageError

        raise UsageError(f"--python {python}: not an executable file")


def main(args, parser, out: Path) -> int:
    arms = _arms(args)
    s = experiment_config(args.quick)
    first = SEEDS[0] if args.first_seed is None else args.first_seed
    if args.seeds or args.first_seed is not None:
        s.seeds = tuple(range(first, first + (args.seeds or len(s.seeds))))
    if args.budget:
        s.budget_s = args.budget
    if args.size:
        s.size_m = args.size
        if not args.quick:  # the graph's bounds follow the garden
            kept = (e for e in s.extra if not e.startswith("navgraph.bounds_"))
            s.extra = (*kept, *graph_bounds(args.size))
    if args.jobs:
        s.jobs = args.jobs
    if arms:
        s.arms = arms
    if getattr(args, "python", None):
        s.python = str(args.python)
    s.extra = (*s.extra, *args.extra)
    # runs a data file in --out already holds are kept (their rows, as row.json beside each)
    for r in rows_from_data(out / "data" / "robustness.json"):
        arm = ex.Arm(r["arm"], GRASS_COST_FACTOR)
        if r["seed"] in s.seeds and r["arm"] in {a.name for a in s.arms}:
            if ex.kept_row(out, r["seed"], arm) is None:
                (out / ex.run_name(r["seed"], arm)).mkdir(parents=True, exist_ok=True)
                ex.keep_row(out, r, arm)
    from .robustness_report import write_outputs  # it imports this module's arms and rules

    rows = ex.run_exploration(s, out, write=write_outputs, keep=finished)
    return ex.finish([{**r, "ok": r.get("measured")} for r in rows], out, "robustness")
