"""The rules and the outputs of `smana experiment robustness` (robustness.py holds the arms, the
runs and the command line): the three rules' verdicts, counted over seeds; the summary per arm;
the tables, the figure and the section docs/experiments.md shows; the files a run writes.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

from smana.lab import paper_figures, stats

from . import exploration as ex
from . import exploration_report as exr
from . import rules
from .robustness import (
    CLEAN,
    FALSE_FREE_MAX,
    GRASS_COST_FACTOR,
    LEVELS,
    OF_SEEDS,
    PASS_SEEDS,
    POSE_DRIFT,
    POSE_NOISE,
    TARGETS,
    conditions,
    default_backend,
    finished,
)

# -- the rules -----------------------------------------------------------------------------------


def _runs(rows: list[dict], backend: str, perception: str) -> dict[int, dict]:
    return {
        r["seed"]: r
        for r in rows
        if r.get("backend") == backend and r.get("perception") == perception
    }


def seed_passes(run: dict | None, ref: dict | None, target: float) -> bool:
    """Rules 1 and 2 for one seed: the run was measured, did not FAIL, moved, had 0 collisions
    and a usable coverage at least `target` x the reference run's (measured, above 0)."""
    if not run or not ref or not run.get("measured") or not ref.get("measured"):
        return False
    if run.get("run_failed") or run.get("moved") is False or run.get("collisions") != 0:
        return False
    mine, base = run.get("usable_share"), ref.get("usable_share")
    if mine is None or not base:
        return False
    return mine >= target * base


def ratio(run: dict | None, ref: dict | None) -> float | None:
    """A run's usable coverage over its seed's noise-free reference's (None when either lacks
    one)."""
    if not run or not ref:
        return None
    mine, base = run.get("usable_share"), ref.get("usable_share")
    return None if mine is None or not base else mine / base


def _count_verdict(passed: int, failed: int, need: int, of: int) -> str:
    from .fleet import MET, NOT_MET

    if passed >= need:
        return MET
    if failed > of - need:
        return NOT_MET
    return stats.INCONCLUSIVE


def verdicts(rows: list[dict]) -> list[dict]:
    """The module docstring's three rules: (claim, paper, smana, verdict, p = None, rule,
    evidence) rows, counts not tests (they stay out of the Holm correction)."""
    from .fleet import MET, NOT_MET

    b = default_backend()
    ref = _runs(rows, b, CLEAN)
    out = []
    for level, target in TARGETS.items():
        runs = _runs(rows, b, level)
        seeds = sorted(runs)
        ok = [s for s in seeds if seed_passes(runs[s], ref.get(s), target)]
        bad = [s for s in seeds if s not in ok]
        out.append(
            {
                "claim": f"{b} at {level} label noise with pose noise (0.10 m, 0.02 rad, drift):"
                f" at least {100 * target:.0f} % of its own noise-free usable coverage, 0 "
                f"collisions, moved and not FAILED, in at least {PASS_SEEDS} of {OF_SEEDS} seeds",
                "paper": f"(beyond the paper) >= {PASS_SEEDS} of {OF_SEEDS}",
                "smana": f"{len(ok)} of {len(seeds)} seeds"
                + (f" (short: seeds {', '.join(map(str, bad))})" if bad else ""),
                "verdict": _count_verdict(len(ok), len(bad), PASS_SEEDS, OF_SEEDS),
                "p": None,
                "rule": "a count",
                "evidence": "",
            }
        )
    measured = [r for r in rows if r.get("measured")]
    known = [r for r in measured if r.get("false_free_share") is not None]
    over = [r for r in known if not r["false_free_share"] < FALSE_FREE_MAX]
    unknown = len(measured) - len(known)
    worst = max((r["false_free_share"] for r in known), default=None)
    out.append(
        {
            "claim": f"false-free area under {100 * FALSE_FREE_MAX:.0f} % of the reachable area "
            "in every run (every arm)",
            "paper": "(beyond the paper) every run",
            "smana": f"{len(known) - len(over)} of {len(measured)} runs"
            + ("" if worst is None else f" (largest {100 * worst:.2f} %)")
            + (f"; {unknown} without the measure" if unknown else ""),
            # a run without the measure cannot show it was under
            "verdict": NOT_MET if over else (MET if known and not unknown else stats.INCONCLUSIVE),
            "p": None,
            "rule": "a count",
            "evidence": "",
        }
    )
    return out


# -- summary -------------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "usable_share",
    "false_obstacle_share",
    "false_free_share",
    "distance_m",
    "time_to_90_s",
    "distance_to_90_m",
)
PERCEPTION_LABEL = {
    CLEAN: "no noise",
    "off": "true labels + pose noise",
    "medium": "medium labels + pose noise",
    "high": "high labels + pose noise",
    "realistic": "realistic labels + pose noise",
}


