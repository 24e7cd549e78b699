"""`smana experiment risk` in closed loop: does planning on the map's label
distribution keep a robot that maps as it drives out of the water that only semantics can see?

The whole stack (`smana up`, run by the exploration experiment's runner: the same starts, budget
and failure accounting) explores the wet garden (`sim.garden.water_share`, class table
`garden3drms_wet`: ponds of water, flat, beside the paths and across the lawns) with NBV, the
class table's grass cost and the TSDF back-end: the back-end whose robot still drives under this
noise (`smana experiment navnoise`: octree-max's robots never moved; in a probe of the wet garden,
seed 3, the octree-bayes robot drove 0.45 m in 80 s, half its graph's nodes obstacles from noisy
hedge labels, where the TSDF robot drove 6.1 m), in four arms on the same seeds:

- `clean`, the reference: noise-free perception (`sim.noise = "none"`: SLIC with its majority
  label; no pose noise), `planner.risk = "expected"`;
- `expected`, `cvar` (`risk_alpha` 0.2), `chance` (`max_risk` 0.25): label noise p = 0.7
  (`sim.noise = "high"`: SLIC, then Table 2's confusions, water among them, services/sim/degrade.py)
  and the paper's highest pose noise (0.10 m on x and y, 0.02 rad on yaw, per pose), under that
  `planner.risk` (its other fields at their defaults). The explorer asks the planner for every
  path (`planner/path`), so each arm's robot drives the paths of its mode.

Measured against ground truth, never the map, from each run's true trajectory (the recorder's
`trajectory_truth.csv`) on its world (rebuilt from the run's config.toml):
- forbidden entries: how many times the true path entered a graph node (navgraph's resolution)
  whose true class, at the node's centre, is forbidden (water); forbidden nodes: how many
  distinct ones; forbidden time: robot seconds with the robot's centre on water;
- the true cost of the travelled path: its length plus t_f x T(true class) of every node entered
  (eq. 1 without the height term; a forbidden node at `planner.risk_forbidden_cost`);
- path length (the true distance driven), contacts (the run report's, footprint on an obstacle)
  and the ground-truth coverage at the end (the run report's).

Rules, fixed before the runs (lab/stats.py; per seed, the same seeds in every arm), for `cvar`
and for `chance` against `expected` (the target fixed before the runs, at p = 0.7):
1. ">= 50 % fewer forbidden entries": the ratio of the arm's entries to expected's (sum over sum,
   its interval Fieller's, `stats.ratio_ci`) is below 0.5, decided by the per-seed differences
   arm - 0.5 x expected, whose interval must lie below 0 (`decide_not_worse`, margin 0; not
   met when it lies above 0);
2. "paths <= 10 % longer": per seed, the arm's true distance over expected's, minus 1, not worse
   than +0.10 (`decide_not_worse`; a seed where expected's robot did not move is left out);
3. "no loss of success": an exploration's success is what it explored: per seed the arm's
   ground-truth coverage minus expected's, not worse than -0.05 (`decide_not_worse`, higher is
   better).
The six verdicts are corrected together (Holm) in the run's summary, and with every other claim
in docs/experiments.md. Contacts are counts, reported per arm, not tested.

One more arm, `label` (the default planner: the label's cost alone, under the same noise), is on
`--arms` to show what planning on the distribution changes at all; no verdict uses it.

A run that `smana up` ended with a navigation warning only (the robot did not move, no path was
ever found) is what the arm did, not a failed run (as in navnoise): it is kept, with no entries
and its distance. A rerun into the same --out keeps the finished runs (`row.json` beside each).
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from smana.lab import stats

from . import exploration as ex
from . import exploration_report as exr
from .noise import POSE_NOISE

WATER_SHARE = 0.1  # of the garden seen from above (services/sim/worlds/water.py)
WET_GARDEN = ('general.class_table="garden3drms_wet"', f"sim.garden.water_share={WATER_SHARE}")
BACKEND = "tsdf"
GRASS_COST_FACTOR = 2.0  # the class table's own grass cost (x2 terrain's)
LABEL_NOISE = "high"  # services/sim/degrade.py NOISE_LEVELS: p = 0.7
POSE_LEVEL = "high"  # noise.POSE_NOISE: (0.10 m, 0.02 rad)
FEWER = 0.5  # rule 1: at most half expected's entries
LONGER_MARGIN = 0.10  # rule 2: at most 10 % longer
COVERAGE_MARGIN = 0.05  # rule 3: coverage at most 5 points lower
TRUTH_FILE = "trajectory_truth.csv"  # the recorder's true poses: t, x, y, z, yaw


@dataclass(frozen=True)
class Condition:
    """One arm: its perception (noisy or not) and its [planner] risk fields."""

    name: str
    noisy: bool
    planner: tuple[tuple[str, object], ...]

    def sets(self) -> tuple[str, ...]:
        xy, yaw = POSE_NOISE[POSE_LEVEL] if self.noisy else (0.0, 0.0)
        return (
            f'mapper.backend="{BACKEND}"',
            f'sim.noise="{LABEL_NOISE if self.noisy else "none"}"',
            f"sim.pose_noise_xy_m={xy}",
            f"sim.pose_noise_yaw_rad={yaw}",
            *(f"planner.{k}={json.dumps(v)}" for k, v in self.planner),
        )

    def arm(self) -> ex.Arm:
        return ex.Arm(self.name, GRASS_COST_FACTOR, sets=self.sets())


CONDITIONS = (
    Condition("clean", False, (("risk", "expected"),)),
    Condition("expected", True, (("risk", "expected"),)),
    Condition("cvar", True, (("risk", "cvar"), ("risk_alpha", 0.2))),
    # 0.25, not the default 0.1: the synthetic form closed every node at 0.1 (lab/.../risk.py)
    Condition("chance", True, (("risk", "chance"), ("max_risk", 0.25))),
)
# not in the default run, in no verdict (`--arms` adds it): the default planner, the label's cost
# alone, under the same noise; what the distribution itself changes
EXTRA_CONDITIONS = (Condition("label", True, (("risk", "label"),)),)
ARMS = tuple(c.arm() for c in CONDITIONS)
_BY_NAME = {c.name: c for c in (*CONDITIONS, *EXTRA_CONDITIONS)}
TESTED = ("cvar", "chance")


def experiment_config(quick: bool = False) -> ex.ExplorationExperimentConfig:
    """Full: 10 seeds, a 10 m wet garden, 75 s of robot time per run, 2 runs at once. Quick: one
    seed (the four arms: two rounds of two runs), the exploration quick form's 6 m garden, small
    camera and 10 cm map, 20 s: it tests the tooling, never the question."""
    if quick:
        s = ex.ExplorationExperimentConfig.quick()
        s.seeds = (3,)
    else:
        s = ex.ExplorationExperimentConfig(
            seeds=tuple(range(3, 13)),
            size_m=10.0,
            budget_s=75.0,
            extra=(
                *ex.ExplorationExperimentConfig.extra,
                # the graph over the garden and a margin, not 100 m: smaller patches and copies
                "navgraph.bounds_min_xy=[-7.0, -7.0]",
                "navgraph.bounds_max_xy=[7.0, 7.0]",
                "deploy.standby_delay_s=3600",  # no hot spares in a run this short
            ),
        )
    # the wet garden is the experiment's world, not an arm's: the starts are drawn in it
    # (`exploration.pick_spawn`), so that no robot starts in water
    s.extra = (*s.extra, *WET_GARDEN)
    s.arms = ARMS
    return s


# -- ground truth ---------------------------------------------------------------------------------


def true_path_fields(traj: np.ndarray, world, config) -> dict:
    """What a true trajectory ((t, x, y, yaw) rows) did in `world`, by the module docstring's
    measures, with the run's config (its navgraph grid, planner weights, explorer costs)."""
    from smana.deploy.report import ground_truth as gt

    classes = world.classes
    top = world.top_class()
    if len(traj) < 2:
        return {"forbidden_entries": 0, "forbidden_nodes": 0, "forbidden_time_s": 0.0,
                "true_cost": 0.0, "length_m": 0.0}  # fmt: skip
    xy = traj[:, 1:3]
    length = float(np.hypot(*np.diff(xy, axis=0).T).sum())
    on = classes.forbidden_lut[top.at(xy[:, 0], xy[:, 1])]
    time_s = float(np.sum(np.diff(traj[:, 0])[on[:-1]]))
    origin = np.asarray(config.navgraph.bounds_min_xy, float)
    res = config.navgraph.resolution_m
    nodes = gt.travelled_nodes(xy, res, origin)[1:]  # the start node is not entered
    centres = (nodes + 0.5) * res + origin
    true = top.at(centres[:, 0], centres[:, 1]) if len(nodes) else np.zeros(0, int)
    bad = classes.forbidden_lut[true]
    lut = classes.costs(classes.cost_overrides(config.explorer.class_costs))
    t = lut[true]
    t = np.where(np.isfinite(t), t, config.planner.risk_forbidden_cost)
    return {
        "forbidden_entries": int(bad.sum()),
        "forbidden_nodes": len({tuple(c) for c in nodes[bad]}),
        "forbidden_time_s": time_s,
        "true_cost": length + config.planner.t_f * float(t.sum()),
        "length_m": length,
    }


