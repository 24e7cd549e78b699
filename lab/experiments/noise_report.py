"""The claims and outputs of `smana experiment noise` (noise.py holds its design, its fixed
trajectory, its runs and its command line): the per-seed losses, the paper's claims (a), (b),
(c) and (c') decided over seeds, the figures and summary a run writes, and the tables of
docs/experiments.md."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from smana.lab import paper_figures, stats

from .noise import (
    BACKENDS,
    LABEL_LOSS_TOLERANCE,
    LEVELS,
    PAPER_LABEL_LOSS,
    POSE_NOISE,
    POSE_NOISE_WHY,
    backend_order,
)

# -- aggregation and claims -------------------------------------------------------------------


def _runs(rows, sweep, backend, level) -> list[dict]:
    """The runs (one per seed) of a (sweep, back-end, level); the pose sweep's "none" is the
    label sweep's "none"."""
    if sweep == "pose" and level == "none":
        sweep = "label"
    return [
        r for r in rows if r["sweep"] == sweep and r["backend"] == backend and r["level"] == level
    ]


def _levels(rows, sweep) -> list[str]:
    used = {r["level"] for r in rows if r["sweep"] == sweep}
    if sweep == "pose" and used:
        used |= {r["level"] for r in rows if r["sweep"] == "label" and r["level"] == "none"}
    return sorted(used, key=LEVELS.index)


def _per_seed(rows, sweep, backend, key) -> dict:
    """{seed: {level: value}} (rows without a seed count as one run, seed None)."""
    out: dict = {}
    for level in _levels(rows, sweep):
        for r in _runs(rows, sweep, backend, level):
            out.setdefault(r.get("seed"), {})[level] = r.get(key)  # older rows lack f_score
    return out


def aggregate(rows) -> list[dict]:
    """Mean and 95 % interval over seeds of each (back-end, sweep, level)."""
    out = []
    backends = sorted({r["backend"] for r in rows}, key=backend_order)
    for sweep in ("label", "pose"):
        for b in backends:
            for level in _levels(rows, sweep):
                runs = _runs(rows, sweep, b, level)
                row = {"backend": b, "sweep": sweep, "level": level}
                for key in ("error_mean_m", "classification_ratio"):
                    ci = stats.mean_ci([r[key] for r in runs])
                    row[key] = ci.as_dict()
                out.append(row)
    return out


def _deltas(rows, sweep, backend, key) -> dict:
    """Per seed: value at the highest level minus at the lowest, of the sweep's levels."""
    levels = _levels(rows, sweep)
    if len(levels) < 2:
        return {}
    lo, hi = levels[0], levels[-1]
    return {
        seed: v[hi] - v[lo]
        for seed, v in _per_seed(rows, sweep, backend, key).items()
        if v.get(lo) is not None and v.get(hi) is not None
    }


def label_losses(rows) -> dict[str, dict]:
    """Classification ratio lost from the lowest to the highest label noise level, per back-end,
    over seeds: in points of ratio (absolute, the one compared with the paper) and relative to
    the ratio at the lowest level."""
    out = {}
    levels = _levels(rows, "label")
    for b in sorted({r["backend"] for r in rows}, key=backend_order):
        per = _per_seed(rows, "label", b, "classification_ratio")
        if len(levels) < 2:
            continue
        lo, hi = levels[0], levels[-1]
        pairs = [(v[lo], v[hi]) for v in per.values() if lo in v and hi in v]
        out[b] = {
            "from": lo,
            "to": hi,
            "loss_abs": stats.mean_ci([a - z for a, z in pairs]).as_dict(),
            "loss_rel": stats.mean_ci([(a - z) / a for a, z in pairs if a]).as_dict(),
            "paper_loss": PAPER_LABEL_LOSS.get(b),
        }
    return out


def _ci(values) -> stats.Interval:
    return stats.mean_ci(list(values))


