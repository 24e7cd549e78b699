"""`smana experiment navnoise` (beyond the paper): does semantic-aware navigation survive
perception noise?

The paper measures its noise on the map (section 4.2: reconstruction error, classification
ratio) and its navigation on noise-free perception (4.3: the terrain share). No anchor measures
the link between the two: whether a robot that avoids grass by its map still avoids grass once
the map is wrong. This experiment closes the loop: the whole stack (`smana up`, run by the
exploration experiment's runner: same worlds, starts, budget and failure accounting) explores
the cluttered 12 m garden with NBV and grass at x4, in four arms, on the same seeds:

    {octree-max, tsdf} (`mapper.backend`) x {noise-free, noisy}

- noise-free: the exploration experiment's perception, `sim.noise = "none"` (SLIC superpixels
  with their majority label, no redraw: p = 1.0) and no pose noise;
- noisy: `sim.noise = "high"` (SLIC, then Table 2's confusion redraw with p = 0.7, the paper's
  4.2.1 high level) and the noise experiment's highest pose noise on every published pose
  (`noise.POSE_NOISE["high"]`: 0.10 m on x and y, 0.02 rad on yaw, white per pose, no drift).

Measured against the world's ground truth, never the map (lab/report.py, per run):
- the true terrain share of the path: the travelled graph nodes of the robot's TRUE trajectory
  (the recorder's `trajectory_truth.csv`), their class read from the world, terrain over terrain
  plus grass. A run whose report fell back to the published (noisy) pose has no true share;
- beside it the map's terrain share of the same nodes (the explorer's final graph labels): what
  the robot believed it drove on;
- contacts (footprint on an obstacle cell, a lasting contact counts once) and close calls, the
  coverage of the reachable traversable area (ground truth at the end), the true distance, the
  robot time to 95 % coverage (time, not distance: the explorer's odometer adds up the pose
  noise).

Rules, fixed before the runs (lab/stats.py; paired per seed, the same seeds in every arm):
1. per back-end, "noise does not lower the true terrain share by more than 5 points":
   non-inferiority (`decide_not_worse`, margin 0.05) of noisy minus noise-free;
2. per back-end, "noise does not lower the coverage by more than 5 points": the same rule;
3. "under noise, TSDF keeps the robot on terrain better than octree-max" (the paper's claim (c),
   TSDF more robust to pose noise, carried over to navigation): the paired difference tsdf minus
   octree-max of the noisy arms' true terrain share lies above 0 (`decide_above`).
Verdicts are "reproduced" (met), "not reproduced", "inconclusive"; docs/experiments.md corrects
them with every other claim (Holm). Contacts are counts, reported per arm, not tested.

A run that `smana up` ends FAILED on what its robot did alone (exploration.py `outcome_failure`:
the robot did not move, no path was ever found, under half the reachable area usable, closed in
by its own map) is what the noise did, not a failed run: it is counted per arm ("FAILED", "did
not move") and in every rule. A robot that stood still scores 0 on the true terrain share and
the coverage (exploration.py `counted`): a failure in the pair, never a seed left out. Two more
arms per back-end, `<backend>_label` and `<backend>_pose` (one noise at a time), are on `--arms`
to tell which noise did what; no verdict uses them.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path

from smana.lab import paper_figures, stats

from . import exploration as ex
from . import exploration_report as exr
from .noise import POSE_NOISE

GRASS_COST_FACTOR = 4.0
LABEL_NOISE = "high"  # services/sim/degrade.py NOISE_LEVELS: p = 0.7
POSE_LEVEL = "high"  # noise.POSE_NOISE: (0.10 m, 0.02 rad)
CLEAN_LABEL_NOISE = "none"  # the exploration experiment's: SLIC majority, p = 1.0
BACKENDS = ("octree-max", "tsdf")
TERRAIN_MARGIN = 0.05  # rule 1: noise may lower the true terrain share by at most 5 points
COVERAGE_MARGIN = 0.05  # rule 2: and the coverage by at most 5 points
TRUE_SOURCE = "ground truth"  # lab/report.py _trajectory: the recorder's true poses


# perception -> (label noise p = 0.7, pose noise); the two single-noise arms are not in the
# default run (no verdict uses them): `--arms` adds them to tell which noise did what
PERCEPTIONS = {
    "clean": (False, False),
    "noisy": (True, True),
    "label": (True, False),
    "pose": (False, True),
}
PERCEPTION_LABEL = {
    "clean": "noise-free",
    "noisy": "noisy",
    "label": "label noise only",
    "pose": "pose noise only",
}


@dataclass(frozen=True)
class Condition:
    """One arm's back-end and perception (a PERCEPTIONS key)."""

    backend: str
    perception: str

    @property
    def name(self) -> str:
        return f"{self.backend.replace('-', '_')}_{self.perception}"

    @property
    def label_noise(self) -> str:
        return LABEL_NOISE if PERCEPTIONS[self.perception][0] else CLEAN_LABEL_NOISE

    @property
    def pose_noise(self) -> tuple[float, float]:
        return POSE_NOISE[POSE_LEVEL] if PERCEPTIONS[self.perception][1] else (0.0, 0.0)

    def sets(self) -> tuple[str, ...]:
        xy, yaw = self.pose_noise
        level = self.label_noise
        return (
            f'mapper.backend="{self.backend}"',
            f'sim.noise="{level}"',
            f"sim.pose_noise_xy_m={xy}",
            f"sim.pose_noise_yaw_rad={yaw}",
        )

    def arm(self) -> ex.Arm:
        return ex.Arm(self.name, GRASS_COST_FACTOR, sets=self.sets())