def run_truth(run_dir: Path, worlds: dict) -> dict:
    """The ground-truth fields of one run directory ({} without its true trajectory); `worlds`
    caches the world per seed and size (every arm of a seed drives the same garden)."""
    from smana.deploy.report import ground_truth as gt

    path = run_dir / TRUTH_FILE
    if not path.is_file():
        return {}
    try:
        traj = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)[:, [0, 1, 2, 4]]
    except (ValueError, IndexError):
        return {}
    config = gt.load_run_config(run_dir)
    key = (config.sim.seed, config.sim.garden.size_m, config.sim.garden.water_share)
    if key not in worlds:
        worlds[key] = gt.world_from_config(config)
    return true_path_fields(traj, worlds[key], config)


def nav_outcome_only(row: dict, m: dict) -> bool:
    """A run that `smana up` ended (exit 1) on what its robot did alone: a result."""
    return ex.outcome_failure(row["exit_code"], m)


def finished(row: dict, run_dir: Path) -> bool:
    """A run whose row is a result (kept on a rerun): it ran, or only its navigation failed."""
    return bool(row["ok"]) or nav_outcome_only(row, ex.load_json(run_dir / "metrics.json"))


def with_truth(rows: list[dict], out: Path) -> list[dict]:
    """The exploration rows with their arm's risk mode and noise, the run's contacts and
    warnings, and the ground-truth fields of its true path."""
    worlds: dict = {}
    full = []
    for r in rows:
        c = _BY_NAME[r["arm"]]
        run_dir = out / ex.run_name(r["seed"], c.arm())
        m = ex.load_json(run_dir / "metrics.json")
        e = m.get("exploration") or {}
        truth = run_truth(run_dir, worlds) if m else {}
        ok = bool(truth) and bool(r["ok"] or nav_outcome_only(r, m))
        full.append(
            {
                **r,
                "ok": ok,
                "risk": dict(c.planner)["risk"],
                "noisy": c.noisy,
                "run_warnings": "; ".join(m.get("warnings") or []),
                "collisions": e.get("collisions"),
                "close_calls": e.get("close_calls"),
                "forbidden_entries": truth.get("forbidden_entries"),
                "forbidden_nodes": truth.get("forbidden_nodes"),
                "forbidden_time_s": truth.get("forbidden_time_s"),
                "true_cost": truth.get("true_cost"),
                "length_m": truth.get("length_m"),
            }
        )
    return full