def summarise(rows: list[dict]) -> list[dict]:
    """Per arm that ran, in `conditions()` order: runs, not measured, FAILED, did not move, ended
    closed_in, collisions (total), the interval of each SUMMARY_KEYS value over its measured runs
    (a robot that did not move with its measured values) and of the usable coverage over the
    seed's noise-free reference."""
    b = default_backend()
    ref = _runs(rows, b, CLEAN)
    out = []
    for c in conditions():
        sel = [r for r in rows if r.get("arm") == c.name]
        if not sel:
            continue
        ok = [r for r in sel if r.get("measured")]
        target = TARGETS.get(c.perception) if c.backend == b else None
        out.append(
            {
                "arm": c.name,
                "backend": c.backend,
                "perception": c.perception,
                "runs": len(sel),
                "not_measured": len(sel) - len(ok),
                "run_failed": sum(bool(r.get("run_failed")) for r in ok),
                "did_not_move": sum(r.get("moved") is False for r in ok),
                "closed_in": sum(r.get("done_reason") == "closed_in" for r in ok),
                "collisions": sum(int(r.get("collisions") or 0) for r in ok),
                "passed": None
                if target is None
                else sum(seed_passes(r, ref.get(r["seed"]), target) for r in ok),
                **{k: stats.mean_ci([r.get(k) for r in ok]) for k in SUMMARY_KEYS},
                "of_clean": stats.mean_ci([ratio(r, ref.get(r["seed"])) for r in ok]),
            }
        )
    return out