def claims(rows) -> list[dict]:
    """The paper's claims of section 4.2, each decided over seeds by a rule of lab/stats.py fixed
    before the runs (p-values uncorrected; docs/experiments.md corrects its table together):
    (a) each loss about the paper's (`decide_near`); (b) and (c), directions the paper gives
    without a size, on per-seed paired differences (`decide_above`). (c) is decided on the
    F-score, which counts what a map leaves out as well as where its points are: a map that
    drops uncertain surface is more accurate without being more robust; (c') is accuracy alone."""
    out = []

    def add(claim, paper, ci, scale, d: stats.Decision, rule, other=None):
        c = {
            "claim": claim,
            "paper": paper,
            "smana": ci,
            "scale": scale,
            "unit": "",
            **d.fields(),
            "rule": rule,
        }
        if other is not None:
            c["other"] = other
        out.append(c)

    loss = {b: _deltas(rows, "label", b, "classification_ratio") for b in ("tsdf", "octree-max")}
    loss = {b: {s: -d for s, d in v.items()} for b, v in loss.items()}  # a loss is a drop
    for b in ("tsdf", "octree-max"):
        ci = _ci(loss[b].values())
        paper = PAPER_LABEL_LOSS[b]
        add(
            f"(a) {b}: classification ratio lost from the lowest to the highest label noise "
            "(points), about the paper's",
            f"{100 * paper:.0f} +/- {100 * LABEL_LOSS_TOLERANCE:.0f}",
            ci,
            100.0,
            stats.decide_near(ci, paper, LABEL_LOSS_TOLERANCE),
            "about X",
        )

    def paired(per_b: dict, per_a: dict) -> stats.Interval:
        both = sorted(set(per_a) & set(per_b), key=str)
        return _ci(per_b[s] - per_a[s] for s in both)

    d = paired(loss["octree-max"], loss["tsdf"])
    add(
        "(b) tsdf loses less than octree-max to label noise: octree-max's loss minus tsdf's, "
        "paired per seed (points)",
        "30 - 11 > 0",
        d,
        100.0,
        stats.decide_above(d),
        "above 0",
    )
    f_lost = {b: _deltas(rows, "pose", b, "f_score") for b in ("tsdf", "octree-max")}
    f_lost = {b: {s: -x for s, x in v.items() if x is not None} for b, v in f_lost.items()}
    d = paired(f_lost["octree-max"], f_lost["tsdf"])
    add(
        "(c) tsdf more robust to localisation noise: F-score (5 cm) lost to the highest pose "
        "noise, octree-max's minus tsdf's, paired per seed (points)",
        "tsdf more robust",
        d,
        100.0,
        stats.decide_above(d),
        "above 0",
    )
    added = {b: _deltas(rows, "pose", b, "error_mean_m") for b in ("tsdf", "octree-max")}
    d = paired(added["octree-max"], added["tsdf"])
    add(
        "(c') the same on accuracy alone: reconstruction error added by the highest pose noise, "
        "octree-max's minus tsdf's, paired per seed (mm)",
        "> 0",
        d,
        1000.0,
        stats.decide_above(d),
        "above 0",
    )
    return out


def _claim_json(c: dict) -> dict:
    d = {k: v for k, v in c.items() if k not in ("smana", "other", "scale", "unit")}
    d["smana"] = c["smana"].as_dict()
    if "other" in c:
        d["other"] = c["other"].as_dict()
    return d