# -- verdicts -------------------------------------------------------------------------------------


def _by_seed(rows: list[dict], arm: str, key: str) -> dict[int, float]:
    return {
        r["seed"]: float(ex.counted(r, key))
        for r in rows
        if r.get("arm") == arm and r.get("ok") and ex.counted(r, key) is not None
    }


def entries_ratio(rows: list[dict], arm: str) -> tuple[stats.Interval, stats.Interval]:
    """(the ratio of the arm's forbidden entries to expected's with its Fieller interval, the
    interval of the per-seed differences arm - FEWER x expected), on the seeds both have."""
    a, b = _by_seed(rows, arm, "forbidden_entries"), _by_seed(rows, "expected", "forbidden_entries")
    seeds = sorted(a.keys() & b.keys())
    mine, ref = [a[s] for s in seeds], [b[s] for s in seeds]
    diff = stats.mean_ci([x - FEWER * y for x, y in zip(mine, ref, strict=True)])
    return stats.ratio_ci(mine, ref), diff


def length_ratios(rows: list[dict], arm: str) -> tuple[stats.Interval, int]:
    """(the interval of per-seed true distance over expected's, minus 1; how many seeds were left
    out because expected's robot did not move)."""
    a, b = _by_seed(rows, arm, "length_m"), _by_seed(rows, "expected", "length_m")
    seeds = sorted(a.keys() & b.keys())
    from smana.deploy.report.measures import MOVED_M

    moved = [s for s in seeds if b[s] >= MOVED_M]
    return stats.mean_ci([a[s] / b[s] - 1 for s in moved]), len(seeds) - len(moved)


