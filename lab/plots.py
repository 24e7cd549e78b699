"""Every figure smana writes: the product's (common/figures.py, re-exported here) and the
research harness's own, drawn with matplotlib off-screen (Agg).

The product's figures (a run's plots, `smana world preview`) and the rules they follow (units,
metres, class colours from the table, `save` refusing a figure without a legend) live in
`smana.common.figures`; this module adds what only the lab draws:
- `bar_plot(groups, series, values, errors, ...)`: grouped bars (`figure_11`, `figure_12`);
- `figure_11(rows, path)`, `figure_12(rows, path)`: the replay benchmark's Figures 11 and 12;
- `band_plot(curves, ...)`: mean curves with an interval band (the experiments' summaries).

matplotlib is imported inside the functions, never at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from smana.common.figures import (  # noqa: F401 - the lab's figures and its callers use these
    LINESTYLES,
    MARKERS,
    MEMBER_COLOURS,
    OVERLAY,
    PlotError,
    Series,
    _figure,
    class_handles,
    class_rgb,
    draw_lines,
    graph_map,
    has_legend,
    line_plot,
    map_figure,
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
    fig = _figure(max(7.5, 1.2 * len(rows) + 2.0), 8.0)
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
    fig = _figure(max(7.5, 1.2 * len(rows) + 2.0), 4.8)
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
    fig = _figure()
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
