"""`smana experiment exploration` (paper 4.3): the whole stack (`smana up`) explores the garden,
one run per arm and seed, `--jobs` runs at once.

Arms: next-best-view (NBV) with the grass traversability cost at x1 (grass costs what terrain
costs), x2 (the class table) and x4, and the nearest-frontier baseline (Yamauchi 1997) at x2, all
in the same worlds. A seed fixes the world and the start pose (a random reachable free cell with
`SPAWN_CLEARANCE_M`, drawn from the seed's own generator).

Reported, each as a mean with its 95 % Student-t interval over seeds (lab/stats.py), and decided
by the intervals: the share of travelled graph nodes on terrain (paper: 60/70/88 %), its rise from
x1 to x4, and the distance to 95 % coverage of NBV against nearest-frontier.

Coverage. The report's coverage (metrics.json `exploration.coverage`) is ground truth, at the end
of the run: usable coverage, the share of the reachable traversable area (cells with the robot's
radius of clearance, connected to the start) whose final graph node is known as traversable. A
run that `smana up` ended FAILED on what its robot did alone (`outcome_failure`) is a result,
flagged `run_failed`; a robot that did not move scores 0 coverage and terrain share (`counted`).

Coverage curve. The explorer's history gives `explored_m2` over time, but counts something else:
known nodes its graph called traversable at each plan, reachable or not, in its own frame. The
curve is the explorer's count rescaled so that its last value equals the ground truth's known
share at the end (reachable cells under a known node, any label: deploy/report/measures.py
KNOWN_CURVE says why not the usable share): `coverage(t) = explored_m2(t) / explored_m2(end) *
known_gt(end)`; that assumes the share of the explorer's count that is reachable ground truth
stays the same over the run (an approximation, exact at the end). "Distance (time) to 95 %" is
the first history row where that curve reaches 0.95; a run that never does is censored ("not
reached"), never a number.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.zenoh_config import free_loopback_port

PAPER_TERRAIN_SHARE = {1.0: 0.60, 2.0: 0.70, 4.0: 0.88}  # grass cost factor -> terrain share
TERRAIN_SHARE_TOLERANCE = 0.10  # "within 10 points of the paper"
COVERAGE_TARGET = 0.95
SPAWN_CLEARANCE_M = 0.6

# The world every exploration run uses, as --set items; the one place to choose it: the
# cluttered garden with the paper's statistics (tests/test_garden_stats.py holds them).
WORLD_SETS: tuple[str, ...] = ('sim.garden.layout="3drms"',)
# The explorer's strategy key (Yamauchi's nearest frontier vs next best view).
STRATEGY_KEY = "explorer.strategy"
WEIGHT_KEY = "explorer.path_cost_weight"


@dataclass(frozen=True)
class Arm:
    """One condition of the experiment: a name, a grass cost factor and its own --set items."""

    name: str
    grass_cost_factor: float
    strategy: str = "nbv"
    sets: tuple[str, ...] = ()
    path_cost_weight: float | None = None

    @property
    def all_sets(self) -> tuple[str, ...]:
        out = list(self.sets)
        if self.strategy != "nbv":
            # only non-default strategies are set: an NBV run works on a build without the key
            out.append(f'{STRATEGY_KEY}="{self.strategy}"')
        if self.path_cost_weight is not None:
            out.append(f"{WEIGHT_KEY}={self.path_cost_weight}")
        return tuple(out)


def nbv(factor: float) -> Arm:
    return Arm(f"nbv_x{factor:g}", factor)


BASELINE = Arm("nearest_frontier_x2", 2.0, strategy="nearest_frontier")
FULL_ARMS = (nbv(1.0), nbv(2.0), nbv(4.0), BASELINE)


@dataclass
class ExplorationExperimentConfig:
    """What `smana experiment exploration` runs: one `smana up` per arm and seed."""

    # 5 seeds (world and start): 20 runs in 20 min; 8 would narrow the intervals by about a
    # third (t = 2.78 -> 2.36) in 32 min, still inside the 45-minute budget with the noise
    # experiment (--seeds 8)
    seeds: tuple[int, ...] = (3, 4, 5, 6, 7)
    arms: tuple[Arm, ...] = FULL_ARMS
    size_m: float = 12.0
    # the cluttered 12 m garden is explored (no view worth a trip) after 60 to 140 s of robot
    # time, 80 to 170 s of wall time with 2 runs at once; 150 s bounds the rare slow run
    budget_s: float = 150.0
    jobs: int = 2
    # a quarter of the default camera's pixels, square so the 57 degree view stays: a pixel spans
    # 2.5 cm at the 8 m range (1.2 cm at 640), still under the 10 cm map voxel, so each voxel's
    # label vote and the graph the explorer plans on keep their kind; rendering costs a quarter
    extra: tuple[str, ...] = ("sim.camera.width=320", "sim.camera.height=320")
    is_quick: bool = False  # the test suite's small version: its summary says so on top
    # the Python that runs each `smana up` ("": this one); another checkout's (a baseline of
    # older code) has the run's report written again by this code, so both measure alike
    python: str = ""

    @classmethod
    def quick(cls) -> ExplorationExperimentConfig:
        # a 6 m garden, a small camera and a 10 cm map: short closed loops for the test suite;
        # the two ends of the grass cost and the baseline
        small = (
            "sim.camera.width=160",
            "sim.camera.height=160",
            "mapper.resolution_m=0.1",
            "navgraph.bounds_min_xy=[-4.0, -4.0]",
            "navgraph.bounds_max_xy=[4.0, 4.0]",
            # no hot spares: a 20 s run would start five only to stop them
            "deploy.standby_delay_s=3600",
        )
        return cls(
            is_quick=True,
            seeds=(3, 4),
            arms=(nbv(1.0), nbv(4.0), BASELINE),
            size_m=6.0,
            budget_s=20.0,
            extra=small,
        )


# -- one run -------------------------------------------------------------------------------------


def experiment_world(seed: int, size_m: float, world_sets=WORLD_SETS):
    """(config, world) of one seed as the runs build it: the garden of `sim.seed` with the
    experiment's size and world overrides."""
    from smana.common.classes import ClassTable
    from smana.common.config import SmanaConfig
    from smana.services.sim.worlds.garden import generate

    cfg = SmanaConfig.load(
        overrides=[f"sim.seed={seed}", f"sim.garden.size_m={size_m}", *world_sets]
    )
    return cfg, generate(cfg.sim.seed, cfg.sim.garden, ClassTable.load(cfg.general.class_table))


