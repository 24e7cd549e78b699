"""The figures and verdicts of `smana experiment exploration` (exploration.py holds its design,
its runs, shared by the other closed-loop experiments, and its command line): the summary per
arm (Kaplan-Meier and restricted mean for the censored times to coverage), the claims'
verdicts, the mean curves, the tables, the figures and the files a run writes; the number
formats the other experiments' tables share.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from smana.lab import paper_figures, stats, survival

from .exploration import (
    COVERAGE_TARGET,
    NOT_REACHED_DISTANCE,
    PAPER_TERRAIN_SHARE,
    TERRAIN_SHARE_TOLERANCE,
    Arm,
    ExplorationExperimentConfig,
    counted,
    horizon_of,
    layout_of,
    run_name,
    run_world_sets,
    time_to_event,
)

# -- aggregation ---------------------------------------------------------------------------------


def _ci(rows, key) -> stats.Interval:
    return stats.mean_ci([counted(r, key) for r in rows if r["ok"]])


def to_event(rows: list[dict], key: str, horizon: float, failed=None):
    """(values, censored) of `key` over the measured runs (`time_to_event`); `failed(r)` says
    which runs count as failures beside those whose robot stood still."""
    pairs = [time_to_event(r, key, horizon, bool(failed and failed(r))) for r in rows]
    return [v for v, _ in pairs], [c for _, c in pairs]


def km_summary(rows: list[dict], key: str, horizon: float, failed=None) -> dict:
    """Kaplan-Meier median of `key` with its 95 % interval (None: not reached by half, or an
    end the band never reaches), and for robot time the restricted mean up to the budget."""
    values, censored = to_event(rows, key, horizon, failed)
    out = {"median": None, "lo": None, "hi": None, "n": len(values), "rmst": None}
    if not values:
        return out
    km = survival.kaplan_meier(values, censored)
    out["median"] = km.median()
    out["lo"], out["hi"] = km.median_ci()
    if math.isfinite(horizon):
        r = km.rmst(horizon)
        lo, hi = r.ci()
        out["rmst"] = {"mean": r.mean, "se": r.se, "lo": lo, "hi": hi, "horizon": horizon}
    return out


def format_km(d: dict, fmt: str = ".1f") -> str:
    """ "62.3 [38.2, 71.8] (n = 10)": a Kaplan-Meier median and its interval; "not reached" for
    a median or an end the curve does not reach."""
    if not d["n"]:
        return "- (n = 0)"

    def f(v):
        return "not reached" if v is None else format(v, fmt)

    if d["median"] is None:
        return f"not reached by half (n = {d['n']})"
    return f"{f(d['median'])} [{f(d['lo'])}, {f(d['hi'])}] (n = {d['n']})"


def format_rmst(d: dict, fmt: str = ".0f") -> str:
    r = d.get("rmst")
    if not r:
        return "-"
    return f"{r['mean']:{fmt}} [{r['lo']:{fmt}}, {r['hi']:{fmt}}] (n = {d['n']})"


def summarise_exploration(rows: list[dict], budget_s: float | None = None) -> list[dict]:
    """Per arm: intervals of terrain share, coverage and distance over the measured runs; and
    the distance and time to 95 % as times to an event (`time_to_event`: a run that did not
    reach it is censored, never dropped nor averaged): how many reached it, the Kaplan-Meier
    medians with their intervals, and the restricted mean time up to the budget."""
    out = []
    for arm in dict.fromkeys(r["arm"] for r in rows):
        sel = [r for r in rows if r["arm"] == arm]
        ok = [r for r in sel if r["ok"]]
        t_end = horizon_of("time_to_95_s", budget_s, ok, "robot_time_s")
        dist = km_summary(ok, "distance_to_95_m", NOT_REACHED_DISTANCE)
        time_ = km_summary(ok, "time_to_95_s", t_end)
        out.append(
            {
                "arm": arm,
                "strategy": sel[0]["strategy"],
                "grass_cost_factor": sel[0]["grass_cost_factor"],
                "path_cost_weight": sel[0].get("path_cost_weight"),
                "runs": len(sel),
                "failed": len(sel) - len(ok),
                "reached_95": sum(not time_to_event(r, "time_to_95_s", t_end)[1] for r in ok),
                "km_median_distance_to_95_m": dist["median"],
                "km_median_time_to_95_s": time_["median"],
                "km_distance_to_95_m": dist,
                "km_time_to_95_s": time_,
                **{k: _ci(sel, k).as_dict() for k in ("terrain_share", "coverage", "distance_m")},
                "paper_terrain_share": PAPER_TERRAIN_SHARE.get(sel[0]["grass_cost_factor"])
                if sel[0]["strategy"] == "nbv"
                else None,
            }
        )
    return out


TO_95_HEAD = (
    "reached 95 % | distance to 95 % (m), Kaplan-Meier median [95 % CI] | time to 95 % (s), "
    "Kaplan-Meier median [95 % CI] | restricted mean time to 95 % within the budget (s) [95 % CI]"
)
TO_95_NOTE = (
    "A run that did not reach 95 % by its end (its budget ran out, its explorer stopped, or its "
    "robot did not move) did not reach it within the budget: censored at the budget for time, "
    "beyond every distance for distance (lab/survival.py); never dropped, never averaged as a "
    "number. Kaplan-Meier medians with the times whose 95 % log-log band holds 0.5 "
    "(Brookmeyer-Crowley; 'not reached' where the curve never gets there); the restricted mean "
    "time is the area under the curve up to the budget (the mean of min(time, budget)), with "
    "its Greenwood-type standard error."
)


def to_95_cells(d: dict) -> str:
    """The TO_95_HEAD cells of one summary row (`summarise_exploration`, `summarise_fleet`)."""
    return (
        f"{d['reached_95']} of {d['runs'] - d['failed']} | "
        f"{format_km(d['km_distance_to_95_m'])} | {format_km(d['km_time_to_95_s'], '.0f')} | "
        f"{format_rmst(d['km_time_to_95_s'])}"
    )


def interval_of(d: dict) -> stats.Interval:
    """The mean and its confidence interval of a summary row's entry."""
    nan = math.nan
    lo, hi = d["ci_lo"], d["ci_hi"]
    return stats.Interval(
        nan if d["mean"] is None else d["mean"],
        nan if lo is None else lo,
        nan if hi is None else hi,
        d["n"],
    )