def paired(rows: list[dict], arm: str, key: str) -> stats.Interval:
    a, b = _by_seed(rows, arm, key), _by_seed(rows, "expected", key)
    return stats.mean_ci([a[s] - b[s] for s in sorted(a.keys() & b.keys())])


def verdicts(rows: list[dict]) -> list[dict]:
    """The module docstring's rules for `cvar` and `chance`, in that order: (claim, paper, smana,
    verdict, p, rule, evidence) rows as the other experiments give them (uncorrected: the
    caller corrects its table together)."""
    out = []

    def add(claim, target, smana, d: stats.Decision, rule, evidence="", scale=1.0, unit=""):
        out.append(
            {
                "claim": claim,
                "paper": target,
                "smana": smana,
                **d.fields(),
                "rule": rule,
                "scale": scale,
                "unit": unit,
                "evidence": "; ".join(e for e in (d.evidence, evidence) if e),
            }
        )

    for arm in TESTED:
        ratio, diff = entries_ratio(rows, arm)
        shown = (
            ratio.format(fmt=".2f")
            if np.isfinite(ratio.mean)
            else f"- (expected entered none, n = {ratio.n})"
        )
        add(
            f"{arm}: >= {100 * (1 - FEWER):.0f} % fewer forbidden-class entries than expected "
            "(p = 0.7 and pose noise, true path; ratio of sums, Fieller interval)",
            f"target: ratio < {FEWER:g}",
            shown,
            stats.decide_not_worse(
                diff, 0.0, yes=f"under {FEWER:g} x expected's", no=f"over {FEWER:g} x expected's"
            ),
            "below, paired",
            f"arm - {FEWER:g} x expected per seed: {diff.format(fmt='.2f')}",
        )
        longer, dropped = length_ratios(rows, arm)
        add(
            f"{arm}: paths at most {100 * LONGER_MARGIN:.0f} % longer than expected's (true "
            "distance driven, ratio per seed)",
            f"target: < +{100 * LONGER_MARGIN:.0f} %",
            longer.format(100, unit=" %"),
            stats.decide_not_worse(longer, LONGER_MARGIN),
            "not worse",
            f"{dropped} seed(s) left out: expected's robot did not move" if dropped else "",
            100,
            " %",
        )
        cov = paired(rows, arm, "coverage")
        add(
            f"{arm}: no loss of success against expected (ground-truth coverage, paired per seed)",
            f"target: > -{100 * COVERAGE_MARGIN:.0f} points",
            cov.format(100, unit=" points"),
            stats.decide_not_worse(cov, COVERAGE_MARGIN, higher_is_better=True),
            "not worse",
            scale=100,
            unit=" points",
        )
    return out