def run_world_sets(extra=()) -> tuple[str, ...]:
    """WORLD_SETS with the garden overrides among `extra` (`--set sim.garden.layout="wheel"`,
    and the class table the garden's classes need: the wet garden's water) in place of those
    they override: the world the runs explore, where the starts are drawn."""
    garden = [e for e in extra if e.strip().startswith(("sim.garden.", "general.class_table"))]
    keys = {e.split("=", 1)[0].strip() for e in garden}
    return (*(e for e in WORLD_SETS if e.split("=", 1)[0].strip() not in keys), *garden)


def layout_of(extra=()) -> str:
    """The garden layout the last `--set sim.garden.layout=...` among `extra` chose ("" when
    none did): it names a run's data file (`data_variant`) and the routes it is judged against
    (report.py)."""
    layouts = [
        value.strip().strip("\"'")
        for key, _, value in (e.partition("=") for e in extra)
        if key.strip() == "sim.garden.layout"
    ]
    return layouts[-1] if layouts else ""


def pick_spawn(seed: int, size_m: float, world_sets=WORLD_SETS) -> list[float]:
    """[x, y, yaw]: a free cell with SPAWN_CLEARANCE_M, reachable from the world's own start
    (its free spot nearest the centre), drawn from the seed's generator."""
    from smana.lab import evaluation as ev

    _, world = experiment_world(seed, size_m, world_sets)
    trav, reach, _ = ev.reachable_from_spawn(world, SPAWN_CLEARANCE_M)
    xs, ys = trav.cell_centres()
    ii, jj = np.nonzero(reach)
    # its own stream, apart from the world's: the start does not move when world generation does
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57A7]))
    k = int(rng.integers(len(ii)))
    yaw = float(rng.uniform(-math.pi, math.pi))
    return [round(float(xs[ii[k]]), 3), round(float(ys[jj[k]]), 3), round(yaw, 3)]


def run_name(seed: int, arm: Arm) -> str:
    return f"seed{seed}_{arm.name}"


