"""The figures and verdicts of `smana experiment fleet` (fleet.py holds its design, its runs and
its command line): the summary per world and fleet size (Kaplan-Meier for the censored times to
coverage), the targets' verdicts, the tables, the figures and the files a run writes."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict
from pathlib import Path

from smana.lab import paper_figures, stats, survival

from . import exploration as ex
from . import exploration_report as exr
from .fleet import (
    COVERAGE_TARGET,
    LARGE_GARDEN,
    MET,
    NOT_MET,
    NOT_WORSE_MARGINS,
    TIME_TARGETS,
    FleetExperimentConfig,
    failed,
    measured,
    run_name,
)

# -- aggregation ---------------------------------------------------------------------------------

SUMMARY_KEYS = (
    "coverage",
    "overlap",
    "map_error_m",
    "classification_ratio",
    "robot_contacts",
)


def budgets_of(meta: dict) -> dict[str, float]:
    """{world: its robot time budget} from a data file's meta (the settings of the run)."""
    out = {}
    for w in meta.get("worlds") or []:
        b = meta.get("budget_s") or w.get("budget_s")
        if b:
            out[w["name"]] = float(b)
    return out


def _budget(rows: list[dict], world: str, budgets: dict[str, float] | None) -> float:
    """Where a run of `world` that did not reach 95 % is censored: its budget (the rows' own,
    or the data file's), else the latest end among its runs."""
    own = [r["budget_s"] for r in rows if r["world"] == world and r.get("budget_s")]
    b = own[0] if own else (budgets or {}).get(world)
    sel = [dict(r, end_time_s=_end_time(r)) for r in rows if r["world"] == world]
    return ex.horizon_of("time_to_95_s", b, sel, "end_time_s")


def _runs(rows: list[dict], world: str, n: int) -> dict[int, dict]:
    """seed -> the measured run of (world, n) (`measured`: failed runs included)."""
    return {
        r["seed"]: r for r in rows if measured(r) and r["world"] == world and r["n_robots"] == n
    }


def _to_event(runs: list[dict], key: str, horizon: float) -> tuple[list[float], list[bool]]:
    return exr.to_event(runs, key, horizon, failed)


def _km(runs: list[dict], key: str, horizon: float) -> dict:
    return exr.km_summary(runs, key, horizon, failed)


def summarise_fleet(rows: list[dict], budgets: dict[str, float] | None = None) -> list[dict]:
    """Per world and N: the time and distance to 95 % as times to an event over the measured
    runs (failed ones counted as not reached: `failed`), the log-rank test of N robots against
    one, and the intervals of SUMMARY_KEYS over the measured runs."""
    out = []
    for world, n in dict.fromkeys((r["world"], r["n_robots"]) for r in rows):
        sel = [r for r in rows if r["world"] == world and r["n_robots"] == n]
        runs = [r for r in sel if measured(r)]
        horizon = _budget(rows, world, budgets)
        lr = None
        one = list(_runs(rows, world, 1).values())
        if n != 1 and one and runs:
            t = _to_event(runs, "time_to_95_s", horizon)
            t1 = _to_event(one, "time_to_95_s", horizon)
            lr = survival.logrank(*t, *t1)
        out.append(
            {
                "world": world,
                "size_m": sel[0]["size_m"],
                "n_robots": n,
                "runs": len(sel),
                "failed": len(sel) - len(runs),  # missing: no figures
                "run_failed": sum(failed(r) for r in runs),
                "reached_95": sum(not c for c in _to_event(runs, "time_to_95_s", horizon)[1]),
                "budget_s": horizon,
                "km_time_to_95_s": _km(runs, "time_to_95_s", horizon),
                "km_distance_to_95_m": _km(runs, "distance_to_95_m", ex.NOT_REACHED_DISTANCE),
                "logrank_vs_one": None if lr is None else asdict(lr) | {"z": lr.z, "p": lr.p},
                "logrank_text": ""
                if lr is None
                else lr.describe(f"{n} robots", "one").replace("log-rank ", ""),
                **{k: stats.mean_ci([r.get(k) for r in runs]).as_dict() for k in SUMMARY_KEYS},
            }
        )
    return out