# -- summary --------------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "forbidden_entries",
    "forbidden_nodes",
    "forbidden_time_s",
    "true_cost",
    "length_m",
    "coverage",
)


def summarise(rows: list[dict]) -> list[dict]:
    """Per arm that ran, in _BY_NAME's order: runs, failed, did not move, contacts (a total), and
    the interval of each SUMMARY_KEYS value over its runs."""
    from smana.deploy.report.measures import MOVED_M

    out = []
    for c in _BY_NAME.values():
        sel = [r for r in rows if r.get("arm") == c.name]
        if not sel:
            continue
        ok = [r for r in sel if r.get("ok")]
        out.append(
            {
                "arm": c.name,
                "runs": len(sel),
                "failed": len(sel) - len(ok),
                "did_not_move": sum((r.get("length_m") or 0.0) < MOVED_M for r in ok),
                "collisions": sum(int(r.get("collisions") or 0) for r in ok),
                **{k: stats.mean_ci([ex.counted(r, k) for r in ok]) for k in SUMMARY_KEYS},
            }
        )
    return out


def arm_table(rows: list[dict]) -> list[str]:
    lines = [
        "| arm | perception | runs (failed) | forbidden entries | forbidden nodes | time in "
        "water (s) | true cost | path length (m) | coverage | did not move | contacts |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for d in summarise(rows):
        c = _BY_NAME[d["arm"]]
        how = "p = 0.7, pose noise" if c.noisy else "noise-free"
        lines.append(
            f"| {d['arm']} | {how} | {d['runs']} ({d['failed']}) | "
            f"{d['forbidden_entries'].format()} | {d['forbidden_nodes'].format()} | "
            f"{d['forbidden_time_s'].format()} | {d['true_cost'].format()} | "
            f"{d['length_m'].format()} | {d['coverage'].format(100, unit=' %')} | "
            f"{d['did_not_move']} | {d['collisions']} |"
        )
    return lines


def setting(meta: dict) -> str:
    """One line: the world and the runs the data comes from."""
    return (
        f"Wet garden {meta.get('size_m', '?')} m (water {100 * WATER_SHARE:.0f} % of the "
        f"ground), {BACKEND}, NBV at grass x{GRASS_COST_FACTOR:g}, "
        f"{meta.get('budget_s', 0):.0f} s of robot time per run; noisy arms: label noise p = 0.7 "
        f"(SLIC + Table 2 with water), pose noise {POSE_NOISE[POSE_LEVEL][0]} m, "
        f"{POSE_NOISE[POSE_LEVEL][1]} rad."
    )


def section(data: dict | None) -> str:
    """docs/experiments.md's generated `risk` section from the committed data (or a line saying
    there is none)."""
    if data is None:
        return (
            "_No raw results of `smana experiment risk` are committed yet "
            "(docs/experiments/data/risk.json): the closed-loop experiment has not been run in "
            "full, and nothing is reported here._\n"
        )
    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    meta = data.get("meta") or {}
    seeds = sorted({r["seed"] for r in rows})
    lines = []
    if meta.get("is_quick"):
        lines += ["**A quick run's data** (`--quick`): it tests the tooling, not the question.", ""]
    lines += [
        f"Generated from docs/experiments/data/risk.json (seeds {seeds}; mean [95 % CI] (n) over "
        "seeds; contacts added over the runs; the verdicts are in the table above). "
        + setting(meta),
        "",
        *arm_table(rows),
    ]
    return "\n".join(lines) + "\n"


# -- outputs --------------------------------------------------------------------------------------


def write_outputs(rows: list[dict], s: ex.ExplorationExperimentConfig, out: Path) -> None:
    """risk_results.{csv,json}, data/risk.json and risk_summary.md (verdicts on top, Holm over
    the six); the runner's `write` hook."""
    from .report import write_data

    out.mkdir(parents=True, exist_ok=True)
    rows[:] = with_truth(rows, out)
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    with open(out / "risk_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(flat[0]))
        w.writeheader()
        w.writerows(flat)
    write_data(out, "risk", rows, asdict(s) | {"form": "closed loop"})
    table = verdicts(rows)
    decided = stats.holm_table(
        [stats.Decision(v["verdict"], v["p"], v["p"], yes=v["p_tests"]) for v in table]
    )
    for v, d in zip(table, decided, strict=True):
        v["holm_verdict"], v["holm"] = d.verdict, d.evidence
    (out / "risk_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "verdicts": table}, indent=2)
    )
    lines = ["# Risk-aware navigation in closed loop", ""]
    failed = [r for r in rows if not r["ok"]]
    if failed:
        names = ", ".join(ex.run_name(r["seed"], _BY_NAME[r["arm"]].arm()) for r in failed)
        lines += [
            f"**WARNING: {len(failed)} of {len(rows)} runs failed** (no metrics or no true "
            "trajectory, or a non-zero exit for another reason than a navigation outcome), left "
            f"out of every number below: {names}.",
            "",
        ]
    if s.is_quick:
        lines += [
            f"**Quick run**: {len(s.seeds)} seed{'s' * (len(s.seeds) != 1)} of "
            f"{s.budget_s:.0f} s in a {s.size_m:g} m garden. It checks that the experiment "
            "works; its verdicts say nothing (the full run: `smana experiment risk`).",
            "",
        ]
    verdict_lines = [
        "| claim | target | smana | rule | verdict (Holm over these six) |",
        "|---|---|---|---|---|",
        *(
            f"| {v['claim']} | {v['paper']} | {v['smana']}"
            f"{'; ' + v['evidence'] if v['evidence'] else ''} | {v['rule']} | "
            f"{v['holm_verdict']} ({v['holm']}, one-sided: {v['p_tests']}) |"
            for v in table
        ),
    ]
    lines += [
        *verdict_lines,
        "",
        f"Seeds {list(s.seeds)}, {s.jobs} run(s) at once. " + setting(asdict(s)),
        "",
        *arm_table(rows),
        "",
        "| run | exit | forbidden entries | time in water (s) | length (m) | coverage | contacts "
        "| wall (s) | run warnings |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {ex.run_name(r['seed'], _BY_NAME[r['arm']].arm())} | {r['exit_code']} | "
            f"{'-' if r['forbidden_entries'] is None else r['forbidden_entries']} | "
            f"{exr.fmt_num(r['forbidden_time_s'])} | {exr.fmt_num(r['length_m'])} | "
            f"{exr.fmt_pct(r['coverage'])} | "
            f"{'-' if r['collisions'] is None else r['collisions']} | "
            f"{exr.fmt_num(r['wall_time_s'], '.0f')} | {r['run_warnings'] or '-'} |"
        )
    (out / "risk_summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(verdict_lines))


def arms_of(text: str) -> tuple[ex.Arm, ...]:
    """The arms `--arms` names (comma-separated, any of _BY_NAME); a bad name: one line."""
    from smana.common.cli import UsageError

    names = [v.strip() for v in text.split(",") if v.strip()]
    if not names or any(v not in _BY_NAME for v in names):
        raise UsageError(f"--arms: expected some of {', '.join(_BY_NAME)}, got {text!r}")
    return tuple(_BY_NAME[v].arm() for v in names)


def run(args, out: Path) -> int:
    """The closed loop as `smana experiment risk` runs it (risk.py parses the arguments)."""
    s = experiment_config(args.quick)
    if args.seeds:
        s.seeds = tuple(range(3, 3 + args.seeds))
    if args.budget:
        s.budget_s = args.budget
    if args.size:
        s.size_m = args.size
    if args.jobs:
        s.jobs = args.jobs
    if args.arms is not None:
        s.arms = arms_of(args.arms)
    s.extra = (*s.extra, *args.extra)
    rows = ex.run_exploration(s, out, write=write_outputs, keep=finished)
    return ex.finish(rows, out, "risk")