def write_noise_outputs(rows: list[dict], meta: dict, out: Path) -> None:
    """noise_results.csv/json (per-seed rows, aggregates, claims), Figures 6 and 7 with 95 %
    intervals over seeds, and noise_summary.md opening with the verdict table."""
    out.mkdir(parents=True, exist_ok=True)
    flat = [{k: v for k, v in r.items() if k != "per_class_ratio"} for r in rows]
    fields = list(flat[0]) if flat else ["seed", "backend", "sweep", "level"]
    with open(out / "noise_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(flat)
    from .report import write_data

    run = {k: meta[k] for k in ("jobs", "wall_s", "failures") if k in meta}
    write_data(out, "noise", rows, {**(meta.get("settings") or {}), **run})
    agg = aggregate(rows)
    decided = claims(rows)
    losses = label_losses(rows)
    (out / "noise_results.json").write_text(
        json.dumps(
            {
                "meta": meta,
                "rows": rows,
                "aggregate": agg,
                "label_loss": losses,
                "claims": [_claim_json(c) for c in decided],
            },
            indent=2,
        )
    )
    if rows:
        _noise_figures(rows, agg, out)
    _noise_summary(rows, agg, decided, meta, out)


def _noise_figures(rows, agg, out: Path) -> None:
    backends = sorted({r["backend"] for r in rows}, key=backend_order)
    ns = {a[k]["n"] for a in agg for k in ("error_mean_m", "classification_ratio")}
    n_txt = f"n = {min(ns)}" if len(ns) == 1 else f"n = {min(ns)} to {max(ns)}"
    note = (
        f"mean over seeds, bars: 95 % t-interval ({n_txt} seeds)"
        if max(ns) >= 2
        else f"{n_txt} run per level and back-end: no interval"
    )

    def series(sweep, key):
        out_s = []
        for b in backends:
            sel = [a for a in agg if a["sweep"] == sweep and a["backend"] == b]
            y = [a[key]["mean"] for a in sel]
            lo = [a[key]["ci_lo"] for a in sel]
            hi = [a[key]["ci_hi"] for a in sel]
            err = None
            if all(v is not None for v in lo + hi):
                err = ([m - v for m, v in zip(y, lo)], [v - m for m, v in zip(y, hi)])
            out_s.append(paper_figures.Series(b, [LEVELS.index(a["level"]) for a in sel], y, err))
        return out_s

    def ticks(sweep):
        return {LEVELS.index(lv): lv for lv in _levels(rows, sweep)}

    figures = (
        ("pose", "error_mean_m", "fig6_pose_noise_error.png", "Reconstruction error",
         "localisation noise level", "reconstruction error (m)"),
        ("pose", "classification_ratio", "fig6_pose_noise_ratio.png", "Classification ratio",
         "localisation noise level", "classification ratio (share of map points labelled right)"),
        ("label", "classification_ratio", "fig7_label_noise_ratio.png", "Classification ratio",
         "label noise level (p = 1, .9, .8, .7)",
         "classification ratio (share of map points labelled right)"),
    )  # fmt: skip
    for sweep, key, name, what, xlabel, ylabel in figures:
        fig_no = "Fig. 6" if sweep == "pose" else "Fig. 7"
        kind = "localisation" if sweep == "pose" else "label"
        paper_figures.save(
            paper_figures.line_plot(
                series(sweep, key),
                f"{what} vs {kind} noise ({fig_no})",
                xlabel,
                ylabel,
                ticks(sweep),
                note=note,
            ),
            out / name,
        )


def _noise_summary(rows, agg, decided, meta, out: Path) -> None:
    st = meta["settings"]
    lines = ["# Noise experiment (paper Figures 6 and 7)", ""]
    failures = meta.get("failures") or {}
    if failures:
        lines += [
            f"> **WARNING: {len(failures)} of {len(st['seeds'])} seeds failed** and are left "
            "out of every number below:",
        ]
        lines += [f"> - seed {s}: {msg}" for s, msg in failures.items()]
        lines.append("")
    if st.get("is_quick"):
        lines += [
            f"> **Quick run**: {len(st['seeds'])} seed{'s' * (len(st['seeds']) != 1)}, a few "
            "small frames, 10 cm voxels. It checks that the "
            "experiment works; its verdicts say nothing about the paper (the full run: "
            "`smana experiment noise`, docs/experiments.md).",
            "",
        ]
    lines += [
        "| claim | paper | smana mean [95 % CI] (n) | verdict |",
        "|---|---|---|---|",
    ]
    for c in decided:
        txt = c["smana"].format(c["scale"], ".1f", c["unit"])
        if "other" in c:
            txt += " vs " + c["other"].format(c["scale"], ".1f", c["unit"])
        lines.append(f"| {c['claim']} | {c['paper']} | {txt} | {c['verdict']} |")
    lines += [
        "",
        "Verdicts by lab/stats.py over seeds (Student-t 95 % intervals, rules in "
        "docs/experiments.md: (a) about X, (b) (c) (c') paired per seed above 0; p-values "
        "uncorrected here, Holm-corrected in the docs' table): a claim is reproduced "
        "only when its interval says so; with fewer than 2 seeds it is inconclusive. The paper's "
        '"11 % / 30 % loss" is read as points of classification ratio (its Figure 7 plots the '
        "ratio in %); the relative loss is in the table below.",
        "",
    ]
    seeds_meta = meta.get("seeds") or []
    frames = sorted({m["frames"] for m in seeds_meta})
    length = [m["trajectory_length_m"] for m in seeds_meta]
    lines += [
        f"Seeds {', '.join(str(s) for s in st['seeds'])} (world and trajectory start; the first "
        f"starts at the spawn), garden overrides {st.get('world') or '{}'}; fixed trajectory of "
        + (f"{min(length):.1f} to {max(length):.1f} m, " if length else "")
        + f"{'/'.join(str(f) for f in frames)} frames of {st['image_px']} px integrated every "
        f"{st['pixel_stride']} pixel(s), map resolution {st['resolution_m']} m; "
        f"{meta.get('jobs', 1)} jobs, {meta.get('wall_s', 0):.0f} s wall.",
        "Localisation noise levels (sigma x/y m, sigma yaw rad, drawn afresh per frame): "
        + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in POSE_NOISE.items())
        + ". "
        + POSE_NOISE_WHY,
        "",
    ]
    if seeds_meta:
        keys = list(seeds_meta[0]["cpu_s"])
        lines += ["CPU time per seed (s, process_time in the worker):", ""]
        lines += ["| seed | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
        for m in seeds_meta:
            lines.append(
                f"| {m['seed']} | " + " | ".join(f"{m['cpu_s'][k]:.1f}" for k in keys) + " |"
            )
        lines.append("")
    lines += [
        "## Mean over seeds [95 % CI]",
        "",
        "| sweep | level | back-end | error mean (mm) | classification ratio (%) |",
        "|---|---|---|---|---|",
    ]
    for a in agg:
        e = stats.Interval(**_iv(a["error_mean_m"]))
        r = stats.Interval(**_iv(a["classification_ratio"]))
        lines.append(
            f"| {a['sweep']} | {a['level']} | {a['backend']} | {e.format(1000, '.1f')} | "
            f"{r.format(100, '.1f')} |"
        )
    lines += [
        "",
        "## Classification loss from the lowest to the highest label noise",
        "",
        "| back-end | loss (points) | loss (relative, %) | paper |",
        "|---|---|---|---|",
    ]
    for b, d in label_losses(rows).items():
        paper = f"{100 * d['paper_loss']:.0f}" if d["paper_loss"] is not None else "-"
        la = stats.Interval(**_iv(d["loss_abs"]))
        lr = stats.Interval(**_iv(d["loss_rel"]))
        lines.append(f"| {b} | {la.format(100, '.1f')} | {lr.format(100, '.1f')} | {paper} |")
    lines += [
        "",
        "![fig6 error](fig6_pose_noise_error.png)",
        "![fig6 ratio](fig6_pose_noise_ratio.png)",
        "![fig7](fig7_label_noise_ratio.png)",
        "",
    ]
    (out / "noise_summary.md").write_text("\n".join(lines))


# -- the tables of docs/experiments.md ------------------------------------------------------------

# what a section's tables show per map: (row key, column, scale, unit, format)
SECTION_METRICS = (
    ("error_mean_m", "error (mm)", 1000.0, "", ".1f"),
    ("precision", "precision (5 cm)", 100.0, " %", ".1f"),
    ("completeness", "completeness (5 cm)", 100.0, " %", ".1f"),
    ("f_score", "F-score (5 cm)", 100.0, " %", ".1f"),
    ("classification_ratio", "classification ratio", 100.0, " %", ".1f"),
)


def _section_head(data: dict, key: str) -> str:
    from .report import duration

    meta, rows = data.get("meta") or {}, data["rows"]
    seeds = sorted({r["seed"] for r in rows})
    commands = [meta["command"]] if meta.get("command") else list(meta.get("commands") or [])
    made = " and ".join(f"`{c}`" for c in commands) or "a command it does not record"
    done = []
    if meta.get("wall_s") is not None:
        jobs = f" with {meta['jobs']} job{'s' * (meta['jobs'] != 1)}" if meta.get("jobs") else ""
        done.append(f"{duration(meta['wall_s'])} wall{jobs}")
    if meta.get("date"):
        done.append(meta["date"])
    backends = sorted({r["backend"] for r in rows}, key=backend_order)
    absent = [b for b in BACKENDS if b not in backends]
    failures = meta.get("failures") or {}
    return (
        f"Generated from docs/experiments/data/{key}.json, made by {made}"
        + (f" ({', '.join(done)})" if done else "")
        + f": seeds {', '.join(map(str, seeds))}"
        + (f" (**seed(s) {', '.join(failures)} failed**, left out)" if failures else "")
        + f"; back-ends {', '.join(backends)}"
        + (f" ({', '.join(absent)} not run: not in this data)" if absent else "")
        + (f"; {meta['note']}" if meta.get("note") else "")
        + ". Mean [95 % CI] (n) over seeds"
        + ('; the pose sweep\'s "none" maps are the label sweep\'s (no noise at all).'
           if any(r["sweep"] == "pose" for r in rows) else ".")
    )  # fmt: skip


def _sweeps_shown(rows) -> list[str]:
    """The sweeps a section shows: the pose sweep when it ran; the label sweep when it has a
    level above "none" or is all there is (a pose sweep alone maps "none" once, as a label row,
    which its own table shows)."""
    label = _levels(rows, "label")
    pose = [lv for lv in _levels(rows, "pose") if lv != "none"]
    out = ["label"] if (len(label) > 1 or not pose) and label else []
    return out + (["pose"] if pose else [])


def section(data: dict | None, key: str = "noise") -> str:
    """docs/experiments.md's tables of one noise data file (`noise.json`, `noise_<variant>.json`):
    per sweep, per back-end and level, the mean [95 % CI] over seeds of each of SECTION_METRICS;
    then, where the sweep has two levels or more, per back-end the change from its lowest level
    to its highest, paired per seed: the error added, the shares lost (in points)."""
    if data is None:
        return (
            f"_No raw results are committed in docs/experiments/data/{key}.json: nothing is "
            "generated here._\n"
        )
    rows = data["rows"]
    lines = [_section_head(data, key), ""]
    for sweep in _sweeps_shown(rows):
        levels = _levels(rows, sweep)
        # the back-ends this sweep ran (a pose sweep's "none" rows are the label sweep's)
        ran = {r["backend"] for r in rows if r["sweep"] == sweep and r["level"] != "none"}
        backends = sorted(ran or {r["backend"] for r in rows}, key=backend_order)
        kind = "localisation (pose)" if sweep == "pose" else "label"
        lines += [
            f"{kind.capitalize()} noise sweep, levels {', '.join(levels)}:",
            "",
            "| back-end | level | " + " | ".join(m[1] for m in SECTION_METRICS) + " |",
            "|---|---|" + "---|" * len(SECTION_METRICS),
        ]
        for b in backends:
            for level in levels:
                runs = _runs(rows, sweep, b, level)
                if not runs:
                    continue
                cells = [
                    stats.mean_ci([r.get(k) for r in runs]).format(scale, fmt, unit)
                    for k, _, scale, unit, fmt in SECTION_METRICS
                ]
                lines.append(f"| {b} | {level} | " + " | ".join(cells) + " |")
        lines.append("")
        if len(levels) < 2:
            continue
        lines += _paired_table(rows, sweep, kind, levels[0], levels[-1], backends)
    return "\n".join(lines)


def _paired_table(rows, sweep, kind, lo, hi, backends) -> list[str]:
    """Per back-end, each metric's change from `lo` to `hi` paired per seed: the error added,
    the shares lost (points). A metric that no seed of any back-end changed is left out, said
    so (label noise moves no point: the geometry is the same at every label level)."""
    deltas = {}
    for k, *_ in SECTION_METRICS:
        sign = 1.0 if k == "error_mean_m" else -1.0  # error added; shares lost
        deltas[k] = {b: [sign * v for v in _deltas(rows, sweep, b, k).values()] for b in backends}
    values = {k: [v for d in deltas[k].values() for v in d] for k in deltas}
    same = [m for m in SECTION_METRICS if values[m[0]] and not any(values[m[0]])]
    moved = [m for m in SECTION_METRICS if m not in same]  # with no value at all: "-" is said
    same = [m[1].split(" (")[0] for m in same]
    lines = [
        f"From {kind} noise {lo} to {hi}, paired per seed ({hi} minus {lo} for the error, "
        f"{lo} minus {hi} for the shares, in points)"
        + (f"; unchanged in every seed, left out: {', '.join(same)}" if same else "")
        + ":",
        "",
    ]
    if not moved:
        return lines
    lines += [
        "| back-end | "
        + " | ".join(
            f"error added by {hi} (mm)" if k == "error_mean_m" else f"{col} lost to {hi}"
            for k, col, *_ in moved
        )
        + " |",
        "|---|" + "---|" * len(moved),
    ]
    for b in backends:
        cells = [_ci(deltas[k][b]).format(scale, fmt) for k, _, scale, _u, fmt in moved]
        if any(c != "- (n = 0)" for c in cells):
            lines.append(f"| {b} | " + " | ".join(cells) + " |")
    return lines + [""]


def _iv(d: dict) -> dict:
    """An `Interval.as_dict()` back into `Interval`'s fields (None for no bound: NaN)."""
    return {
        "mean": d["mean"] if d["mean"] is not None else math.nan,
        "lo": d["ci_lo"] if d["ci_lo"] is not None else math.nan,
        "hi": d["ci_hi"] if d["ci_hi"] is not None else math.nan,
        "n": d["n"],
        "confidence": d["confidence"],
    }