def arm_table(rows: list[dict]) -> list[str]:
    """The markdown table of `summarise` (the run's summary and the doc's generated section)."""
    lines = [
        "| back-end | perception | runs (not measured) | usable coverage | of noise-free, "
        "same seed | false obstacle | false free | distance (m) | time to 90 % (s) | "
        "FAILED | did not move | closed in | collisions | target met |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for d in summarise(rows):
        target = "-" if d["passed"] is None else f"{d['passed']} of {d['runs']}"
        lines.append(
            f"| {d['backend']} | {PERCEPTION_LABEL[d['perception']]} | {d['runs']} "
            f"({d['not_measured']}) | {d['usable_share'].format(100, unit=' %')} | "
            f"{d['of_clean'].format(100, unit=' %')} | "
            f"{d['false_obstacle_share'].format(100, unit=' %')} | "
            f"{d['false_free_share'].format(100, '.2f', ' %')} | {d['distance_m'].format()} | "
            f"{d['time_to_90_s'].format(fmt='.0f')} | {d['run_failed']} | "
            f"{d['did_not_move']} | {d['closed_in']} | {d['collisions']} | {target} |"
        )
    return lines


def setting(meta: dict) -> str:
    """One sentence: the garden, seeds, budget and noise the data was made with."""
    seeds = list(meta.get("seeds") or [])
    span = f"seeds {seeds[0]} to {seeds[-1]}" if len(seeds) > 1 else f"seed {seeds}"
    return (
        f"garden {float(meta.get('size_m', 0)):g} m, {span}, {float(meta.get('budget_s', 0)):.0f}"
        f" s of robot time per run, {meta.get('jobs', '?')} run(s) at once; pose noise "
        f"{POSE_NOISE[0]} m and {POSE_NOISE[1]} rad white plus drift {POSE_DRIFT[0]} m/sqrt(s) "
        f"and {POSE_DRIFT[1]} rad/sqrt(s)"
    )


def section(data: dict | None, key: str = "robustness") -> str:
    """docs/experiments.md's generated section `key` from the committed data file `<key>.json`
    (`robustness`, or a variant such as a confirmation on other seeds), or a line saying there
    is none."""
    if data is None:
        return (
            "_No raw results of `smana experiment robustness` are committed yet "
            f"(docs/experiments/data/{key}.json): nothing is reported here until they are._\n"
        )
    rows = data["rows"]
    lines = []
    if (data.get("meta") or {}).get("is_quick"):
        lines += ["**A quick run's data** (`--quick`): it tests the tooling, not the question.", ""]
    lines += [
        f"Generated from docs/experiments/data/{key}.json ("
        + setting(data.get("meta") or {})
        + "; mean [95 % CI] (n) over the measured runs, a robot that did not move with its "
        "measured values; shares of the reachable area; collisions added over the runs; the "
        "rules' verdicts are in the table above):",
        "",
        *arm_table(rows),
        "",
        rules.line(data),
    ]
    return "\n".join(lines) + "\n"


# -- outputs -------------------------------------------------------------------------------------


def figure(rows: list[dict], path: Path) -> Path | None:
    """Usable coverage against perception noise, one line per back-end (mean and 95 % CI over
    seeds), the noise-free reference and the targets of rules 1 and 2."""
    summary = summarise(rows)
    order = [CLEAN, *LEVELS]
    ticks = {float(k): PERCEPTION_LABEL[p].replace(" + ", "\n+ ") for k, p in enumerate(order)}
    series = []
    for backend in dict.fromkeys(d["backend"] for d in summary):
        arms = [d for d in summary if d["backend"] == backend]
        cis = [d["usable_share"] for d in arms]
        if not any(c.n for c in cis):
            continue  # no run of this back-end has the measure: no line to draw
        err = [c.share_error_bars() for c in cis]
        ns = "-".join(sorted({str(c.n) for c in cis}))
        series.append(
            paper_figures.Series(
                f"{backend} (n = {ns} seed{'s' * (ns != '1')})",
                [float(order.index(d["perception"])) for d in arms],
                [None if c.n == 0 else c.mean for c in cis],
                ([e[0] for e in err], [e[1] for e in err]),
            )
        )
    base = next((d for d in summary if d["perception"] == CLEAN), None)
    if base is not None and base["usable_share"].n:
        m = base["usable_share"].mean
        levels = [lv for lv in TARGETS if any(d["perception"] == lv for d in summary)]
        if levels:
            series.append(
                paper_figures.Series(
                    "target: 90 % (high), 80 % (realistic) of noise-free",
                    [float(order.index(lv)) for lv in levels],
                    [TARGETS[lv] * m for lv in levels],
                    dashed=True,
                )
            )
    if not series:
        return None
    return paper_figures.save(
        paper_figures.line_plot(
            series,
            "Usable coverage under perception noise",
            "perception",
            "usable share of the reachable area (ground truth)",
            ticks,
            ylim=(0.0, 1.02),
            note="mean, 95 % CI clipped to [0, 1]",
        ),
        path,
    )


def _pct2(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} %"


def write_outputs(rows: list[dict], s: ex.ExplorationExperimentConfig, out: Path) -> None:
    """robustness_results.{csv,json}, data/robustness.json, the figure and
    robustness_summary.md (verdicts on top); the runner's `write` hook."""
    from .report import write_data

    out.mkdir(parents=True, exist_ok=True)
    for r in rows:
        if "measured" not in r:  # a row the runner did not keep (not measured)
            finished(r, out / ex.run_name(r["seed"], ex.Arm(r["arm"], GRASS_COST_FACTOR)))
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    keys = list(dict.fromkeys(k for r in flat for k in r))
    with open(out / "robustness_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(flat)
    write_data(out, "robustness", rows, asdict(s), "quick" if s.is_quick else None)
    table = verdicts(rows)
    (out / "robustness_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "verdicts": table}, indent=2)
    )
    fig = figure(rows, out / "robustness_usable_coverage.png")
    lines = ["# Robustness: exploring under realistic perception noise", ""]
    lost = [r for r in rows if not r.get("measured")]
    if lost:
        names = ", ".join(f"seed{r['seed']}_{r['arm']} (exit {r['exit_code']})" for r in lost)
        lines += [
            f"**WARNING: {len(lost)} of {len(rows)} runs did not run to their report** (no "
            f"metrics: a crash or a timeout), left out of every number below: {names}.",
            "",
        ]
    if s.is_quick:
        lines += [
            f"**Quick run**: {len(s.seeds)} seed{'s' * (len(s.seeds) != 1)} of "
            f"{s.budget_s:.0f} s in a {s.size_m:g} m garden. It checks that the experiment "
            "works; its verdicts say nothing (the full run: `smana experiment robustness`, "
            "docs/experiments.md).",
            "",
        ]
    lines += [
        "| rule | target | smana | verdict |",
        "|---|---|---|---|",
        *(f"| {v['claim']} | {v['paper']} | {v['smana']} | {v['verdict']} |" for v in table),
        "",
        setting(asdict(s)) + ".",
        "",
        *arm_table(rows),
        "",
        "| run | exit | done | usable | false obstacle | false free | distance (m) | "
        "to 90 % (s) | collisions | wall (s) | warnings |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| seed{r['seed']}_{r['arm']} | {r['exit_code']} | {r.get('done_reason') or '-'} | "
            f"{exr.fmt_pct(r.get('usable_share'))} | "
            f"{exr.fmt_pct(r.get('false_obstacle_share'))} | "
            f"{_pct2(r.get('false_free_share'))} | {exr.fmt_num(r.get('distance_m'))} | "
            f"{exr.fmt_num(r.get('time_to_90_s'), '.0f')} | "
            f"{'-' if r.get('collisions') is None else r['collisions']} | "
            f"{exr.fmt_num(r.get('wall_time_s'), '.0f')} | {r.get('run_warnings') or '-'} |"
        )
    if fig is not None:
        lines += ["", f"![{fig.stem}]({fig.name})"]
    (out / "robustness_summary.md").write_text("\n".join(lines) + "\n")
