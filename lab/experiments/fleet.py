"""`smana experiment fleet`: does a fleet explore faster, without a worse map and without touching
each other? One `smana up --robots N` per world, fleet size N and seed, `--jobs` runs at once.

Worlds: the default garden (12 m) and one 3.4 times its area (22 m, `sim.garden.size_m`), both
the exploration experiment's cluttered layout. A seed fixes the world and the spawn
(`exploration.pick_spawn`, the same for every N: the first member starts there, the simulator
places the others `fleet.spawn_spacing_m` apart).

Reported per world and N, each as a mean with its 95 % Student-t interval over seeds
(lab/stats.py): robot time and total distance (all members) to 95 % coverage, coverage at the
end, the overlap of the members' maps, the merged map's reconstruction error and classification
ratio, robot-robot contacts. The numbers are the run report's (`metrics.json` "fleet",
deploy/report/fleet.py): its coverage curve is the members' explored area (the largest any
member had reported) rescaled to the ground-truth coverage at the end, as the exploration
experiment's.

Verdicts, never from one run:
- in the larger world, time to 95 % with 2 robots at most 0.6 times one robot's, with 3 at most
  0.45 times: the ratio per seed (paired: same world, same spawn), its mean and interval; met
  when the interval's upper end is under the target, not met when its lower end is above,
  inconclusive otherwise. A seed where either run never reached 95 % is censored (left out, and
  said so), never given a number;
- the merged map as accurate as a single robot's: per seed, the fleet's error minus the 1-robot
  run's (met when the interval reaches 0 or lies below), the classification ratio likewise
  (reaches 0 or lies above);
- zero robot-robot contacts over all runs.
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path

from smana.common import progress
from smana.common.zenoh_config import free_loopback_port
from smana.lab import plots, stats

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
        ex._LIVE.add(p.pid)  # the exploration runner's: Ctrl-C stops these runs too
        # N stacks share the cores: robot time runs slower than for one robot
        timer = threading.Timer(
            s.budget(world) * (2 + 2 * n) + 240, os.killpg, (p.pid, signal.SIGKILL)
        )
        timer.start()
        try:
            _, status, usage = os.wait4(p.pid, 0)
        finally:
            timer.cancel()
            ex._LIVE.discard(p.pid)
        code = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    return code, ex._load(run_dir / "metrics.json"), usage.ru_utime + usage.ru_stime, wall


# A warning that is one of the experiment's outcomes, not a failure of the run: a run whose only
# warnings are robot-robot contacts exits 1 but is data (its contacts are counted, its coverage
# and map scored). Dropping it would leave the contact count to runs that had none.
OUTCOME_WARNING = re.compile(r"^\d+ robot-robot contact\(s\)")


def run_ok(code: int, m: dict) -> bool:
    """A run is data when it left its figures and exited 0, or exited 1 for outcomes only."""
    warnings = m.get("warnings") or [] if m else []
    outcomes_only = bool(warnings) and all(OUTCOME_WARNING.match(str(w)) for w in warnings)
    return bool(m) and (code == 0 or (code == 1 and outcomes_only))


def make_row(seed: int, world: World, n: int, code: int, m: dict, cpu_s: float, wall_s: float):
    """One run's figures from its metrics.json: the "fleet" section, or for a run of one robot
    without it, the single robot's exploration and map (the same curve, exploration.py's)."""
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
    return ex._load(Path(m["run_dir"]) / "explorer" / "state.json").get("history") or []


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
        previous = signal.signal(signal.SIGTERM, ex._terminate)
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
                row = make_row(seed, w, n, *fut.result())
            except Exception as exc:  # a run that could not even start is a failed run
                row = make_row(seed, w, n, -1, {}, 0.0, 0.0)
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
        for pid in list(ex._LIVE):
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
    write_fleet_outputs(rows, s, out)
    return rows


# -- aggregation ---------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "time_to_95_s",
    "distance_to_95_m",
    "coverage",
    "overlap",
    "map_error_m",
    "classification_ratio",
    "robot_contacts",
)


def summarise_fleet(rows: list[dict]) -> list[dict]:
    """Per world and N: the intervals of SUMMARY_KEYS over the runs that ran (time and distance
    to 95 % over those that reached it, with how many did)."""
    out = []
    for world, n in dict.fromkeys((r["world"], r["n_robots"]) for r in rows):
        sel = [r for r in rows if r["world"] == world and r["n_robots"] == n]
        ok = [r for r in sel if r["ok"]]
        out.append(
            {
                "world": world,
                "size_m": sel[0]["size_m"],
                "n_robots": n,
                "runs": len(sel),
                "failed": len(sel) - len(ok),
                "reached_95": sum(r["time_to_95_s"] is not None for r in ok),
                **{k: ex._ci(sel, k).as_dict() for k in SUMMARY_KEYS},
            }
        )
    return out


def _by_seed(rows, world: str, n: int, key: str) -> dict[int, float | None]:
    return {
        r["seed"]: r[key] for r in rows if r["ok"] and r["world"] == world and r["n_robots"] == n
    }


def _met(d: stats.Decision) -> str:
    return {stats.REPRODUCED: MET, stats.NOT_REPRODUCED: NOT_MET}.get(d.verdict, d.verdict)


def decide_below(ci: stats.Interval, target: float) -> stats.Decision:
    """ "At most `target`" as a one-sided test: met when the interval's upper end is under it
    (p_yes: the test "mean >= target"), not met when its lower end is above. A time ratio's
    target is positive: the rule is non-inferiority with the target as its margin."""
    return stats.decide_not_worse(ci, target)


def target_below(ci: stats.Interval, target: float) -> str:
    """ "At most `target`": met when the interval's upper end is under it, not met when its lower
    end is above, inconclusive otherwise (or without an interval)."""
    return _met(decide_below(ci, target))


def not_worse(ci: stats.Interval, lower_is_better: bool, margin: float) -> str:
    """A paired difference (fleet minus one robot) that must not be worse by more than `margin`
    (declared before the runs, `NOT_WORSE_MARGINS`): met when its interval lies on the good side
    of the margin, not met when wholly on the bad side (`stats.decide_not_worse`). An interval
    that merely holds 0 is not enough: it must be narrow enough to rule the margin out."""
    return _met(stats.decide_not_worse(ci, margin, higher_is_better=not lower_is_better))


def time_ratios(rows: list[dict], world: str, n: int) -> tuple[dict[int, float], list[int]]:
    """(seed -> time to 95 % with n robots over one robot's, the censored seeds: one of the two
    runs never reached 95 %). Seeds where either run failed are in neither."""
    one, many = _by_seed(rows, world, 1, "time_to_95_s"), _by_seed(rows, world, n, "time_to_95_s")
    ratios, censored = {}, []
    for seed in sorted(one.keys() & many.keys()):
        a, b = one[seed], many[seed]
        if a is None or b is None:
            censored.append(seed)
        elif a > 0:
            ratios[seed] = b / a
    return ratios, censored


def _end_time(row: dict) -> float | None:
    """A run's robot time at its end: `end_time_s` (what the committed data keeps, having no
    curves), or the last time of its curve."""
    if row.get("end_time_s") is not None:
        return float(row["end_time_s"])
    t = (row.get("curve") or {}).get("t_s") or []
    return float(t[-1]) if t else None


def bounded_ratios(rows: list[dict], world: str, n: int) -> dict[int, tuple[float, str]]:
    """seed -> (time to 95 % with n robots over one robot's, how it is known): "" exact;
    "above" when the fleet never reached 95 % (the ratio is above its robot time at the end over
    one robot's time); "below" when the lone robot never did (below the fleet's time over the
    lone robot's time at the end). Censored seeds are kept as these bounds, not dropped; a seed
    where neither reached 95 %, or a run failed, says nothing and is left out."""
    by = {
        (r["seed"], r["n_robots"]): r
        for r in rows
        if r["ok"] and r["world"] == world and r["n_robots"] in (1, n)
    }
    out: dict[int, tuple[float, str]] = {}
    for seed in sorted({s for s, m in by if (s, 1) in by and (s, n) in by}):
        one, many = by[(seed, 1)], by[(seed, n)]
        a, b = one["time_to_95_s"], many["time_to_95_s"]
        if a is not None and b is not None and a > 0:
            out[seed] = (b / a, "")
        elif a is not None and a > 0 and b is None and _end_time(many):
            out[seed] = (_end_time(many) / a, "above")
        elif a is None and b is not None and _end_time(one):
            out[seed] = (b / _end_time(one), "below")
    return out


def decide_below_censored(bounded: dict[int, tuple[float, str]], target: float) -> stats.Decision:
    """ "At most `target`" over per-seed ratios some of which are bounds (`bounded_ratios`):
    the interval of the values and bounds decides as `decide_below` does, except that a ratio
    known only to lie above its bound forbids "met" (its true value could be anything larger),
    and one known only to lie below forbids "not met"."""
    d = decide_below(stats.mean_ci([v for v, _ in bounded.values()]), target)
    kinds = {kind for _, kind in bounded.values()}
    if (d.verdict == stats.REPRODUCED and "above" in kinds) or (
        d.verdict == stats.NOT_REPRODUCED and "below" in kinds
    ):
        return stats.Decision(stats.INCONCLUSIVE, d.p_yes, d.p_no, d.alpha, "a censored bound")
    return d


def target_below_censored(bounded: dict[int, tuple[float, str]], target: float) -> str:
    return _met(decide_below_censored(bounded, target))


def paired_difference(rows: list[dict], world: str, n: int, key: str) -> stats.Interval:
    """Interval of (n robots minus one robot) of `key` over the seeds both ran with a value."""
    one, many = _by_seed(rows, world, 1, key), _by_seed(rows, world, n, key)
    return stats.mean_ci(
        [
            many[k] - one[k]
            for k in sorted(one.keys() & many.keys())
            if one[k] is not None and many[k] is not None
        ]
    )


def verdicts(rows: list[dict], large_world: str = LARGE_GARDEN.name) -> list[dict]:
    """The targets, each decided by intervals over seeds: (claim, target, smana, verdict) rows."""
    out = []
    worlds = list(dict.fromkeys(r["world"] for r in rows))
    sizes = sorted({r["n_robots"] for r in rows})
    if large_world in worlds and 1 in sizes:
        for n, target in TIME_TARGETS.items():
            if n not in sizes:
                continue
            bounded = bounded_ratios(rows, large_world, n)
            ci = stats.mean_ci([v for v, _ in bounded.values()])
            kept = [
                f"seed {k}: {'>' if kind == 'above' else '<'} {v:.2f}"
                for k, (v, kind) in bounded.items()
                if kind
            ]
            note = f"; censored (never reached 95 %), kept as bounds: {', '.join(kept)}"
            d = decide_below_censored(bounded, target)
            out.append(
                {
                    "claim": f"{large_world}: time to {100 * COVERAGE_TARGET:.0f} % coverage with "
                    f"{n} robots over one robot's, paired per seed",
                    "target": f"<= {target:g}",
                    "smana": ci.format(fmt=".2f") + (note if kept else ""),
                    "verdict": _met(d),
                    "p": d.p,
                    "rule": "at most T",
                }
            )
    for world in worlds:
        for n in sizes:
            if n == 1 or 1 not in sizes:
                continue
            for key, what, lower in (
                ("map_error_m", "reconstruction error (m)", True),
                ("classification_ratio", "classification ratio", False),
            ):
                ci = paired_difference(rows, world, n, key)
                margin = NOT_WORSE_MARGINS[key]
                d = stats.decide_not_worse(ci, margin, higher_is_better=not lower)
                out.append(
                    {
                        "claim": f"{world}: merged map's {what} with {n} robots minus one "
                        "robot's, paired per seed, not worse",
                        "target": (f"below +{margin:g}" if lower else f"above -{margin:g}")
                        + " (margin)",
                        "smana": ci.format(fmt=".4f" if lower else ".3f"),
                        "verdict": _met(d),
                        "p": d.p,
                        "rule": "not worse",
                    }
                )
    ok = [r for r in rows if r["ok"]]
    counts = [r.get("robot_contacts") for r in ok]
    known = [c for c in counts if c is not None]
    total = int(sum(known))
    if total:
        verdict = NOT_MET
    elif ok and len(known) == len(counts):
        verdict = MET
    else:
        verdict = stats.INCONCLUSIVE
    out.append(
        {
            "claim": "robot-robot contacts over all runs",
            "target": "0",
            "smana": f"{total} in {len(known)} runs"
            + (
                f" ({len(counts) - len(known)} runs without a count)"
                if len(known) < len(counts)
                else ""
            ),
            "verdict": verdict,
            "p": None,  # a count, not a test
            "rule": "a count",
        }
    )
    for v in out:
        v["paper"] = v["target"]
    return out


# -- outputs -------------------------------------------------------------------------------------


def write_fleet_outputs(rows: list[dict], s: FleetExperimentConfig, out: Path) -> list[Path]:
    """fleet.md (verdicts on top), fleet.json (settings, runs, summary, verdicts), fleet.csv and a
    coverage-vs-time figure per world; returns the figures."""
    out.mkdir(parents=True, exist_ok=True)
    # the end time beside the curve: the censored bounds need it, and the data file has no curves
    rows = [dict(r, end_time_s=_end_time(r)) for r in rows]
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    if flat:
        with open(out / "fleet.csv", "w", newline="") as f:
            # every row's fields (a row kept from an older run may lack the newer ones)
            fields = list(dict.fromkeys(k for r in flat for k in r))
            w = csv.DictWriter(f, fieldnames=fields, restval="")
            w.writeheader()
            w.writerows(flat)
    summary = summarise_fleet(rows)
    from .report import write_data

    write_data(out, "fleet", rows, asdict(s))
    table = verdicts(rows)
    (out / "fleet.json").write_text(
        json.dumps(
            {"settings": asdict(s), "runs": rows, "summary": summary, "verdicts": table}, indent=2
        )
    )
    figures = _figures(rows, out)
    lines = ["# Fleet experiment", ""]
    if s.is_quick:
        lines += [
            f"**Quick run**: the default garden, {' and '.join(map(str, s.robots))} robots, "
            f"{len(s.seeds)} seed(s) of {s.budget(s.worlds[0]):.0f} s. It checks that the "
            "experiment works; its verdicts say nothing (the full run: `smana experiment fleet`).",
            "",
        ]
    failed = [r for r in rows if not r["ok"]]
    if failed:
        names = ", ".join(
            f"{run_name(r['seed'], r['world'], r['n_robots'])} (exit {r['exit_code']})"
            for r in failed
        )
        lines += [
            f"**WARNING: {len(failed)} of {len(rows)} runs failed** (no metrics or non-zero "
            f"exit), left out of every number below: {names}.",
            "",
        ]
    lines += [
        "| claim | target | smana mean [95 % CI] (n) | verdict |",
        "|---|---|---|---|",
        *(f"| {v['claim']} | {v['target']} | {v['smana']} | {v['verdict']} |" for v in table),
        "",
        f"Seeds {list(s.seeds)}, worlds "
        + ", ".join(f"{w.name} ({w.size_m:g} m, budget {s.budget(w):.0f} s)" for w in s.worlds)
        + f", {s.jobs} run(s) at once. World: {' '.join(ex.WORLD_SETS)}.",
        "",
        "| world | robots | runs (failed) | reached 95 % | time to 95 % (s) | total distance to "
        "95 % (m) | coverage | overlap | map error (m) | classification ratio | contacts |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for d in summary:
        iv = {k: ex._interval(d[k]) for k in SUMMARY_KEYS}
        lines.append(
            f"| {d['world']} | {d['n_robots']} | {d['runs']} ({d['failed']}) | "
            f"{d['reached_95']} of {d['runs'] - d['failed']} | "
            f"{iv['time_to_95_s'].format(fmt='.0f')} | {iv['distance_to_95_m'].format()} | "
            f"{iv['coverage'].format(100, unit=' %')} | {iv['overlap'].format(100, unit=' %')} | "
            f"{iv['map_error_m'].format(fmt='.3f')} | "
            f"{iv['classification_ratio'].format(fmt='.3f')} | "
            f"{iv['robot_contacts'].format(fmt='.1f')} |"
        )
    lines += [
        "",
        "Time and distance to 95 % are over the runs that reached it; the others are counted "
        "as not reached (censored), never as a number. The distance is every member's, added.",
        "",
        "| run | exit | coverage | time to 95 % (s) | distance to 95 % (m) | overlap | "
        "contacts | min separation (m) | wall (s) | CPU (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t95 = "not reached" if r["time_to_95_s"] is None else f"{r['time_to_95_s']:.0f}"
        lines.append(
            f"| {run_name(r['seed'], r['world'], r['n_robots'])} | {r['exit_code']} | "
            f"{ex._pct(r['coverage'])} | {t95} | {ex._num(r['distance_to_95_m'])} | "
            f"{ex._pct(r['overlap'])} | {_int(r['robot_contacts'])} | "
            f"{ex._num(r['min_separation_m'], '.2f')} | {ex._num(r['wall_time_s'], '.0f')} | "
            f"{ex._num(r['cpu_s'], '.0f')} |"
        )
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    (out / "fleet.md").write_text("\n".join(lines))
    return figures


def _int(v) -> str:
    return "-" if v is None else str(int(v))


def _figures(rows: list[dict], out: Path) -> list[Path]:
    """Coverage against robot time per world, one curve (mean and interval over seeds) per N."""
    saved = []
    for world in dict.fromkeys(r["world"] for r in rows):
        curves = []
        for n in sorted({r["n_robots"] for r in rows if r["world"] == world}):
            sel = [r for r in rows if r["world"] == world and r["n_robots"] == n]
            c = ex.mean_curve(sel, "t_s")
            if c is not None:
                k = sum(1 for r in sel if r["ok"] and len(r["curve"]["t_s"]) >= 2)
                curves.append((f"{n} robot{'s' * (n > 1)} (n = {k})", *c))
        if curves:
            size = next(r["size_m"] for r in rows if r["world"] == world)
            saved.append(
                plots.save(
                    plots.band_plot(
                        curves,
                        f"Coverage vs robot time, {size:g} m garden",
                        "robot time (s)",
                        "coverage (rescaled to ground truth at the end)",
                        note="mean and 95 % CI over seeds",
                        hline=COVERAGE_TARGET,
                        clip=(0.0, 1.0),  # a share
                    ),
                    out / f"fleet_coverage_time_{world}.png",
                )
            )
    return saved


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
    failed = sum(not r["ok"] for r in rows)
    print(f"results in {out} (fleet.md)")
    if failed:
        print(f"warning: {failed} of {len(rows)} runs failed (see fleet.md)")
        return 1
    return 0
