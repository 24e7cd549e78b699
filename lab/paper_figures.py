"""Every figure smana writes: the product's (common/plotting.py, re-exported here) and the
research harness's own, drawn with matplotlib off-screen (Agg).

The product's figures (a run's plots, `smana world preview`) and the rules they follow (units,
metres, class colours from the table, `save` refusing a figure without a legend) live in
`smana.common.plotting`; this module adds what only the lab draws:
- `bar_plot(groups, series, values, errors, ...)`: grouped bars (`figure_11`, `figure_12`);
- `figure_11(rows, path)`, `figure_12(rows, path)`: the replay benchmark's Figures 11 and 12;
- `band_plot(curves, ...)`: mean curves with an interval band (the experiments' summaries);
- `risk_map_figure(case, ...)`: a synthetic wet garden coloured by risk (docs/risk.md).

matplotlib is imported inside the functions, never at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from smana.common.plotting import (  # noqa: F401 - the lab's figures and its callers use these
    LINESTYLES,
    MARKERS,
    MEMBER_COLOURS,
    OVERLAY,
    PlotError,
    Series,
    class_handles,
    class_rgb,
    draw_lines,
    graph_map,
    halo,
    has_legend,
    line_plot,
    map_figure,
    new_figure,
    progress_plot,
    rgb01,
    save,
    world_map,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def bar_plot(
    ax: Axes,
    groups: list[str],
    series: list[str],
    values,
    errors,
    title: str,
    ylabel: str,
    log: bool = False,
    error_label: str | None = None,
) -> None:
    """Grouped bars on `ax`; values/errors [n_series][n_groups], NaN bars left out, hatches tell
    the series apart in grey print too."""
    vals = np.asarray(values, float)
    errs = np.nan_to_num(np.asarray(errors, float))
    n_s = len(series)
    width = 0.8 / max(n_s, 1)
    x = np.arange(len(groups))
    hatches = ("", "//", "..", "xx")
    for s, name in enumerate(series):
        ok = np.isfinite(vals[s])
        e = np.where(errs[s] > 0, errs[s], 0.0)[ok]
        ax.bar(
            x[ok] + (s - (n_s - 1) / 2) * width,
            vals[s][ok],
            width * 0.95,
            yerr=e if np.any(e > 0) else None,
            capsize=3,
            label=name,
            hatch=hatches[s % len(hatches)],
            edgecolor="black",
            linewidth=0.5,
        )
    if log:
        ax.set_yscale("log")
    ax.set_xticks(x, groups, fontsize="small")
    ax.set_title(title)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title=error_label, title_fontsize="small", fontsize="small")


def _bench_groups(rows: list[dict]) -> list[str]:
    return [f"{r['backend']}\n{r['map_res']:g} / {r['graph_res']:g} m" for r in rows]


def _bench_note(rows: list[dict]) -> str:
    n = sorted({int(r.get("repeats", 1)) for r in rows})
    runs = f"n = {n[0]} run" + ("s" if n[0] != 1 else "") if len(n) == 1 else f"n = {n} runs"
    return f"error bars: std over samples\n(median over {runs})"


def figure_11(rows: list[dict], path: str | Path) -> Path:
    """Paper Figure 11: average CPU use with std (log scale) and peak RAM of the map and graph
    processes, per back-end and resolution pair (map / graph)."""
    fig = new_figure(max(7.5, 1.2 * len(rows) + 2.0), 8.0)
    top, bottom = fig.subplots(2, 1)
    g = _bench_groups(rows)
    bar_plot(
        top,
        g,
        ["map process", "graph process"],
        [[r["cpu_map"] for r in rows], [r["cpu_graph"] for r in rows]],
        [[r["cpu_map_std"] for r in rows], [r["cpu_graph_std"] for r in rows]],
        "Average CPU use (Fig. 11)",
        "CPU (%, 100 % = one core, log scale)",
        log=True,
        error_label=_bench_note(rows),
    )
    bar_plot(
        bottom,
        g,
        ["map process", "graph process"],
        [[r["rss_map_mb"] for r in rows], [r["rss_graph_mb"] for r in rows]],
        [[0] * len(rows), [0] * len(rows)],
        "Peak RAM (resident set size)",
        "peak RSS (MB)",
        error_label="median over runs, no spread drawn",
    )
    bottom.set_xlabel("back-end, map / graph resolution")
    return save(fig, path)


def figure_12(rows: list[dict], path: str | Path) -> Path:
    """Paper Figure 12: integration time per point with std, map and graph, log scale."""
    fig = new_figure(max(7.5, 1.2 * len(rows) + 2.0), 4.8)
    ax = fig.add_subplot()
    bar_plot(
        ax,
        _bench_groups(rows),
        ["map (mapper integration)", "graph (navgraph update)"],
        [[r["map_us_pt"] for r in rows], [r["graph_us_pt"] for r in rows]],
        [[r["map_us_pt_std"] for r in rows], [r["graph_us_pt_std"] for r in rows]],
        "Average integration time per point (Fig. 12)",
        "time per point (µs, log scale)",
        log=True,
        error_label=_bench_note(rows),
    )
    ax.set_xlabel("back-end, map / graph resolution")
    return save(fig, path)


def band_plot(
    curves: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    title: str,
    xlabel: str,
    ylabel: str,
    note: str | None = None,
    hline: float | None = None,
    clip: tuple[float, float] | None = None,
) -> Figure:
    """Mean curves with a shaded interval band: each curve is (label, x, mean, lo, hi); NaN in
    lo/hi (fewer than two runs there) leaves the band out at those x. `hline` marks a target
    (95 % coverage). `clip`: the range a value can take (a share: (0, 1)); the band is cut to it,
    and the legend's note says so."""
    fig = new_figure()
    ax = fig.add_subplot()
    if clip is not None and note is not None:
        note = f"{note}, cut to [{clip[0]:g}, {clip[1]:g}]"
    for k, (label, x, mean, lo, hi) in enumerate(curves):
        if clip is not None:
            lo, hi = np.clip(lo, *clip), np.clip(hi, *clip)
        (line,) = ax.plot(x, mean, label=label, linestyle=LINESTYLES[k % len(LINESTYLES)])
        ok = np.isfinite(lo) & np.isfinite(hi)
        ax.fill_between(x, lo, hi, where=ok, color=line.get_color(), alpha=0.2, linewidth=0)
    if hline is not None:
        ax.axhline(hline, color="grey", linestyle=":", linewidth=1)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(title=note, title_fontsize="small", fontsize="small")
    return fig