def _met(d: stats.Decision) -> str:
    return {stats.REPRODUCED: MET, stats.NOT_REPRODUCED: NOT_MET}.get(d.verdict, d.verdict)


def not_worse(ci: stats.Interval, lower_is_better: bool, margin: float) -> str:
    """A paired difference (fleet minus one robot) that must not be worse by more than `margin`
    (declared before the runs, `NOT_WORSE_MARGINS`): met when its interval lies on the good side
    of the margin, not met when wholly on the bad side (`stats.decide_not_worse`). An interval
    that merely holds 0 is not enough: it must be narrow enough to rule the margin out."""
    return _met(stats.decide_not_worse(ci, margin, higher_is_better=not lower_is_better))


def _end_time(row: dict) -> float | None:
    """A run's robot time at its end: `end_time_s` (what the committed data keeps, having no
    curves), or the last time of its curve."""
    if row.get("end_time_s") is not None:
        return float(row["end_time_s"])
    t = (row.get("curve") or {}).get("t_s") or []
    return float(t[-1]) if t else None


def time_pairs(
    rows: list[dict], world: str, n: int, target: float, budgets: dict[str, float] | None = None
):
    """(seeds, the fleet's (time, censored), `target` x the lone robot's (time, censored)) over
    the seeds where both ran (failed runs counted as not reached, censored at the budget)."""
    one, many = _runs(rows, world, 1), _runs(rows, world, n)
    seeds = sorted(one.keys() & many.keys())
    horizon = _budget(rows, world, budgets)
    fleet = _to_event([many[k] for k in seeds], "time_to_95_s", horizon)
    lone = _to_event([one[k] for k in seeds], "time_to_95_s", horizon)
    return seeds, fleet, ([target * v for v in lone[0]], lone[1])


def decide_time(
    rows: list[dict], world: str, n: int, target: float, budgets: dict[str, float] | None = None
) -> tuple[stats.Decision, str]:
    """ "Time to 95 % with n robots at most `target` times one robot's", paired per seed: the
    exact sign test over the seeds whose order is known (`survival.paired_order`, the fleet's
    time against `target` times the lone robot's); (its decision, the text the table shows)."""
    seeds, (a, ac), (b, bc) = time_pairs(rows, world, n, target, budgets)
    order = survival.paired_order(a, ac, b, bc)
    unknown = [
        k
        for k, x, xc, y, yc in zip(seeds, a, ac, b, bc, strict=True)
        if survival.pair_order(x, xc, y, yc) == "unknown"
    ]
    horizon = _budget(rows, world, budgets)
    text = (
        f"under {target:g} x one robot's time in {order.a_first} of {len(seeds)} seeds, over in "
        f"{order.b_first}"
        + (f", tied in {order.tied}" if order.tied else "")
        + (
            f", order unknown in {order.unknown} (seed {', '.join(map(str, unknown))})"
            if unknown
            else ""
        )
        + (
            f" ({order.through_censoring} known through a run that did not reach 95 % within "
            f"the {horizon:.0f} s budget)"
            if order.through_censoring
            else ""
        )
    )
    many, one = _runs(rows, world, n), _runs(rows, world, 1)
    fails = [f"seed {k} ({m} robot{'s' * (m > 1)})" for m, runs in ((n, many), (1, one))
             for k in seeds if failed(runs[k])]  # fmt: skip
    if fails:
        text += f"; FAILED runs counted as not reached: {', '.join(fails)}"
    if seeds and math.isfinite(horizon):
        rm = [
            survival.kaplan_meier(v, c).rmst(horizon).mean
            for v, c in (
                _to_event([many[k] for k in seeds], "time_to_95_s", horizon),
                _to_event([one[k] for k in seeds], "time_to_95_s", horizon),
            )
        ]
        text += (
            f"; restricted mean time to 95 % within {horizon:.0f} s: {rm[0]:.0f} s vs "
            f"{rm[1]:.0f} s alone (ratio {rm[0] / rm[1]:.2f})"
        )
    d = stats.decide_first_paired(
        order, f"at most {target:g} x one robot's", f"more than {target:g} x one robot's"
    )
    return d, text


