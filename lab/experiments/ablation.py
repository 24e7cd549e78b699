"""`smana experiment ablation`: NBV at one grass cost factor (x4 by default) for several path-cost
weights (`explorer.path_cost_weight`), over seeds: terrain share, distance and coverage per weight,
each with its 95 % interval, and a plot. It reuses the exploration runner (same worlds, starts,
parallel runs, failure accounting). Its compact rows go into `<out>/data/ablation.json`, from
which `smana experiment report` generates the table of docs/experiments.md (`section`).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

from smana.lab import paper_figures

from . import exploration as ex
from . import exploration_report as exr

DEFAULT_WEIGHTS = (0.0, 0.5, 2.0)  # docs/experiments.md; 2 is the default weight


def weight_arms(factor: float, weights) -> tuple[ex.Arm, ...]:
    return tuple(
        ex.Arm(f"nbv_x{factor:g}_w{w:g}", factor, path_cost_weight=float(w)) for w in weights
    )


# what ablation.json keeps of a run's row: enough for the table (`summarise_exploration`)
DATA_KEYS = (
    "seed",
    "arm",
    "strategy",
    "grass_cost_factor",
    "path_cost_weight",
    "ok",
    "exit_code",
    "terrain_share",
    "distance_m",
    "coverage",
    "distance_to_95_m",
    "time_to_95_s",
    "robot_time_s",
)


def table(rows: list[dict]) -> list[str]:
    """The markdown table of intervals per weight (the summary's and the doc's)."""
    lines = [
        "| weight | grass | runs (failed) | terrain share | distance (m) | coverage | "
        "reached 95 % |",
        "|---|---|---|---|---|---|---|",
    ]
    for d in exr.summarise_exploration(rows):
        iv = {k: exr.interval_of(d[k]) for k in ("terrain_share", "distance_m", "coverage")}
        lines.append(
            f"| {d['path_cost_weight']:g} | x{d['grass_cost_factor']:g} | {d['runs']} "
            f"({d['failed']}) | {iv['terrain_share'].format(100, unit=' %')} | "
            f"{iv['distance_m'].format()} | {iv['coverage'].format(100, unit=' %')} | "
            f"{d['reached_95']} of {d['runs'] - d['failed']} |"
        )
    return lines


def section(data: dict | None) -> str:
    """docs/experiments.md's ablation table, from docs/experiments/data/ablation.json."""
    if data is None:
        return (
            "_No raw results of `smana experiment ablation` are committed yet "
            "(docs/experiments/data/ablation.json): nothing is generated here._\n"
        )
    meta, rows = data.get("meta") or {}, [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    seeds = sorted({r["seed"] for r in rows})
    from .report import duration

    done = [f"{duration(meta['wall_s'])} wall"] if meta.get("wall_s") else []
    done += [meta["date"]] if meta.get("date") else []
    head = (
        "Generated from docs/experiments/data/ablation.json"
        + (f", made by `{meta['command']}`" if meta.get("command") else "")
        + (f" ({', '.join(done)})" if done else "")
        + f": seeds {', '.join(map(str, seeds))}, garden {meta.get('size_m', '?')} m, budget "
        f"{meta.get('budget_s', 0):.0f} s of robot time per run, {len(rows)} runs, "
        + (f"**{sum(not r['ok'] for r in rows)} failed** (left out of every figure)"
           if any(not r["ok"] for r in rows) else "none failed")
        + ". Mean [95 % CI] (n) over seeds."
    )  # fmt: skip
    return "\n".join([head, "", *table(rows)]) + "\n"


def write_ablation_outputs(
    rows: list[dict], s: ex.ExplorationExperimentConfig, out: Path, wall_s: float | None = None
):
    """CSV/JSON of the runs, a table of intervals per weight, a plot of the three metrics, and
    the compact rows (`data/ablation.json`) the doc's table is generated from."""
    from .report import write_data

    out.mkdir(parents=True, exist_ok=True)
    summary = exr.summarise_exploration(rows)
    (out / "ablation_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "summary": summary}, indent=2)
    )
    meta = {"seeds": list(s.seeds), "size_m": s.size_m, "budget_s": s.budget_s, "jobs": s.jobs}
    meta.update({"extra": list(s.extra), "is_quick": s.is_quick})
    if wall_s is not None:
        meta["wall_s"] = round(wall_s, 1)
    compact = [{k: r.get(k) for k in DATA_KEYS} for r in rows]
    write_data(out, "ablation", compact, meta, "quick" if s.is_quick else None)
    failed = [r for r in rows if not r["ok"]]
    lines = ["# Path-cost weight ablation (NBV)", ""]
    if failed:
        lines += [
            f"**WARNING: {len(failed)} of {len(rows)} runs failed** (no metrics or non-zero "
            "exit), left out of every number below.",
            "",
        ]
    lines += [
        f"Seeds {list(s.seeds)}, garden {s.size_m} m, budget {s.budget_s:.0f} s per run, key "
        f"`{ex.WEIGHT_KEY}`. Mean [95 % CI] (n) over seeds.",
        "",
        *table(rows),
    ]
    weights = [d["path_cost_weight"] for d in summary]
    series = []
    for key, label, scale in (
        ("terrain_share", "terrain share", 1.0),
        ("coverage", "coverage", 1.0),
        ("distance_m", "distance / 100 m", 0.01),
    ):
        cis = [exr.interval_of(d[key]) for d in summary]
        err = None
        if all(c.defined for c in cis):
            err = ([scale * (c.mean - c.lo) for c in cis], [scale * (c.hi - c.mean) for c in cis])
        ys = [None if c.n == 0 else scale * c.mean for c in cis]
        series.append(paper_figures.Series(label, list(range(len(weights))), ys, err))
    ns = sorted({exr.interval_of(d["terrain_share"]).n for d in summary})
    path = paper_figures.save(
        paper_figures.line_plot(
            series,
            f"NBV path-cost weight ablation (grass x{summary[0]['grass_cost_factor']:g})",
            f"{ex.WEIGHT_KEY}",
            "share (terrain, coverage); distance / 100 m",
            {i: f"{w:g}" for i, w in enumerate(weights)},
            note=f"mean and 95 % CI, n = {'-'.join(map(str, ns))}",
        ),
        out / "ablation.png",
    )
    lines += ["", f"![ablation]({path.name})", ""]
    (out / "ablation_summary.md").write_text("\n".join(lines))


def _weights(text: str) -> tuple[float, ...]:
    """`--weights 0,0.5,2`: non-negative numbers (argparse turns the ValueError into one line)."""
    try:
        out = tuple(float(w) for w in text.split(",") if w.strip())
    except ValueError:
        raise ValueError(text) from None
    if not out or min(out) < 0:
        raise ValueError(text)
    return out


_weights.__name__ = "list of weights >= 0"  # what argparse names in its error


def add_parser(sub) -> None:
    """The `ablation` subcommand of `smana experiment`."""
    from smana.common.cli import positive_float

    e = sub.add_parser(
        "ablation",
        help="NBV terrain share, distance, coverage vs path-cost weight "
        "(measured once: about 10 min)",
        description="NBV at one grass cost factor for several explorer.path_cost_weight values.",
        epilog="Duration measured once on a 2-core machine: about 10 minutes with the defaults "
        "(3 weights x 3 "
        "seeds = 9 runs, 2 at once: measured 9 min 28 s); --quick about 2.5 minutes (2 weights "
        "x 2 seeds of 20 s). Exits 1 if any run failed.",
    )
    ex.add_common_args(
        e, quick_help="2 weights x 2 seeds of 20 s in a 6 m garden", seeds_help="default 3; quick 2"
    )
    e.add_argument(
        "--weights",
        type=_weights,
        help="comma-separated path-cost weights >= 0 (default 0,0.5,2)",
    )
    e.add_argument(
        "--grass", type=positive_float, default=4.0, help="grass cost factor (default 4)"
    )


check_args = ex.check_args


def main(args, parser, out: Path) -> int:
    if args.quick:
        s = ex.ExplorationExperimentConfig.quick()
        weights = args.weights or DEFAULT_WEIGHTS[1:]
    else:
        s = ex.ExplorationExperimentConfig(seeds=(3, 4, 5))
        weights = args.weights or DEFAULT_WEIGHTS
    s.arms = weight_arms(args.grass, weights)
    s = ex.apply_args(s, args)
    t0 = time.perf_counter()

    def write(rows, s, out):
        write_ablation_outputs(rows, s, out, wall_s=time.perf_counter() - t0)

    rows = ex.run_exploration(s, out, write=write)
    return ex.finish(rows, out, "ablation")