def _paired(a_rows: list[dict], b_rows: list[dict], key: str) -> stats.Interval:
    """Interval of b - a over the seeds both arms ran with a value: every arm runs the same
    worlds from the same starts, so a per-seed difference removes the world-to-world spread."""
    a = {r["seed"]: counted(r, key) for r in a_rows if r["ok"] and counted(r, key) is not None}
    b = {r["seed"]: counted(r, key) for r in b_rows if r["ok"] and counted(r, key) is not None}
    return stats.mean_ci([b[k] - a[k] for k in sorted(a.keys() & b.keys())])


def verdicts(rows: list[dict], routes: dict[float, stats.Interval] | None = None) -> list[dict]:
    """The claims, each decided by a rule of lab/stats.py fixed before the runs: (claim, paper,
    smana, verdict, p, p_tests, rule, need) rows. The terrain share "about X" (`decide_near`,
    or "not reproducible in this world" when `routes`, the layout's own shares per factor, rule
    X out); its rise "about +D" paired per seed (the size of the paper's effect, not only its
    sign); NBV sooner than nearest frontier in distance to 95 % by the log-rank test, runs that
    did not reach it kept as censored (`time_to_event`), with the paired count per seed beside
    it. The p-values are uncorrected; docs/experiments.md corrects its whole table together
    (Holm)."""
    nbv_rows = [r for r in rows if r["strategy"] == "nbv" and r.get("path_cost_weight") is None]
    out = []

    def add(claim, paper, smana, d: stats.Decision, rule, scale=1.0, unit=""):
        out.append(
            {
                "claim": claim,
                "paper": paper,
                "smana": smana,
                **d.fields(),
                "rule": rule,
                "evidence": d.evidence,
                "scale": scale,
                "unit": unit,
            }
        )

    tol = TERRAIN_SHARE_TOLERANCE
    factors = sorted({r["grass_cost_factor"] for r in nbv_rows})
    for f in factors:
        ci = _ci([r for r in nbv_rows if r["grass_cost_factor"] == f], "terrain_share")
        paper = PAPER_TERRAIN_SHARE.get(f)
        if paper is None:
            continue
        world = (routes or {}).get(f)
        d = (
            stats.decide_in_world(ci, paper, tol, world)
            if world is not None
            else stats.decide_near(ci, paper, tol)
        )
        add(
            f"terrain share at grass x{f:g}, about the paper's",
            f"{100 * paper:.0f} % +/- {100 * tol:.0f}",
            ci.format(100, unit=" %"),
            d,
            "about X",
            100,
            " points",
        )
    known = [f for f in factors if f in PAPER_TERRAIN_SHARE]
    if len(known) >= 2:
        lo_f, hi_f = min(known), max(known)
        effect = PAPER_TERRAIN_SHARE[hi_f] - PAPER_TERRAIN_SHARE[lo_f]
        d = _paired(
            [r for r in nbv_rows if r["grass_cost_factor"] == lo_f],
            [r for r in nbv_rows if r["grass_cost_factor"] == hi_f],
            "terrain_share",
        )
        add(
            f"terrain share rises from x{lo_f:g} to x{hi_f:g} by about the paper's effect, "
            "paired per seed",
            f"+{100 * effect:.0f} points +/- {100 * tol:.0f}",
            d.format(100, unit=" points"),
            stats.decide_near(d, effect, tol),
            "about +D",
            100,
            " points",
        )
    base = [r for r in rows if r["strategy"] == "nearest_frontier" and r["ok"]]
    if base:
        f = base[0]["grass_cost_factor"]
        nb = [r for r in nbv_rows if r["grass_cost_factor"] == f and r["ok"]]
        seeds = {r["seed"] for r in nb} & {r["seed"] for r in base}
        nb = [r for r in nb if r["seed"] in seeds]  # the same seed set for both arms
        bs = [r for r in base if r["seed"] in seeds]
        key, far = "distance_to_95_m", NOT_REACHED_DISTANCE
        # one run per seed and arm, in seed order: the pairs of `paired_order`
        nb = list({r["seed"]: r for r in sorted(nb, key=_seed)}.values())
        bs = list({r["seed"]: r for r in sorted(bs, key=_seed)}.values())
        a, ac = to_event(nb, key, far)
        b, bc = to_event(bs, key, far)
        d = (
            stats.decide_sooner_censored(a, ac, b, bc, names=("NBV", "nearest frontier"))
            if a and b
            else stats.Decision(stats.INCONCLUSIVE, 1.0, 1.0)
        )
        order = survival.paired_order(a, ac, b, bc)
        pairs = f"; NBV first in {order.a_first} of {order.ordered} seeds whose order is known" + (
            f" ({order.unknown} unknown: neither reached 95 %)" if order.unknown else ""
        )
        add(
            f"NBV reaches {100 * COVERAGE_TARGET:.0f} % coverage in less distance than nearest "
            f"frontier (x{f:g}), censored runs kept",
            "(NBV's motivation)",
            f"reached in {len(ac) - sum(ac)} of {len(ac)} vs {len(bc) - sum(bc)} of {len(bc)}; "
            + (d.evidence or "no runs")
            + (pairs if a and b else ""),
            d,
            "sooner, censored",
        )
    return out