CONDITIONS = tuple(Condition(b, p) for b in BACKENDS for p in ("clean", "noisy"))
EXTRA_CONDITIONS = tuple(Condition(b, p) for b in BACKENDS for p in ("label", "pose"))
ARMS = tuple(c.arm() for c in CONDITIONS)  # the default run's
_BY_NAME = {c.name: c for c in (*CONDITIONS, *EXTRA_CONDITIONS)}


def experiment_config(quick: bool = False) -> ex.ExplorationExperimentConfig:
    """The exploration experiment's settings (full: 5 seeds, 12 m garden, 150 s; quick: the
    6 m garden, 20 s) with the four arms."""
    s = ex.ExplorationExperimentConfig.quick() if quick else ex.ExplorationExperimentConfig()
    s.arms = ARMS
    return s


# -- rows ----------------------------------------------------------------------------------------


def ground_truth_fields(m: dict) -> dict:
    """What a run's metrics.json says against ground truth, beyond the exploration row: the true
    terrain share (only when the report measured the recorder's true trajectory and the robot
    moved: a robot that stood still has no path to score), the map's share of the same nodes,
    contacts and close calls, and whether the robot moved."""
    from smana.deploy.report.measures import MOVED_M

    e = m.get("exploration") or {}
    source = e.get("trajectory_source")
    dist = e.get("distance_m")
    moved = None if dist is None else dist >= MOVED_M  # None: no trajectory measured at all
    true = source == TRUE_SOURCE and bool(moved)
    return {
        "moved": moved,
        "trajectory_source": source,
        "terrain_share_true": e.get("terrain_share") if true else None,
        "terrain_share_map": e.get("terrain_share_map") if true else None,
        "collisions": e.get("collisions"),
        "close_calls": e.get("close_calls"),
        "collision_time_s": e.get("collision_time_s"),
    }


def with_conditions(rows: list[dict], out: Path) -> list[dict]:
    """The exploration rows with each arm's back-end and noise, and the ground-truth fields of
    its run's metrics.json (the run directory the runner made)."""
    full = []
    for r in rows:
        c = _BY_NAME[r["arm"]]
        run_dir = out / ex.run_name(r["seed"], c.arm())
        m = ex.load_json(run_dir / "metrics.json")
        warnings = m.get("warnings") or []
        # a run that FAILED on what its robot did alone is a measurement (module docstring)
        outcome = bool(m) and ex.outcome_failure(r["exit_code"], m)
        full.append(
            {
                **r,
                "ok": bool(r["ok"] or outcome),
                "run_failed": outcome,
                "run_warnings": "; ".join(warnings),
                "backend": c.backend,
                "perception": c.perception,
                "label_noise": c.label_noise,
                "pose_noise_xy_m": c.pose_noise[0],
                "pose_noise_yaw_rad": c.pose_noise[1],
                **ground_truth_fields(m),
            }
        )
    return full


