"""`smana experiment ablation`: NBV at one grass cost factor (x4 by default) for several path-cost
weights (`explorer.path_cost_weight`), over seeds: terrain share, distance and coverage per weight,
each with its 95 % interval, and a plot. It reuses the exploration runner (same worlds, starts,
parallel runs, failure accounting).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from smana.lab import plots

from . import exploration as ex

DEFAULT_WEIGHTS = (0.0, 0.5, 2.0)  # docs/experiments.md; 2 is the default weight


def weight_arms(factor: float, weights) -> tuple[ex.Arm, ...]:
    return tuple(
        ex.Arm(f"nbv_x{factor:g}_w{w:g}", factor, path_cost_weight=float(w)) for w in weights
    )


def write_ablation_outputs(rows: list[dict], s: ex.ExplorationExperimentConfig, out: Path):
    """CSV/JSON of the runs, a table of intervals per weight and a plot of the three metrics."""
    out.mkdir(parents=True, exist_ok=True)
    summary = ex.summarise_exploration(rows)
    (out / "ablation_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "summary": summary}, indent=2)
    )
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
        "| weight | grass | runs (failed) | terrain share | distance (m) | coverage | "
        "reached 95 % |",
        "|---|---|---|---|---|---|---|",
    ]
    for d in summary:
        iv = {k: ex._interval(d[k]) for k in ("terrain_share", "distance_m", "coverage")}
        lines.append(
            f"| {d['path_cost_weight']:g} | x{d['grass_cost_factor']:g} | {d['runs']} "
            f"({d['failed']}) | {iv['terrain_share'].format(100, unit=' %')} | "
            f"{iv['distance_m'].format()} | {iv['coverage'].format(100, unit=' %')} | "
            f"{d['reached_95']} |"
        )
    weights = [d["path_cost_weight"] for d in summary]
    series = []
    for key, label, scale in (
        ("terrain_share", "terrain share", 1.0),
        ("coverage", "coverage", 1.0),
        ("distance_m", "distance / 100 m", 0.01),
    ):
        cis = [ex._interval(d[key]) for d in summary]
        err = None
        if all(c.defined for c in cis):
            err = ([scale * (c.mean - c.lo) for c in cis], [scale * (c.hi - c.mean) for c in cis])
        ys = [None if c.n == 0 else scale * c.mean for c in cis]
        series.append(plots.Series(label, list(range(len(weights))), ys, err))
    ns = sorted({ex._interval(d["terrain_share"]).n for d in summary})
    path = plots.save(
        plots.line_plot(
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
    rows = ex.run_exploration(s, out, write=write_ablation_outputs)
    return ex.finish(rows, out, "ablation")