def set_aside(run_dir: Path) -> None:
    """A run runs in an empty folder: what an interrupted run left there (a map autosave, a
    journal, the explorer's state) would be resumed by the new one's services (`mapper.load =
    auto`, the explorer's restart), a robot teleported back to its spawn inside a map of the
    last run. It is moved to `<name>.interrupted-N`, kept for a look, never read."""
    if not run_dir.exists():
        return
    n = 1
    while run_dir.with_name(f"{run_dir.name}.interrupted-{n}").exists():
        n += 1
    run_dir.rename(run_dir.with_name(f"{run_dir.name}.interrupted-{n}"))


def exploration_run(out: Path, seed: int, arm: Arm, s: ExplorationExperimentConfig, spawn=None):
    """One `smana up` run; returns (exit code, metrics, explorer state, cpu seconds, wall s)."""
    from smana.common.classes import ClassTable

    terrain = ClassTable.load("garden3drms").by_name("terrain").cost
    # absolute: the supervisor starts each service inside the run directory
    run_dir = (out / run_name(seed, arm)).resolve()
    # a robot name of its own: stray processes of another stack that reach this router (a reused
    # port) then talk on other keys
    robot = f"exp{os.getpid()}-s{seed}-{arm.name}".replace(".", "_")
    sets = [
        f'general.robot="{robot}"',
        f"sim.seed={seed}",
        f"sim.garden.size_m={s.size_m}",
        *WORLD_SETS,
        f"explorer.time_budget_s={s.budget_s}",
        f'explorer.class_costs=["grass={arm.grass_cost_factor * terrain}"]',
        *arm.all_sets,
        *s.extra,
    ]
    if spawn is not None:
        sets.append(f"sim.spawn={list(spawn)}")
    port = free_loopback_port()
    argv = [s.python or sys.executable, "-m", "smana.deploy.cli", "up", "--run-dir", str(run_dir)]
    argv += ["--set", f'deploy.router_listen=["tcp/127.0.0.1:{port}"]']
    for item in sets:
        argv += ["--set", item]
    set_aside(run_dir)
    run_dir.mkdir(parents=True)
    t0 = time.perf_counter()
    with open(run_dir / "up.log", "w") as f:
        # its own process group, so a timeout ends the whole stack; Ctrl-C no longer reaches it
        # by itself, run_exploration forwards it (LIVE_GROUPS)
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        LIVE_GROUPS.add(p.pid)
        # a hung run must not hang the experiment: its process group is ended after a timeout
        timer = threading.Timer(s.budget_s * 3 + 180, os.killpg, (p.pid, signal.SIGKILL))
        timer.start()
        try:
            # wait4, not wait: the run's own CPU time (its supervisor waits for its services)
            _, status, usage = os.wait4(p.pid, 0)
        finally:
            timer.cancel()
            LIVE_GROUPS.discard(p.pid)
        p.returncode = code = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if s.python and (run_dir / "metrics.json").exists():
        # another checkout ran it: this code's report functions measure it, as every other run
        subprocess.run(
            [sys.executable, "-m", "smana.deploy.report", str(run_dir)],
            stdout=subprocess.DEVNULL,
            check=False,
        )
    metrics = load_json(run_dir / "metrics.json")
    state = load_json(run_dir / "explorer" / "state.json")
    return code, metrics, state, usage.ru_utime + usage.ru_stime, wall


LIVE_GROUPS: set[int] = set()  # process groups of the runs under way