def paired_difference(rows: list[dict], world: str, n: int, key: str) -> stats.Interval:
    """Interval of (n robots minus one robot) of `key` over the seeds both ran with a value
    (failed runs included, their maps scored as they are)."""
    one, many = _runs(rows, world, 1), _runs(rows, world, n)
    return stats.mean_ci(
        [
            many[k][key] - one[k][key]
            for k in sorted(one.keys() & many.keys())
            if one[k].get(key) is not None and many[k].get(key) is not None
        ]
    )


def verdicts(
    rows: list[dict],
    large_world: str = LARGE_GARDEN.name,
    budgets: dict[str, float] | None = None,
) -> list[dict]:
    """The targets, each decided over seeds: (claim, target, smana, verdict, p, p_tests, rule,
    need) rows. `budgets`: {world: robot time budget} where the rows do not say (data written
    before they did)."""
    out = []
    worlds = list(dict.fromkeys(r["world"] for r in rows))
    sizes = sorted({r["n_robots"] for r in rows})
    if large_world in worlds and 1 in sizes:
        for n, target in TIME_TARGETS.items():
            if n not in sizes:
                continue
            d, text = decide_time(rows, large_world, n, target, budgets)
            out.append(
                {
                    "claim": f"{large_world}: time to {100 * COVERAGE_TARGET:.0f} % coverage with "
                    f"{n} robots over one robot's, paired per seed, runs that did not reach it "
                    "kept",
                    "target": f"<= {target:g}",
                    "smana": text,
                    **d.fields(),
                    "verdict": _met(d),
                    "rule": "at most T, sign test",
                    "evidence": "",
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
                        **d.fields(),
                        "verdict": _met(d),
                        "rule": "not worse",
                        "evidence": "",
                        "unit": " m" if lower else "",
                    }
                )
    runs = [r for r in rows if measured(r)]
    counts = [r.get("robot_contacts") for r in runs]
    known = [c for c in counts if c is not None]
    total = int(sum(known))
    if total:
        verdict = NOT_MET
    elif runs and len(known) == len(counts):
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
    # the end time beside the curve: the data file has no curves, and a run without a budget
    # is censored at the latest end
    rows = [dict(r, end_time_s=_end_time(r)) for r in rows]
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    if flat:
        with open(out / "fleet.csv", "w", newline="") as f:
            # every row's fields (a row kept from an older run may lack the newer ones)
            fields = list(dict.fromkeys(k for r in flat for k in r))
            w = csv.DictWriter(f, fieldnames=fields, restval="")
            w.writeheader()
            w.writerows(flat)
    budgets = {w.name: s.budget(w) for w in s.worlds}
    summary = summarise_fleet(rows, budgets)
    from .report import write_data

    write_data(out, "fleet", rows, asdict(s))
    table = verdicts(rows, budgets=budgets)
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
    missing = [r for r in rows if not measured(r)]
    if missing:
        names = ", ".join(
            f"{run_name(r['seed'], r['world'], r['n_robots'])} (exit {r['exit_code']})"
            for r in missing
        )
        lines += [
            f"**WARNING: {len(missing)} of {len(rows)} runs failed to run** (no metrics, or a "
            f"non-zero exit for another reason than what the robots did), left out of every "
            f"number below: {names}.",
            "",
        ]
    flagged = [r for r in rows if failed(r)]
    if flagged:
        names = ", ".join(run_name(r["seed"], r["world"], r["n_robots"]) for r in flagged)
        lines += [
            f"**WARNING: {len(flagged)} of {len(rows)} runs FAILED on what their robots did** "
            f"(a member that did not move or found no path): counted as not reached in the "
            f"times to 95 %, their maps scored as they are: {names}.",
            "",
        ]
    lines += [
        "| claim | target | smana | p | verdict |",
        "|---|---|---|---|---|",
        *(
            f"| {v['claim']} | {v['target']} | {v['smana']} | "
            f"{stats.format_p(v['p'], v.get('p_tests'))} | {v['verdict']} |"
            for v in table
        ),
        "",
        f"Seeds {list(s.seeds)}, worlds "
        + ", ".join(f"{w.name} ({w.size_m:g} m, budget {s.budget(w):.0f} s)" for w in s.worlds)
        + f", {s.jobs} run(s) at once. World: {' '.join(ex.WORLD_SETS)}.",
        "",
        *summary_table(summary),
        "",
        exr.TO_95_NOTE + " A run that smana up ended FAILED on what its robots did counts as "
        "not reached; the distance is every member's, added; the log-rank test is two-sided, "
        "with the side the data lean to.",
        "",
        "| run | exit | coverage | time to 95 % (s) | distance to 95 % (m) | overlap | "
        "contacts | min separation (m) | wall (s) | CPU (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t95 = "not reached" if r["time_to_95_s"] is None else f"{r['time_to_95_s']:.0f}"
        lines.append(
            f"| {run_name(r['seed'], r['world'], r['n_robots'])} | {r['exit_code']} | "
            f"{exr.fmt_pct(r['coverage'])} | {t95} | {exr.fmt_num(r['distance_to_95_m'])} | "
            f"{exr.fmt_pct(r['overlap'])} | {_int(r['robot_contacts'])} | "
            f"{exr.fmt_num(r['min_separation_m'], '.2f')} | "
            f"{exr.fmt_num(r['wall_time_s'], '.0f')} | "
            f"{exr.fmt_num(r['cpu_s'], '.0f')} |"
        )
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    (out / "fleet.md").write_text("\n".join(lines))
    return figures


SUMMARY_HEAD = (
    "| world | robots | runs (FAILED; missing) | "
    + exr.TO_95_HEAD
    + " | against one robot, time to 95 % | coverage | overlap | map error (m) | "
    "classification ratio |"
)


def summary_table(summary: list[dict]) -> list[str]:
    """The table per world and N (fleet.md's and docs/experiments.md's): times to 95 % as times
    to an event, the log-rank test against one robot, and intervals over the measured runs."""
    lines = [SUMMARY_HEAD, "|" + "---|" * SUMMARY_HEAD.count(" | ") + "---|"]
    for d in summary:
        iv = {k: exr.interval_of(d[k]) for k in SUMMARY_KEYS}
        lines.append(
            f"| {d['world']} | {d['n_robots']} | {d['runs']} ({d['run_failed']}; "
            f"{d['failed']}) | {exr.to_95_cells(d)} | {d['logrank_text'] or '-'} | "
            f"{iv['coverage'].format(100, unit=' %')} | {iv['overlap'].format(100, unit=' %')} | "
            f"{iv['map_error_m'].format(fmt='.3f')} | "
            f"{iv['classification_ratio'].format(fmt='.3f')} |"
        )
    return lines


def _int(v) -> str:
    return "-" if v is None else str(int(v))


def _figures(rows: list[dict], out: Path) -> list[Path]:
    """Coverage against robot time per world, one curve (mean and interval over seeds) per N."""
    saved = []
    for world in dict.fromkeys(r["world"] for r in rows):
        curves = []
        for n in sorted({r["n_robots"] for r in rows if r["world"] == world}):
            sel = [r for r in rows if r["world"] == world and r["n_robots"] == n]
            c = exr.mean_curve(sel, "t_s")
            if c is not None:
                k = sum(1 for r in sel if r["ok"] and len(r["curve"]["t_s"]) >= 2)
                curves.append((f"{n} robot{'s' * (n > 1)} (n = {k})", *c))
        if curves:
            size = next(r["size_m"] for r in rows if r["world"] == world)
            saved.append(
                paper_figures.save(
                    paper_figures.band_plot(
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