# -- verdicts -------------------------------------------------------------------------------------


def _values(rows: list[dict], backend: str, perception: str, key: str) -> dict[int, float]:
    return {
        r["seed"]: float(ex.counted(r, key))
        for r in rows
        if r.get("backend") == backend
        and r.get("perception") == perception
        and r.get("ok")
        and ex.counted(r, key) is not None
    }


def paired(rows: list[dict], key: str, a: tuple[str, str], b: tuple[str, str]):
    """Interval of b - a over the seeds where both arms, each (backend, perception), have a
    value (module docstring)."""
    va, vb = _values(rows, *a, key), _values(rows, *b, key)
    return stats.mean_ci([vb[s] - va[s] for s in sorted(va.keys() & vb.keys())])


def verdicts(rows: list[dict]) -> list[dict]:
    """The module docstring's three rules, in its order: (claim, paper, smana, verdict, p, rule,
    evidence) rows as the other experiments give them."""
    out = []

    def add(claim, target, ci: stats.Interval, d: stats.Decision, rule, evidence=""):
        out.append(
            {
                "claim": claim,
                "paper": target,
                "smana": ci.format(100, unit=" points"),
                **d.fields(),
                "rule": rule,
                "scale": 100,
                "unit": " points",
                "evidence": "; ".join(e for e in (d.evidence, evidence) if e),
            }
        )

    def stood_still(b: str) -> str:
        runs = [r for r in rows if (r.get("backend"), r.get("perception")) == (b, "noisy")]
        runs = [r for r in runs if r.get("ok")]
        k = sum(ex.stood_still(r) for r in runs)
        if not k:
            return ""
        return (
            f"{b}: the robot did not move in {k} of {len(runs)} noisy runs, each counted as a "
            "failure (0)"
        )

    for b in BACKENDS:
        ci = paired(rows, "terrain_share_true", (b, "clean"), (b, "noisy"))
        add(
            f"{b}, grass x{GRASS_COST_FACTOR:g}: label noise p = 0.7 and pose noise do not "
            f"lower the true terrain share of the path by more than {100 * TERRAIN_MARGIN:.0f} "
            "points (noisy minus noise-free, paired per seed)",
            f"(beyond the paper) > -{100 * TERRAIN_MARGIN:.0f} points",
            ci,
            stats.decide_not_worse(ci, TERRAIN_MARGIN, higher_is_better=True),
            "not worse",
            stood_still(b),
        )
    for b in BACKENDS:
        ci = paired(rows, "coverage", (b, "clean"), (b, "noisy"))
        add(
            f"{b}, grass x{GRASS_COST_FACTOR:g}: the noise does not lower the ground-truth "
            f"coverage by more than {100 * COVERAGE_MARGIN:.0f} points (paired per seed)",
            f"(beyond the paper) > -{100 * COVERAGE_MARGIN:.0f} points",
            ci,
            stats.decide_not_worse(ci, COVERAGE_MARGIN, higher_is_better=True),
            "not worse",
            stood_still(b),
        )
    ci = paired(rows, "terrain_share_true", ("octree-max", "noisy"), ("tsdf", "noisy"))
    add(
        "under the noise, TSDF keeps the robot on terrain better than octree-max (claim (c) "
        "carried to navigation): tsdf minus octree-max, true terrain share, paired per seed",
        "(beyond the paper) > 0",
        ci,
        stats.decide_above(ci),
        "above 0",
        "; ".join(e for e in (stood_still(b) for b in BACKENDS) if e),
    )
    return out