def _seed(r: dict) -> int:
    return r["seed"]


def mean_curve(runs: list[dict], axis: str, n_points: int = 60):
    """(x grid, mean, lo, hi) of coverage over runs against `axis` ("t_s" or "distance_m"); a
    run that ended keeps its last coverage (what it had explored when it stopped)."""
    curves = [r["curve"] for r in runs if r["ok"] and len(r["curve"][axis]) >= 2]
    if not curves:
        return None
    x_max = max(c[axis][-1] for c in curves)
    grid = np.linspace(0.0, x_max, n_points)
    # np.interp holds the end values outside a run's range: 0 before, the final coverage after
    ys = np.array([np.interp(grid, c[axis], c["coverage"], left=0.0) for c in curves])
    cis = [stats.mean_ci(ys[:, k]) for k in range(n_points)]
    return (
        grid,
        np.array([c.mean for c in cis]),
        np.array([c.lo for c in cis]),
        np.array([c.hi for c in cis]),
    )


# -- outputs -------------------------------------------------------------------------------------


def data_variant(s: ExplorationExperimentConfig) -> str | None:
    """The name of a run's data file beside the default one (`exploration.json`, the 12 m garden
    of the default layout): `exploration_garden20.json` for a 20 m garden, with the layout when
    a `--set sim.garden.layout=...` changed it (`exploration_garden12<layout>.json`); a quick
    run is `quick`."""
    if s.is_quick:
        return "quick"
    layout = "".join(c for c in layout_of(s.extra) if c.isalnum()).lower()
    if s.size_m == ExplorationExperimentConfig.size_m and not layout:
        return None
    return f"garden{s.size_m:g}".replace(".", "p") + layout