def load_json(path: Path) -> dict:
    """A run's JSON file ({} when it is missing or does not read)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def coverage_curve(history, explored_m2_end: float | None, coverage_end: float | None):
    """(robot time s from the first row, distance m, coverage) arrays from the explorer's history
    rows (t, explored_m2, frontier_size, distance_m), rescaled to the ground-truth coverage at
    the end (module docstring); empty arrays when either end is missing."""
    h = np.asarray(history or [], float).reshape(-1, 4)
    empty = np.zeros(0)
    if not len(h) or coverage_end is None:
        return empty, empty, empty
    end = explored_m2_end if explored_m2_end else h[-1, 1]
    if not end > 0:
        return empty, empty, empty
    cov = np.clip(h[:, 1] / end * coverage_end, 0.0, 1.0)
    return h[:, 0] - h[0, 0], h[:, 3], cov


def first_reach(x: np.ndarray, cov: np.ndarray, target: float = COVERAGE_TARGET) -> float | None:
    """x at the first row where coverage reaches `target`; None (censored) if it never does."""
    hit = np.nonzero(cov >= target)[0]
    return float(x[hit[0]]) if len(hit) else None


def outcome_failure(code: int, m: dict) -> bool:
    """`smana up` exited 1 on what the robot did alone (deploy/report/checks.py
    OUTCOME_WARNINGS: it did not move, found no path, knew under half the reachable area as
    usable, was closed in by its own map): a measured failure, not a run that failed to run."""
    from smana.deploy.report.checks import OUTCOME_WARNINGS

    warnings = m.get("warnings") or []
    return code == 1 and bool(warnings) and all(w.startswith(OUTCOME_WARNINGS) for w in warnings)


# A run whose robot did not move explored nothing: it counts as a failure, scoring 0 on these
# (what its sensors saw from the start is not exploration), never as missing data.
STILL_SCORES = ("coverage", "terrain_share", "terrain_share_true")


def stood_still(r: dict) -> bool:
    """The row's robot did not move (`moved` False, or a distance under MOVED_M)."""
    from smana.deploy.report.measures import MOVED_M

    moved = r.get("moved")
    if moved is None and r.get("distance_m") is not None:
        moved = r["distance_m"] >= MOVED_M
    return moved is False


def counted(r: dict, key: str):
    """The value a row counts with in every table and verdict: its own, except that a measured
    run whose robot stood still scores 0 on STILL_SCORES (a failure, not missing data)."""
    if key in STILL_SCORES and r.get("ok") and stood_still(r):
        return 0.0
    return r.get(key)


# Time and distance to 95 % as times to an event (lab/survival.py). A run that did not reach 95 %
# by its end, because its budget ran out, its explorer stopped early or its robot did not move,
# did not reach it within the budget: censored there. Robot time has the budget as its end;
# distance has no budget, so such a run is censored beyond every distance (infinity): it is at
# risk through every event of the others and is never counted as having reached it. A robot
# that did not move counts as not reached even if its camera saw 95 % from where it stood.
NOT_REACHED_DISTANCE = math.inf


def time_to_event(r: dict, key: str, horizon: float, failed: bool = False) -> tuple[float, bool]:
    """(value, censored) of `key` ("time_to_95_s" or "distance_to_95_m") for a measured run:
    its value when it reached 95 %; censored at `horizon` (the budget for time,
    NOT_REACHED_DISTANCE for distance) when it did not, or when it counts as a failure
    (`failed`, or its robot stood still)."""
    v = r.get(key)
    if v is None or failed or stood_still(r):
        return float(horizon), True
    return float(v), False


def horizon_of(key: str, budget_s: float | None, rows: list[dict], end: str) -> float:
    """Where a run that did not reach 95 % is censored: at the budget for robot time (or, when
    no budget is known, the latest end among the runs, `end` their robot time at the end); for
    distance, beyond every distance."""
    if key.startswith("distance"):
        return NOT_REACHED_DISTANCE
    if budget_s:
        return float(budget_s)
    ends = [float(r[end]) for r in rows if r.get(end) is not None]
    ends += [float(r[key]) for r in rows if r.get(key) is not None]
    return max(ends) if ends else math.inf


def make_row(seed: int, arm: Arm, code: int, m: dict, state: dict, cpu_s: float, wall_s: float):
    from smana.deploy.report.measures import KNOWN_CURVE, MOVED_M

    ex = m.get("exploration") or {}
    ee = m.get("explorer") or {}
    t, d, cov = coverage_curve(state.get("history"), ee.get("explored_m2"), ex.get(KNOWN_CURVE))
    failed = bool(m) and outcome_failure(code, m)
    # a run that FAILED on what its robot did is a result (flagged `run_failed`), not a gap
    ok = (code == 0 and bool(m)) or failed
    dist = ex.get("distance_m")
    return {
        "seed": seed,
        "arm": arm.name,
        "strategy": arm.strategy,
        "grass_cost_factor": arm.grass_cost_factor,
        "path_cost_weight": arm.path_cost_weight,
        "exit_code": code,
        "ok": ok,
        "run_failed": failed,
        "moved": None if dist is None else dist >= MOVED_M,
        "terrain_share": ex.get("terrain_share"),
        "coverage": ex.get("coverage"),
        "usable_area_m2": ex.get("usable_area_m2"),
        "false_obstacle_share": ex.get("false_obstacle_share"),
        "false_free_share": ex.get("false_free_share"),
        "known_share": ex.get(KNOWN_CURVE),
        "reachable_area_m2": ex.get("reachable_area_m2"),
        "distance_m": dist,
        "min_clearance_m": ex.get("min_clearance_m"),
        "done_reason": ee.get("done_reason"),
        "robot_time_s": float(t[-1]) if len(t) else None,
        "distance_to_95_m": first_reach(d, cov),
        "time_to_95_s": first_reach(t, cov),
        "wall_time_s": round(wall_s, 1),
        "cpu_s": round(cpu_s, 1),
        "real_time_factor": _achieved_rtf(ee),
        "curve": {"t_s": t.tolist(), "distance_m": d.tolist(), "coverage": cov.tolist()},
    }