def save_palette(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """`save`, then a PNG's colours cut to a 256-colour palette: a map of noisy rasters (one
    colour per node, antialiased edges) is three times smaller so, for a figure kept in the
    repository (docs/risk_map.png)."""
    from PIL import Image

    path = save(fig, path, dpi=dpi)
    if path.suffix.lower() == ".png":
        with Image.open(path) as im:
            small = im.convert("RGB").quantize(256)
        small.save(path, optimize=True)
    return path


def risk_map_figure(case: dict, seed: int, resolution_m: float) -> Figure:
    """`smana experiment risk --synthetic --figure` (docs/risk.md): one seed's synthetic wet
    garden and its map at p = 0.7 (`lab/experiments/risk.py`, `figure_case`) in six panels: the
    true classes, the map's most likely class, P(forbidden) as `chance` counts it, and the node
    cost T under `expected`, `cvar` and `chance` (common/risk.py, as the planner prices a node)
    on one log colour scale, each arm's path between the same start and goal drawn over its
    panel with its true water entries (`judge`) in the title. The true water is outlined on
    every panel."""
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE
    from smana.common.risk import forbidden_probability, risk_class_costs

    w, labels, configs = case["world"], case["labels"], case["configs"]
    alt, p_label, p_alt = case["risk"]
    classes, truth, flags = w.classes, w.truth, w.flags
    water = classes[w.forbidden].name
    n = truth.shape[0]
    extent = (0.0, n * resolution_m, 0.0, truth.shape[1] * resolution_m)
    blocked = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0
    obstacle = (flags & FLAG_OBSTACLE) != 0
    lut = classes.cost_lut
    closed_label = ~np.isfinite(lut[np.minimum(labels, classes.size - 1)]) & ~blocked
    closed_rgb = {
        "obstacle": OVERLAY["obstacle"],
        "safety zone": OVERLAY["safety zone"],
        "chance": (1.0, 0.0, 0.8),
        "label": rgb01(classes[w.forbidden].colour),
    }

    fig = new_figure(15.0, 10.5)
    axes = fig.subplots(2, 3).ravel()

    def show(ax, img, **kw):
        return ax.imshow(
            np.swapaxes(img, 0, 1), origin="lower", extent=extent, interpolation="nearest", **kw
        )

    def paint(ax, mask, colour):
        rgba = np.zeros((*mask.shape, 4))
        rgba[mask] = (*colour, 1.0)
        show(ax, rgba)

    def path_title(arm):
        res, score = case["paths"][arm]
        if not res.ok:
            return "none found"
        k = score["forbidden"]
        return f"{k} {water} entr{'y' if k == 1 else 'ies'}, {score['length_m']:.1f} m"

    start_goal = w.pairs[case["pair"]]
    xs = (np.arange(n) + 0.5) * resolution_m

    def overlay(ax, arm=None):
        wet = (truth == w.forbidden).T.astype(float)
        ax.contour(xs, xs, wet, levels=[0.5], colors=[OVERLAY["frontier"]], linewidths=1.4)
        if arm is not None:
            ax.set_label(arm)  # which arm's path the panel draws (tests read its title)
        if arm is not None and case["paths"][arm][0].ok:
            xy = case["paths"][arm][0].path
            (line,) = ax.plot(xy[:, 0], xy[:, 1], color=OVERLAY["trajectory"], linewidth=1.8)
            line.set_path_effects(halo())
        (a, b) = start_goal
        ax.plot(*a, "o", markersize=8, color="white", markeredgecolor="black")
        ax.plot(*b, "*", markersize=12, color="white", markeredgecolor="black")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")

    # 1, 2: classes
    show(axes[0], class_rgb(classes, truth))
    axes[0].set_title(
        f"Ground truth: classes ({water}: forbidden)\npath on the truth: {path_title('truth')}"
    )
    overlay(axes[0], "truth")
    show(axes[1], class_rgb(classes, labels))
    axes[1].set_title(
        "Map at p = 0.7: most likely class\n"
        f"path on its labels alone (argmax): {path_title('argmax')}"
    )
    overlay(axes[1], "argmax")
    # 3: P(forbidden)
    chance = configs["chance"]
    pf = forbidden_probability(labels, alt, p_label, p_alt, lut, chance)
    im_p = show(axes[2], np.where(blocked, np.nan, pf), cmap="Greys", norm=Normalize(0.0, 1.0))
    paint(axes[2], obstacle, closed_rgb["obstacle"])
    paint(axes[2], blocked & ~obstacle, closed_rgb["safety zone"])
    axes[2].set_title(
        f"P(forbidden) per node as chance counts it\n({water} + unnamed mass x "
        f"{chance.risk_other_forbidden:g}; chance closes > {chance.max_risk:g})"
    )
    overlay(axes[2])
    fig.colorbar(im_p, ax=axes[2], shrink=0.8, label="P(forbidden)")
    # 4-6: node costs, one scale
    norm = LogNorm(1.0, chance.risk_forbidden_cost)
    names = {
        "expected": "expected: sum of P(k) T(k)",
        "cvar": f"cvar: CVaR at alpha {configs['cvar'].risk_alpha:g}",
        "chance": f"chance: expected, closed if P(forbidden) > {chance.max_risk:g}",
    }
    for ax, arm in zip(axes[3:], ("expected", "cvar", "chance"), strict=True):
        t = risk_class_costs(labels, alt, p_label, p_alt, lut, configs[arm])
        im = show(ax, np.where(np.isfinite(t) & ~blocked, t, np.nan), cmap="Greys", norm=norm)
        paint(ax, obstacle, closed_rgb["obstacle"])
        paint(ax, blocked & ~obstacle, closed_rgb["safety zone"])
        paint(ax, closed_label, closed_rgb["label"])
        paint(ax, ~np.isfinite(t) & ~blocked & ~closed_label, closed_rgb["chance"])
        ax.set_title(f"Node cost T under {names[arm]}\npath: {path_title(arm)}")
        overlay(ax, arm)
    ticks = [v for v in (1, 2, 5, 10, 20, 50, 100) if v <= chance.risk_forbidden_cost]
    bar = fig.colorbar(im, ax=list(axes[3:]), shrink=0.8, ticks=ticks)
    bar.set_label("node cost T before t_f (log scale)")
    bar.ax.set_yticklabels([f"{v:g}" for v in ticks])
    handles = [
        *class_handles(classes, np.unique(truth)),
        Line2D([], [], color=OVERLAY["frontier"], label=f"true {water} (outline)"),
        Patch(facecolor=closed_rgb["obstacle"], label="obstacle (never entered)"),
        Patch(facecolor=closed_rgb["safety zone"], label="safety zone (never entered)"),
        Patch(facecolor=closed_rgb["label"], label=f"most likely {water}: closed in every mode"),
        Patch(facecolor=closed_rgb["chance"], label="closed by chance"),
        Line2D([], [], color=OVERLAY["trajectory"], linewidth=1.8, label="planned path"),
        Line2D([], [], marker="o", color="white", markeredgecolor="black", linestyle="none",
               label="start"),
        Line2D([], [], marker="*", markersize=12, color="white", markeredgecolor="black",
               linestyle="none", label="goal"),
    ]  # fmt: skip
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize="small")
    fig.suptitle(
        f"Risk-aware planning on one synthetic wet garden (seed {seed}, label noise p = 0.7): "
        f"one start and goal, the one of the seed's {len(w.pairs)} pairs that the labels alone "
        "plan into water most often"
    )
    return fig
