"""`smana experiment fleet`: does a fleet explore faster, without a worse map and without touching
each other? One `smana up --robots N` per world, fleet size N and seed, `--jobs` runs at once.

Worlds: the default garden (12 m) and one 3.4 times its area (22 m, `sim.garden.size_m`), both
the exploration experiment's cluttered layout. A seed fixes the world and the spawn
(`exploration.pick_spawn`, the same for every N: the first member starts there, the simulator
places the others `fleet.spawn_spacing_m` apart).

Reported per world and N (lab/stats.py, lab/survival.py): time and total distance (all members)
to 95 % coverage as times to an event (how many runs reached it, Kaplan-Meier medians, the
restricted mean time up to the budget, and the log-rank test against one robot), coverage at the
end, the overlap of the members' maps, the merged map's reconstruction error and classification
ratio (each a mean with its 95 % Student-t interval over seeds), robot-robot contacts. The
numbers are the run report's (`metrics.json` "fleet", deploy/report/fleet.py): its coverage
curve is the members' explored area (the largest any member had reported) rescaled to the
ground-truth coverage at the end, as the exploration experiment's.

A run that did not reach 95 % by its end did not reach it within the budget: censored at the
budget (exploration.py `time_to_event`). A run that `smana up` ended FAILED on what its robots
did (a member that did not move or found no path: `run_failed`) is a result, not a gap: it
counts as not reached, censored at the budget, and its map is scored as it is. Only a run that
left no figures is missing (and named).

Verdicts, never from one run:
- in the larger world, time to 95 % with 2 robots at most 0.6 times one robot's, with 3 at most
  0.45 times, paired per seed (same world, same spawn): per seed, is the fleet's time under T
  times the lone robot's? Known when both reached 95 %, and often when one did not (a fleet at
  150 s is under 0.6 times a lone robot that had not reached it by 700 s). The exact sign test
  over the seeds whose order is known (for pairs, the log-rank test stratified by seed): met
  when the fleet is under significantly often, not met when over; the seeds whose order
  censoring hides are counted and left out of the test. The restricted mean times are given
  beside it;
- the merged map as accurate as a single robot's: per seed, the fleet's error minus the 1-robot
  run's, not worse by more than a margin declared before the runs, the classification ratio
  likewise;
- zero robot-robot contacts over all runs.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from smana.common import progress
from smana.common.zenoh_config import free_loopback_port

from . import exploration as ex

COVERAGE_TARGET = ex.COVERAGE_TARGET
# fleet size -> the largest time to 95 % it may take, as a share of one robot's (larger world)
TIME_TARGETS = {2: 0.6, 3: 0.45}
# "Not worse" margins, declared before the runs (issue 26): a merged map may be worse than one
# robot's by less than 5 mm of reconstruction error (one robot's is about 37 mm at 10 cm voxels)
# and 1 point of classification ratio; the paired interval must rule out anything more
NOT_WORSE_MARGINS = {"map_error_m": 0.005, "classification_ratio": 0.01}
MET, NOT_MET = "met", "not met"  # a target's verdict; otherwise stats.INCONCLUSIVE


@dataclass(frozen=True)
class World:
    name: str
    size_m: float
    budget_s: float  # robot time per run


DEFAULT_GARDEN = World("garden12", 12.0, 150.0)
# 22 m: 3.4 times the default garden's area. One robot reached 95 % of it in 375 s (seed 3, 395 s
# to the end): the budget leaves it room, so that the 1-robot runs the ratios divide by finish
LARGE_GARDEN = World("garden22", 22.0, 700.0)


@dataclass
class FleetExperimentConfig:
    """What `smana experiment fleet` runs: one `smana up --robots N` per world, N and seed."""

    seeds: tuple[int, ...] = (3, 4, 5)
    worlds: tuple[World, ...] = (DEFAULT_GARDEN, LARGE_GARDEN)
    robots: tuple[int, ...] = (1, 2, 3)
    # a fleet of 3 is 3 simulated cameras and 3 stacks on a 2-core machine: one run at a time
    jobs: int = 1
    budget_s: float | None = None  # overrides every world's budget
    # no hot spares: a fleet of 3 is 14 services, whose spares would prepare mid-run
    extra: tuple[str, ...] = (
        "sim.camera.width=320",
        "sim.camera.height=320",
        "deploy.standby_delay_s=3600",
    )
    is_quick: bool = False

    @classmethod
    def quick(cls) -> FleetExperimentConfig:
        # the default garden, 1 and 2 robots, one seed, a short budget: two runs of ~1 min
        return cls(
            is_quick=True,
            seeds=(3,),
            worlds=(DEFAULT_GARDEN,),
            robots=(1, 2),
            budget_s=40.0,
            extra=(
                "sim.camera.width=160",
                "sim.camera.height=160",
                "deploy.standby_delay_s=3600",  # no hot spares for a 40 s run
            ),
        )

    def budget(self, world: World) -> float:
        return self.budget_s if self.budget_s is not None else world.budget_s


# -- one run -------------------------------------------------------------------------------------


def run_name(seed: int, world: str, n: int) -> str:
    return f"{world}_n{n}_seed{seed}"


def fleet_argv(run_dir: Path, seed: int, world: World, n: int, s, spawn=None, port=None):
    """The `smana up --robots N` command line of one run."""
    # every run a fleet (`--robots 1` too: a one-member fleet is a lone robot, bit for bit, and
    # its report has the same "fleet" section); each on its own loopback port
    sets = [
        f"sim.seed={seed}",
        f"sim.garden.size_m={world.size_m}",
        *ex.WORLD_SETS,
        f"explorer.time_budget_s={s.budget(world)}",
        *s.extra,
    ]
    if spawn is not None:
        sets.append(f"sim.spawn={list(spawn)}")
    port = free_loopback_port() if port is None else port
    argv = [sys.executable, "-m", "smana.deploy.cli", "up", "--robots", str(n)]
    argv += ["--run-dir", str(run_dir)]
    argv += ["--set", f'deploy.router_listen=["tcp/127.0.0.1:{port}"]']
    for item in sets:
        argv += ["--set", item]
    return argv


def fleet_run(out: Path, seed: int, world: World, n: int, s: FleetExperimentConfig, spawn=None):
    """One `smana up --robots N`; returns (exit code, metrics, cpu seconds, wall seconds)."""
    run_dir = (out / run_name(seed, world.name, n)).resolve()
    ex.set_aside(run_dir)  # an interrupted run's leftovers would be resumed
    run_dir.mkdir(parents=True)
    argv = fleet_argv(run_dir, seed, world, n, s, spawn)
    t0 = time.perf_counter()
    with open(run_dir / "up.log", "w") as f:
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        ex.LIVE_GROUPS.add(p.pid)  # the exploration runner's: Ctrl-C stops these runs too
        # N stacks share the cores: robot time runs slower than for one robot
        timer = threading.Timer(
            s.budget(world) * (2 + 2 * n) + 240, os.killpg, (p.pid, signal.SIGKILL)
        )
        timer.start()
        try:
            _, status, usage = os.wait4(p.pid, 0)
        finally:
            timer.cancel()
            ex.LIVE_GROUPS.discard(p.pid)
        code = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    return code, ex.load_json(run_dir / "metrics.json"), usage.ru_utime + usage.ru_stime, wall


# A warning that is one of the experiment's outcomes, not a failure of the run: a run whose only
# warnings are robot-robot contacts exits 1 but is data (its contacts are counted, its coverage
# and map scored). Dropping it would leave the contact count to runs that had none. A member
# that did not do its job ("r3: the robot did not move", "the fleet knows only ...") is an
# outcome too: the run is data and counts as a failed one (`run_failed`).
OUTCOME_WARNING = re.compile(r"^\d+ robot-robot contact\(s\)")
MEMBER = re.compile(r"^[A-Za-z0-9_-]+: ")


def _failure_warning(w: str) -> bool:
    """A warning on what a member (or the fleet) did: exploration.OUTCOME_WARNINGS's, after the
    member's name, or the fleet's own "knows only"."""
    from smana.deploy.report.checks import OUTCOME_WARNINGS

    text = MEMBER.sub("", str(w), count=1).replace("the fleet knows", "the robot knows")
    return text.startswith(OUTCOME_WARNINGS)


def run_failed(code: int, m: dict) -> bool:
    """`smana up` exited 1 on outcomes only, a member's failure among them."""
    warnings = [str(w) for w in (m.get("warnings") or [])] if m else []
    outcomes = all(OUTCOME_WARNING.match(w) or _failure_warning(w) for w in warnings)
    return code == 1 and outcomes and any(_failure_warning(w) for w in warnings)