def _achieved_rtf(ee: dict) -> float | None:
    """Robot seconds per wall second over the exploration (the sim's status reports the same
    factor live but leaves no record): the explorer's elapsed robot time over its wall time."""
    t, wall = ee.get("elapsed_s"), ee.get("wall_time_s")
    return round(t / wall, 3) if t and wall else None


def terminate(signum, frame):
    """A signal handler: SIGTERM ends an experiment as Ctrl-C does (its runs are stopped)."""
    raise KeyboardInterrupt(f"signal {signum}")


ROW_FILE = "row.json"  # a finished run's row, beside its outputs (a rerun keeps it)


def keep_row(out: Path, row: dict, arm: Arm) -> None:
    """Write a finished run's row beside its outputs (ROW_FILE), whole or not at all."""
    path = out / run_name(row["seed"], arm) / ROW_FILE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(row))
    tmp.replace(path)


def kept_row(out: Path, seed: int, arm: Arm) -> dict | None:
    """The row a finished run of (seed, arm) left in `out`, or None (not run, not kept, or a file
    that does not read as that run's row: it runs again)."""
    try:
        row = json.loads((out / run_name(seed, arm) / ROW_FILE).read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(row, dict) and (row.get("seed"), row.get("arm")) == (seed, arm.name)
    return row if same else None


def run_exploration(
    s: ExplorationExperimentConfig, out: Path, log=progress.say, write=None, keep=None
) -> list[dict]:
    """Every arm x seed, `s.jobs` at once; writes the outputs (`write(rows, s, out)`, by default
    the exploration's) and returns the rows. `keep(row, run_dir)`: a run whose row it accepts is
    finished, its row saved beside its outputs (`row.json`), and a rerun into the same `out`
    reads it back instead of running it again (an interrupted experiment resumes, as the fleet
    experiment does); without `keep` every run runs."""
    spawns = {seed: pick_spawn(seed, s.size_m, run_world_sets(s.extra)) for seed in s.seeds}
    todo = [(seed, arm) for seed in s.seeds for arm in s.arms]
    rows = []
    if keep is not None:
        for seed, arm in list(todo):
            kept = kept_row(out, seed, arm)
            if kept is not None:
                rows.append(kept)
                todo.remove((seed, arm))
        if rows:
            log(f"{len(rows)} finished run(s) kept from {out}; {len(todo)} to run")
    # a `kill` (SIGTERM) stops the runs as Ctrl-C does: each `smana up` is in its own process
    # group and would otherwise live on without the experiment
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, terminate)
    runs = progress.bar(len(todo), "exploration", unit="run")
    pool = ThreadPoolExecutor(max_workers=s.jobs)
    try:
        futs = {
            pool.submit(exploration_run, out, seed, arm, s, spawns[seed]): (seed, arm)
            for seed, arm in todo
        }
        for fut in as_completed(futs):
            seed, arm = futs[fut]
            try:
                row = make_row(seed, arm, *fut.result())
            except Exception as exc:  # a run that could not even start is a failed run
                row = make_row(seed, arm, -1, {}, {}, 0.0, 0.0)
                log(f"{run_name(seed, arm)}: {exc}")
            if keep is not None and keep(row, out / run_name(seed, arm)):
                keep_row(out, row, arm)
            rows.append(row)
            runs.update()
            log(
                f"{run_name(seed, arm)}: exit {row['exit_code']}, {row['wall_time_s']} s, "
                f"terrain share {row['terrain_share']}, coverage {row['coverage']}"
            )
    except BaseException:
        # Ctrl-C: stop the queued runs and ask the running stacks to stop as `smana up` would
        pool.shutdown(wait=False, cancel_futures=True)
        for pid in list(LIVE_GROUPS):
            try:
                os.killpg(pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        raise
    finally:
        pool.shutdown(wait=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    runs.close()
    rows.sort(key=lambda r: ([a.name for a in s.arms].index(r["arm"]), r["seed"]))
    if write is None:
        from .exploration_report import write_exploration_outputs as write  # imports this module

    write(rows, s, out)
    return rows


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `exploration` subcommand of `smana experiment`."""
    e = sub.add_parser(
        "exploration",
        help="terrain share vs grass cost, NBV vs nearest frontier "
        "(measured once: about 20 min; --quick 3 min)",
        description="Paper 4.3: one `smana up` per arm (NBV at grass x1, x2, x4; nearest "
        "frontier at x2) and seed; terrain share of travelled nodes, coverage curves, verdicts.",
        epilog="Duration measured once on a 2-core machine: about 20 minutes (4 arms x 5 seeds = "
        "20 runs of "
        "smana up, 2 at once, about 2 min each in the cluttered 12 m garden: measured 19 min "
        "50 s; --seeds 8 about 32 min); --quick about 3 minutes (3 arms x 2 seeds of 20 s in "
        "a 6 m garden). A progress bar with an ETA shows on a terminal "
        "(SMANA_PROGRESS=1 forces it, 0 hides it). Exits 1 if any run failed.",
    )
    add_common_args(
        e, quick_help="3 arms x 2 seeds of 20 s in a 6 m garden (measured once: about 3 min)"
    )
    e.add_argument(
        "--arms",
        help="comma-separated subset of the arms, e.g. nbv_x2,nearest_frontier_x2 "
        "(default: " + ",".join(a.name for a in FULL_ARMS) + ")",
    )


def add_common_args(e, quick_help: str, seeds_help: str = "default 5; quick 2") -> None:
    from smana.common.cli import positive_float, positive_int

    e.add_argument("--quick", action="store_true", help=quick_help)
    e.add_argument(
        "--out", type=Path, help="output directory (default runs/experiment-<name>-<time>)"
    )
    e.add_argument("--seeds", type=positive_int, help=f"number of seeds, from 3 up ({seeds_help})")
    e.add_argument(
        "--size", type=positive_float, help="side of the garden, m (default 12; quick 6)"
    )
    e.add_argument(
        "--budget", type=positive_float, help="time budget per run, s of robot time (default 150)"
    )
    e.add_argument("--jobs", type=positive_int, help="runs of smana up at once (default 2)")
    e.add_argument(
        "--set",
        dest="extra",
        action="append",
        default=[],
        help="extra config override for every run",
    )


def check_args(args, parser=None) -> None:
    """Refuse a bad --set now, not in every run (ConfigError, one line)."""
    from smana.common.config import SmanaConfig

    SmanaConfig.load(overrides=[*WORLD_SETS, *args.extra])
    apply_args(ExplorationExperimentConfig(), args)  # a bad --arms: one line, before any run


def apply_args(s: ExplorationExperimentConfig, args) -> ExplorationExperimentConfig:
    from smana.common.cli import UsageError

    if args.seeds:
        s.seeds = tuple(range(3, 3 + args.seeds))
    if args.budget:
        s.budget_s = args.budget
    if getattr(args, "size", None):
        s.size_m = args.size
    if getattr(args, "arms", None) is not None:  # `--arms ""` is no arm, not all
        known = {a.name: a for a in (*FULL_ARMS, *s.arms)}
        names = [v.strip() for v in args.arms.split(",") if v.strip()]
        bad = [v for v in names if v not in known]
        if bad or not names:
            raise UsageError(f"--arms: expected some of {', '.join(known)}, got {args.arms!r}")
        s.arms = tuple(known[v] for v in names)
    if args.jobs:
        s.jobs = args.jobs
    s.extra = (*s.extra, *args.extra)
    return s


def finish(rows: list[dict], out: Path, name: str) -> int:
    failed = sum(not r["ok"] for r in rows)
    print(f"results in {out} ({name}_summary.md)")
    if failed:
        print(f"warning: {failed} of {len(rows)} runs failed (see {name}_summary.md)")
        return 1
    return 0


def main(args, parser, out: Path) -> int:
    s = ExplorationExperimentConfig.quick() if args.quick else ExplorationExperimentConfig()
    rows = run_exploration(apply_args(s, args), out)
    return finish(rows, out, "exploration")