# -- summary -------------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "terrain_share_true",
    "terrain_share_map",
    "coverage",
    "distance_m",
    "time_to_95_s",
    "min_clearance_m",
)


def _run_failed(r: dict) -> bool:
    """A measured run that `smana up` ended FAILED (exit 1): on what its robot did alone, or it
    would not be measured (data written before `run_failed` was recorded say so by the exit)."""
    return bool(r.get("run_failed", r.get("exit_code") == 1))


def summarise(rows: list[dict]) -> list[dict]:
    """Per arm that ran, in _BY_NAME's order: runs, failed (not measured), FAILED (measured, the
    run's outcome a failure), did not move, totals of contacts and close calls, and the interval
    of each SUMMARY_KEYS value over its measured runs, a robot that stood still at 0
    (`ex.counted`)."""
    out = []
    for c in _BY_NAME.values():
        sel = [r for r in rows if r.get("arm") == c.name]
        if not sel:
            continue
        ok = [r for r in sel if r.get("ok")]
        out.append(
            {
                "arm": c.name,
                "backend": c.backend,
                "perception": c.perception,
                "runs": len(sel),
                "failed": len(sel) - len(ok),
                "no_true_trajectory": sum(r.get("terrain_share_true") is None for r in ok),
                "reached_95": sum(r.get("time_to_95_s") is not None for r in ok),
                "run_failed": sum(_run_failed(r) for r in ok),
                "did_not_move": sum(ex.stood_still(r) for r in ok),
                "collisions": sum(int(r.get("collisions") or 0) for r in ok),
                "close_calls": sum(int(r.get("close_calls") or 0) for r in ok),
                **{k: stats.mean_ci([ex.counted(r, k) for r in ok]) for k in SUMMARY_KEYS},
            }
        )
    return out