def run_ok(code: int, m: dict) -> bool:
    """A run is data when it left its figures and exited 0, or exited 1 for outcomes only
    (contacts, or a member that failed: `run_failed`)."""
    warnings = [str(w) for w in (m.get("warnings") or [])] if m else []
    outcomes_only = bool(warnings) and all(
        OUTCOME_WARNING.match(w) or _failure_warning(w) for w in warnings
    )
    return bool(m) and (code == 0 or (code == 1 and outcomes_only))


def failed(r: dict) -> bool:
    """The row counts as a failed run (not reached, its map scored as it is): `run_failed`; in
    data written before that field, a run that exited 1 and left its figures (`smana up`
    said FAILED on what its robots did: the runs of docs/experiments.md, a member that never
    moved)."""
    if "run_failed" in r:
        return bool(r["run_failed"])
    return not r.get("ok") and r.get("exit_code") == 1 and r.get("coverage") is not None


def measured(r: dict) -> bool:
    """The row is data: a run that ran (`ok`) or one that failed on what its robots did."""
    return bool(r.get("ok")) or failed(r)


def make_row(
    seed: int,
    world: World,
    n: int,
    code: int,
    m: dict,
    cpu_s: float,
    wall_s: float,
    budget_s: float | None = None,
):
    """One run's figures from its metrics.json: the "fleet" section, or for a run of one robot
    without it, the single robot's exploration and map (the same curve, exploration.py's);
    `budget_s`, its robot time budget, is where a run that did not reach 95 % is censored."""
    f = m.get("fleet") or {}
    mp = m.get("map") if isinstance(m.get("map"), dict) else {}
    if f:
        sim = f.get("sim") or {}
        curve = f.get("curve") or {"t_s": [], "distance_m": [], "coverage": []}
        row = {
            "coverage": f.get("coverage"),
            "time_to_95_s": f.get("time_to_95_s"),
            "distance_to_95_m": f.get("distance_to_95_m"),
            "total_distance_m": f.get("total_distance_m"),
            "overlap": f.get("overlap"),
            "robot_contacts": sim.get("robot_contacts_total"),
            "min_separation_m": sim.get("min_separation_overall_m"),
        }
        merged = (f.get("map") or {}).get("merged")
        if isinstance(merged, dict):
            mp = merged
    else:
        e, ee = m.get("exploration") or {}, m.get("explorer") or {}
        t, d, cov = ex.coverage_curve(_history(m), ee.get("explored_m2"), e.get("coverage"))
        curve = {"t_s": t.tolist(), "distance_m": d.tolist(), "coverage": cov.tolist()}
        row = {
            "coverage": e.get("coverage"),
            "time_to_95_s": ex.first_reach(t, cov),
            "distance_to_95_m": ex.first_reach(d, cov),
            "total_distance_m": e.get("distance_m"),
            "overlap": None,
            # one robot cannot touch another
            "robot_contacts": 0 if n == 1 and m else None,
            "min_separation_m": None,
        }
    ex_ = m.get("exploration") or {}
    return {
        "seed": seed,
        "world": world.name,
        "size_m": world.size_m,
        "n_robots": n,
        "exit_code": code,
        "ok": run_ok(code, m),
        "run_failed": run_failed(code, m),
        "budget_s": budget_s,
        # it ran to its end and left its figures (failed or not): a rerun keeps it, so that a
        # failure is not traded for another try (delete its directory to run it again)
        "finished": bool(m) and code >= 0,
        "warnings": list(m.get("warnings") or []) if m else [],
        **row,
        "map_error_m": mp.get("reconstruction_error_mean_m"),
        "classification_ratio": mp.get("classification_ratio"),
        "collisions": ex_.get("collisions"),
        "wall_time_s": round(wall_s, 1),
        "cpu_s": round(cpu_s, 1),
        "curve": curve,
    }