def write_exploration_outputs(rows: list[dict], s: ExplorationExperimentConfig, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    flat = [{k: v for k, v in r.items() if k != "curve"} for r in rows]
    with open(out / "exploration_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(flat[0]))
        w.writeheader()
        w.writerows(flat)
    from .report import write_data

    write_data(out, "exploration", rows, asdict(s), data_variant(s))
    summary = summarise_exploration(rows, s.budget_s)
    table = verdicts(rows)
    (out / "exploration_results.json").write_text(
        json.dumps(
            {"settings": asdict(s), "runs": rows, "summary": summary, "verdicts": table},
            indent=2,
        )
    )
    figures = _figures(rows, out)
    failed = [r for r in rows if not r["ok"]]
    lines = ["# Exploration experiment (paper 4.3)", ""]
    if failed:
        names = ", ".join(
            f"{run_name(r['seed'], _arm_of(r))} (exit {r['exit_code']})" for r in failed
        )
        lines += [
            f"**WARNING: {len(failed)} of {len(rows)} runs failed** (no metrics or non-zero "
            f"exit), left out of every number below: {names}.",
            "",
        ]
    if s.is_quick:
        lines += [
            f"**Quick run**: {len(s.seeds)} seed{'s' * (len(s.seeds) != 1)} of "
            f"{s.budget_s:.0f} s in a {s.size_m:g} m garden. It checks that the experiment "
            "works; its verdicts say nothing about the paper (the full run: `smana experiment "
            "exploration`, docs/experiments.md).",
            "",
        ]
    lines += [
        "| claim | paper | smana mean [95 % CI] (n) | verdict |",
        "|---|---|---|---|",
        *(f"| {v['claim']} | {v['paper']} | {v['smana']} | {v['verdict']} |" for v in table),
        "",
        f"Seeds {list(s.seeds)}, garden {s.size_m} m, budget {s.budget_s:.0f} s per run, "
        f"{s.jobs} runs at once. World: {' '.join(run_world_sets(s.extra))}.",
        "",
        f"| arm | runs (failed) | terrain share | coverage | distance (m) | {TO_95_HEAD} |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in summary:
        iv = {k: interval_of(d[k]) for k in ("terrain_share", "coverage", "distance_m")}
        lines.append(
            f"| {d['arm']} | {d['runs']} ({d['failed']}) | "
            f"{iv['terrain_share'].format(100, unit=' %')} | "
            f"{iv['coverage'].format(100, unit=' %')} | {iv['distance_m'].format()} | "
            f"{to_95_cells(d)} |"
        )
    lines += [
        "",
        TO_95_NOTE + " Coverage curves: the explorer's explored area rescaled to the "
        "ground-truth coverage at the end of each run (lab/experiments/exploration.py explains).",
        "",
        "| run | exit | terrain share | coverage | distance (m) | to 95 % (m) | wall (s) | "
        "CPU (s) | real-time factor |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        d95 = "not reached" if r["distance_to_95_m"] is None else f"{r['distance_to_95_m']:.1f}"
        lines.append(
            f"| {run_name(r['seed'], _arm_of(r))} | {r['exit_code']} | "
            f"{fmt_pct(r['terrain_share'])} | {fmt_pct(r['coverage'])} | "
            f"{fmt_num(r['distance_m'])} | {d95} | "
            f"{fmt_num(r['wall_time_s'], '.0f')} | {fmt_num(r['cpu_s'], '.0f')} | "
            f"{fmt_num(r['real_time_factor'], '.2f')} |"
        )
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    (out / "exploration_summary.md").write_text("\n".join(lines))


def _arm_of(r: dict) -> Arm:
    return Arm(r["arm"], r["grass_cost_factor"])


def fmt_pct(v):
    """A share as a percentage with one decimal, "-" when there is none."""
    return "-" if v is None else f"{100 * v:.1f} %"


def fmt_num(v, fmt=".1f"):
    """A number in `fmt`, "-" when there is none."""
    return "-" if v is None else format(v, fmt)


def _figures(rows: list[dict], out: Path) -> list[Path]:
    saved = []
    nbv_rows = [r for r in rows if r["strategy"] == "nbv" and r["ok"]]
    factors = sorted({r["grass_cost_factor"] for r in nbv_rows if r["terrain_share"] is not None})
    if factors:
        cis = [
            _ci([r for r in nbv_rows if r["grass_cost_factor"] == f], "terrain_share")
            for f in factors
        ]
        ns = sorted({c.n for c in cis})
        n_text = f"n = {ns[0]}" if len(ns) == 1 else f"n = {ns[0]}-{ns[-1]}"
        n_text += " seed" if ns == [1] else " seeds"
        err = None  # with one seed there is no interval to draw
        if all(c.defined for c in cis):
            err = ([c.mean - c.lo for c in cis], [c.hi - c.mean for c in cis])
        label = f"smana NBV, mean and 95 % CI ({n_text})" if err else f"smana NBV ({n_text})"
        series = [paper_figures.Series(label, factors, [c.mean for c in cis], err)]
        paper = [(f, v) for f, v in PAPER_TERRAIN_SHARE.items() if f in factors]
        if paper:
            series.append(
                paper_figures.Series(
                    "paper", [f for f, _ in paper], [v for _, v in paper], dashed=True
                )
            )
        base = [r for r in rows if r["strategy"] == "nearest_frontier" and r["ok"]]
        if base:
            ci = _ci(base, "terrain_share")
            series.append(
                paper_figures.Series(
                    f"nearest frontier (n = {ci.n})",
                    [base[0]["grass_cost_factor"]],
                    [ci.mean],
                    ([ci.mean - ci.lo], [ci.hi - ci.mean]) if ci.defined else None,
                )
            )
        saved.append(
            paper_figures.save(
                paper_figures.line_plot(
                    series,
                    f"Travelled nodes on terrain vs grass cost ({n_text})",
                    "grass cost factor (x terrain's cost)",
                    "terrain share of travelled nodes",
                    {f: f"x{f:g}" for f in factors},
                ),
                out / "exploration_terrain_share.png",
            )
        )
    # coverage curves: NBV against the baseline at the baseline's cost (x2), else every NBV arm
    base = [r for r in rows if r["strategy"] == "nearest_frontier"]
    f0 = base[0]["grass_cost_factor"] if base else None
    groups = {}
    for r in rows:
        if r["strategy"] == "nbv" and r.get("path_cost_weight") is None:
            if f0 is None or r["grass_cost_factor"] == f0:
                groups.setdefault(f"NBV x{r['grass_cost_factor']:g}", []).append(r)
    if base:
        groups[f"nearest frontier x{f0:g}"] = base
    for axis, xlabel, name in (
        ("distance_m", "distance travelled (m)", "exploration_coverage_distance.png"),
        ("t_s", "robot time (s)", "exploration_coverage_time.png"),
    ):
        curves = []
        for label, sel in groups.items():
            c = mean_curve(sel, axis)
            if c is not None:
                n = sum(1 for r in sel if r["ok"] and len(r["curve"][axis]) >= 2)
                curves.append((f"{label} (n = {n})", *c))
        if curves:
            saved.append(
                paper_figures.save(
                    paper_figures.band_plot(
                        curves,
                        f"Coverage of the reachable traversable area vs {xlabel.split(' (')[0]}",
                        xlabel,
                        "coverage (rescaled to ground truth at the end)",
                        note="mean and 95 % CI over seeds",
                        hline=COVERAGE_TARGET,
                        clip=(0.0, 1.0),  # a share
                    ),
                    out / name,
                )
            )
    return saved