def arm_table(rows: list[dict]) -> list[str]:
    """The markdown table of `summarise` (the run's summary and the doc's generated section)."""
    lines = [
        "| arm | runs (failed) | true terrain share | map's terrain share of the same path | "
        "coverage | distance (m) | time to 95 % (s) | FAILED | did not move | contacts | "
        "close calls |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for d in summarise(rows):
        label = f"{d['backend']}, {PERCEPTION_LABEL[d['perception']]}"
        lines.append(
            f"| {label} | {d['runs']} ({d['failed']}) | "
            f"{d['terrain_share_true'].format(100, unit=' %')} | "
            f"{d['terrain_share_map'].format(100, unit=' %')} | "
            f"{d['coverage'].format(100, unit=' %')} | {d['distance_m'].format()} | "
            f"{d['time_to_95_s'].format(fmt='.0f')} ({d['reached_95']} reached) | "
            f"{d['run_failed']} | {d['did_not_move']} | {d['collisions']} | {d['close_calls']} |"
        )
    return lines


def section(data: dict | None) -> str:
    """docs/experiments.md's generated `navnoise` section from the committed data (or a line
    saying there is none)."""
    if data is None:
        return (
            "_No raw results of `smana experiment navnoise` are committed yet "
            "(docs/experiments/data/navnoise.json): the full experiment has not been run, and "
            "nothing is reported here._\n"
        )
    rows = data["rows"]
    seeds = sorted({r["seed"] for r in rows})
    lines = []
    if (data.get("meta") or {}).get("is_quick"):
        lines += ["**A quick run's data** (`--quick`): it tests the tooling, not the question.", ""]
    lines += [
        f"Generated from docs/experiments/data/navnoise.json (seeds {seeds}; mean [95 % CI] (n) "
        "over seeds; contacts and close calls added over the runs; the verdicts are in the "
        "table above):",
        "",
        *arm_table(rows),
    ]
    return "\n".join(lines) + "\n"


# -- outputs -------------------------------------------------------------------------------------


def _figure(rows: list[dict], out: Path) -> Path | None:
    summary = summarise(rows)
    # x positions: the perceptions that ran, noise-free first, both noises last
    order = [
        p for p in ("clean", "label", "pose", "noisy") if p in {d["perception"] for d in summary}
    ]
    series = []
    for b in BACKENDS:
        arms = [d for d in summary if d["backend"] == b]
        if not arms:
            continue
        xs = [float(order.index(d["perception"])) for d in arms]
        cis = [d["terrain_share_true"] for d in arms]
        ys = [None if c.n == 0 else c.mean for c in cis]
        err = [c.share_error_bars() for c in cis]
        series.append(
            paper_figures.Series(
                f"{b} (n = {'-'.join(sorted({str(c.n) for c in cis}))})",
                xs,
                ys,
                ([e[0] for e in err], [e[1] for e in err]),
            )
        )
    if not series:
        return None
    return paper_figures.save(
        paper_figures.line_plot(
            series,
            f"True terrain share of the path, NBV at grass x{GRASS_COST_FACTOR:g}",
            "perception",
            "terrain share of travelled nodes (ground truth)",
            {float(k): PERCEPTION_LABEL[p] for k, p in enumerate(order)},
            ylim=(0.0, 1.02),
            note="mean, 95 % CI clipped to [0, 1]",
        ),
        out / "navnoise_terrain_share.png",
    )


def write_outputs(rows: list[dict], s: ex.ExplorationExperimentConfig, out: Path) -> None:
    """navnoise_results.{csv,json}, data/navnoise.json, the figure and navnoise_summary.md
    (verdicts on top); the runner's `write` hook."""
    from .report import write_data

    out.mkdir(parents=True, exist_ok=True)
    rows[:] = with_conditions(rows, out)
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    with open(out / "navnoise_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(flat[0]))
        w.writeheader()
        w.writerows(flat)
    write_data(out, "navnoise", rows, asdict(s))
    table = verdicts(rows)
    (out / "navnoise_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "verdicts": table}, indent=2)
    )
    figure = _figure(rows, out)
    lines = ["# Navigation under perception noise (beyond the paper)", ""]
    failed = [r for r in rows if not r["ok"]]
    if failed:
        names = ", ".join(f"{ex.run_name(r['seed'], _BY_NAME[r['arm']].arm())}" for r in failed)
        lines += [
            f"**WARNING: {len(failed)} of {len(rows)} runs failed** (no metrics, or a non-zero "
            "exit for another reason than a navigation outcome), left out of every number "
            f"below: {names}.",
            "",
        ]
    untrue = [r for r in rows if r["ok"] and r["trajectory_source"] != TRUE_SOURCE]
    if untrue:
        lines += [
            f"**WARNING: {len(untrue)} run(s) have no true trajectory** (the report measured "
            f"{', '.join(sorted({str(r['trajectory_source']) for r in untrue}))}): no true "
            "terrain share for them.",
            "",
        ]
    if s.is_quick:
        lines += [
            f"**Quick run**: {len(s.seeds)} seed{'s' * (len(s.seeds) != 1)} of "
            f"{s.budget_s:.0f} s in a {s.size_m:g} m garden. It checks that the experiment "
            "works; its verdicts say nothing (the full run: `smana experiment navnoise`, "
            "docs/experiments.md).",
            "",
        ]
    lines += [
        "| claim | target | smana, mean [95 % CI] (n) | rule | verdict |",
        "|---|---|---|---|---|",
        *(
            f"| {v['claim']} | {v['paper']} | {v['smana']} | {v['rule']} | {v['verdict']} |"
            for v in table
        ),
        "",
        f"Seeds {list(s.seeds)}, garden {s.size_m:g} m, budget {s.budget_s:.0f} s per run, "
        f"{s.jobs} run(s) at once, NBV at grass x{GRASS_COST_FACTOR:g}. Noisy: label noise "
        f'"{LABEL_NOISE}" (p = 0.7), pose noise {POSE_NOISE[POSE_LEVEL][0]} m, '
        f'{POSE_NOISE[POSE_LEVEL][1]} rad. Noise-free: label noise "{CLEAN_LABEL_NOISE}".',
        "",
        *arm_table(rows),
        "",
        "| run | exit | trajectory | true terrain share | map's terrain share | coverage | "
        "distance (m) | contacts | wall (s) | run warnings |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {ex.run_name(r['seed'], _BY_NAME[r['arm']].arm())} | {r['exit_code']} | "
            f"{r['trajectory_source'] or '-'} | {exr.fmt_pct(r['terrain_share_true'])} | "
            f"{exr.fmt_pct(r['terrain_share_map'])} | {exr.fmt_pct(r['coverage'])} | "
            f"{exr.fmt_num(r['distance_m'])} | "
            f"{'-' if r['collisions'] is None else r['collisions']}"
            f" | {exr.fmt_num(r['wall_time_s'], '.0f')} | {r['run_warnings'] or '-'} |"
        )
    if figure is not None:
        lines += ["", f"![{figure.stem}]({figure.name})"]
    (out / "navnoise_summary.md").write_text("\n".join(lines) + "\n")


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `navnoise` subcommand of `smana experiment`."""
    e = sub.add_parser(
        "navnoise",
        help="beyond the paper: NBV at grass x4 under label and pose noise, octree-max vs tsdf "
        "(5 seeds measured once, one run at a time: 51 min)",
        description="Closed-loop exploration (one `smana up` per arm and seed) with octree-max "
        "and tsdf, noise-free and with label noise p = 0.7 plus pose noise (0.10 m, 0.02 rad): "
        "the true terrain share of the driven path, contacts, coverage; verdicts paired per "
        "seed (docs/experiments.md, 'Beyond the paper').",
        epilog="Duration measured once on a 2-core machine shared with other work (load 12 to "
        "46): one seed of the four arms, one run at a time (--seeds 1 --jobs 1), 11 min 52 s "
        "(three runs 3.3 to 3.6 min each; octree-max under noise 1.3 min: its robot never "
        "moved); the 5 seeds x 4 arms = 20 runs, one at a time (--jobs 1), 51 min (2 at once, "
        "the default --jobs, not measured). --quick: 4 arms x 2 "
        "seeds of 20 s in a 6 m garden; one seed of it (--seeds 1) measured once: 2 to 3.7 "
        "min. Exits 1 if any run failed to run (a run that `smana up` ended FAILED only on "
        "what its robot did, such as not moving or finding no path, is a result, counted as a "
        "failure: a robot that stood still scores 0).",
    )
    ex.add_common_args(
        e, quick_help="4 arms x 2 seeds of 20 s in a 6 m garden (one seed measured once: 2-4 min)"
    )
    e.add_argument(
        "--arms",
        help="comma-separated arms (default: "
        + ",".join(a.name for a in ARMS)
        + "; also "
        + ",".join(c.name for c in EXTRA_CONDITIONS)
        + ": one noise at a time, in no verdict)",
    )


def _arms(args) -> tuple[ex.Arm, ...] | None:
    """The arms `--arms` names (any of _BY_NAME), None without it; a bad name: one line."""
    from smana.common.cli import UsageError

    if getattr(args, "arms", None) is None:  # `--arms ""` is refused below, not all arms
        return None
    names = [v.strip() for v in args.arms.split(",") if v.strip()]
    if not names or any(v not in _BY_NAME for v in names):
        raise UsageError(f"--arms: expected some of {', '.join(_BY_NAME)}, got {args.arms!r}")
    return tuple(_BY_NAME[v].arm() for v in names)


def check_args(args, parser=None) -> None:
    """Refuse a bad --set or --arms now, not in every run (one line)."""
    from smana.common.config import SmanaConfig

    SmanaConfig.load(overrides=[*ex.WORLD_SETS, *ARMS[-1].sets, *args.extra])
    _arms(args)


def main(args, parser, out: Path) -> int:
    arms = _arms(args)
    args.arms = None  # chosen here: exploration's apply_args knows only its own arms
    s = ex.apply_args(experiment_config(args.quick), args)
    if arms:
        s.arms = arms
    rows = ex.run_exploration(s, out, write=write_outputs)
    return ex.finish(rows, out, "navnoise")