ROW_FILE = "row.json"


def _keep_row(out: Path, row: dict) -> None:
    """A finished run's row beside its outputs, so a rerun into the same --out keeps it."""
    path = out / run_name(row["seed"], row["world"], row["n_robots"]) / ROW_FILE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(row))
    tmp.replace(path)


def _kept_row(out: Path, seed: int, world: World, n: int) -> dict | None:
    """The row a finished run of (seed, world, n) left in `out`, failed or not, or None (not run,
    interrupted, or a file that does not read as that run's row: it runs again)."""
    path = out / run_name(seed, world.name, n) / ROW_FILE
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(row, dict) and (row.get("seed"), row.get("world"), row.get("n_robots")) == (
        seed,
        world.name,
        n,
    )
    return row if same and row.get("finished", row.get("ok")) else None


def _history(m: dict) -> list:
    """A single robot's explorer history, read back from its run directory."""
    if not m.get("run_dir"):
        return []
    return ex.load_json(Path(m["run_dir"]) / "explorer" / "state.json").get("history") or []


def run_fleet(s: FleetExperimentConfig, out: Path, log=progress.say) -> list[dict]:
    """Every world x N x seed, `s.jobs` at once; writes the outputs and returns the rows."""
    spawns = {(w.name, seed): ex.pick_spawn(seed, w.size_m) for w in s.worlds for seed in s.seeds}
    todo = [(seed, w, n) for w in s.worlds for seed in s.seeds for n in s.robots]
    rows = []
    for seed, w, n in list(todo):  # an interrupted experiment, run again into the same --out
        kept = _kept_row(out, seed, w, n)
        if kept is not None:
            rows.append(kept)
            todo.remove((seed, w, n))
    if rows:
        log(f"{len(rows)} finished run(s) kept from {out}; {len(todo)} to run")
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, ex.terminate)
    bar = progress.bar(len(todo), "fleet", unit="run")
    pool = ThreadPoolExecutor(max_workers=s.jobs)
    try:
        futs = {
            pool.submit(fleet_run, out, seed, w, n, s, spawns[(w.name, seed)]): (seed, w, n)
            for seed, w, n in todo
        }
        for fut in as_completed(futs):
            seed, w, n = futs[fut]
            try:
                row = make_row(seed, w, n, *fut.result(), budget_s=s.budget(w))
            except Exception as exc:  # a run that could not even start is a failed run
                row = make_row(seed, w, n, -1, {}, 0.0, 0.0, s.budget(w))
                log(f"{run_name(seed, w.name, n)}: {exc}")
            if row["finished"]:
                _keep_row(out, row)
            rows.append(row)
            bar.update()
            log(
                f"{run_name(seed, w.name, n)}: exit {row['exit_code']}, {row['wall_time_s']} s, "
                f"coverage {row['coverage']}, time to 95 % {row['time_to_95_s']}"
            )
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        for pid in list(ex.LIVE_GROUPS):
            try:
                os.killpg(pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        raise
    finally:
        pool.shutdown(wait=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    bar.close()
    order = [w.name for w in s.worlds]
    rows.sort(key=lambda r: (order.index(r["world"]), r["n_robots"], r["seed"]))
    from .fleet_report import write_fleet_outputs  # it imports this module's runs and targets

    write_fleet_outputs(rows, s, out)
    return rows


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `fleet` subcommand of `smana experiment`."""
    from smana.common.cli import positive_float, positive_int

    e = sub.add_parser(
        "fleet",
        help="1, 2 and 3 robots exploring the 12 m and 22 m gardens "
        "(measured once: about 80 min; --quick 2 min)",
        description="One `smana up --robots N` per world (12 m and 22 m garden), N (1, 2, 3) and "
        "seed: time and total distance to 95 % coverage, overlap, merged map's accuracy, "
        "robot-robot contacts; verdicts on the speed-up in the larger world.",
        epilog="Duration measured once on a 2-core machine, one run at a time (2026-11-27): 3 "
        "seeds x 2 worlds x 3 fleet sizes = 18 runs; the 22 m garden's 5 to 9 min each (59 min in "
        "all), the 12 m garden's 1 to 3 min each (18 min): about 80 minutes (--seeds 5 about "
        "2 h 10 min). The 22 m garden alone at 8 seeds (24 runs), as two experiments of 12 at "
        "once (--first-seed 3 and 7, --seeds 4 each): 1 h 40 min (2026-12-03). --quick 2 "
        "minutes (the 12 m garden, 1 and 2 robots, 1 seed of 40 s). A progress bar with an "
        "ETA shows on a terminal (SMANA_PROGRESS=1 forces it, 0 hides it). Run it again with "
        "the same --out to finish an interrupted experiment: the runs that finished are kept, "
        "the rest run; a run that finished and failed is kept as failed (delete its directory "
        "to run it again). Exits 1 if any run failed.",
    )
    e.add_argument(
        "--quick", action="store_true", help="1 seed, 1 and 2 robots, 12 m (measured once: 2 min)"
    )
    e.add_argument(
        "--out", type=Path, help="output directory (default runs/experiment-fleet-<time>)"
    )
    e.add_argument("--seeds", type=positive_int, help="number of seeds, from 3 up (default 3)")
    e.add_argument(
        "--first-seed",
        type=positive_int,
        help="the first seed (default 3): two machines, or two runs at once, each take a share "
        "of the seeds; copy one's run directories into the other's --out and run it again with "
        "every seed to get the whole experiment's outputs",
    )
    e.add_argument(
        "--robots", help="comma-separated fleet sizes (default 1,2,3; 1 is the reference)"
    )
    e.add_argument(
        "--worlds",
        help=f"comma-separated subset of {DEFAULT_GARDEN.name},{LARGE_GARDEN.name} (default both)",
    )
    e.add_argument(
        "--budget",
        type=positive_float,
        help=f"time budget per run, s of robot time (default {DEFAULT_GARDEN.budget_s:.0f} in the "
        f"{DEFAULT_GARDEN.size_m:g} m garden, {LARGE_GARDEN.budget_s:.0f} in the "
        f"{LARGE_GARDEN.size_m:g} m one)",
    )
    e.add_argument("--jobs", type=positive_int, help="runs of smana up at once (default 1)")
    e.add_argument("--set", dest="extra", action="append", default=[], help="extra config override")


def apply_args(s: FleetExperimentConfig, args) -> FleetExperimentConfig:
    from smana.common.cli import UsageError

    first = getattr(args, "first_seed", None) or 3
    if args.seeds or first != 3:
        s.seeds = tuple(range(first, first + (args.seeds or len(s.seeds))))
    if args.budget:
        s.budget_s = args.budget
    if args.jobs:
        s.jobs = args.jobs
    if args.robots:
        try:
            sizes = tuple(sorted({int(v) for v in args.robots.split(",") if v.strip()}))
        except ValueError:
            sizes = ()
        if not sizes or min(sizes) < 1:
            raise UsageError(f"--robots: expected fleet sizes like 1,2,3, got {args.robots!r}")
        s.robots = sizes
    if args.worlds:
        known = {w.name: w for w in (DEFAULT_GARDEN, LARGE_GARDEN)}
        names = [v.strip() for v in args.worlds.split(",") if v.strip()]
        if not names or any(v not in known for v in names):
            raise UsageError(f"--worlds: expected some of {', '.join(known)}, got {args.worlds!r}")
        s.worlds = tuple(known[v] for v in names)
    s.extra = (*s.extra, *args.extra)
    return s


def check_args(args, parser=None) -> None:
    """Refuse a bad --set, --robots or --worlds now, not in every run."""
    from smana.common.config import SmanaConfig

    SmanaConfig.load(overrides=[*ex.WORLD_SETS, *args.extra])
    apply_args(FleetExperimentConfig(), args)


def main(args, parser, out: Path) -> int:
    s = FleetExperimentConfig.quick() if args.quick else FleetExperimentConfig()
    rows = run_fleet(apply_args(s, args), out)
    bad = sum(not r["ok"] or failed(r) for r in rows)
    print(f"results in {out} (fleet.md)")
    if bad:
        print(f"warning: {bad} of {len(rows)} runs failed (see fleet.md)")
        return 1
    return 0
