"""The figures the product writes, drawn with matplotlib off-screen (Agg): a run's plots
(`smana up`, `smana replay`: world_trajectory.png, graph.png, progress.png, replay_latency.png and a
fleet's) and `smana world preview`. lab/paper_figures.py adds the paper's figures on top of this
module.

The rules a reviewer checks are kept here, once: axes carry units, maps are drawn in metres with
equal aspect and a scale bar, class colours and names come from the `ClassTable` itself, series
differ by marker and line style (so equal values stay visible), and `save` refuses a figure
without a legend.

matplotlib is imported inside the functions, never at import time, so `smana --help` and the
services stay fast. Figures are `matplotlib.figure.Figure` objects (no pyplot state machine), so
nothing leaks between calls or threads.

Figure functions:
- `line_plot(series, ...)`: series over numeric or named x positions, with error bars;
- `map_figure(...)`: a class raster seen from above with trajectory, start, goals and overlays
  (`world_map`: world_trajectory.png, `smana world preview`; `graph_map`: graph.png);
- `progress_plot(...)`: the explorer's explored area and distance over robot time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from smana.common.classes import MEMBER_COLOURS as MEMBER_RGB

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from smana.common.classes import ClassTable

MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
LINESTYLES = ("-", "--", ":", "-.")
# Colours of what a map overlays on the classes: picked away from every garden3drms class colour.
OVERLAY = {
    "unknown": (0.82, 0.82, 0.82),
    "obstacle": (0.85, 0.0, 0.0),
    "safety zone": (1.0, 0.55, 0.0),
    "doubtful": (0.55, 0.35, 0.75),
    "frontier": (0.0, 0.85, 1.0),
    "trajectory": (1.0, 0.9, 0.0),
    "start": (1.0, 1.0, 1.0),
    "goals": (1.0, 0.0, 0.8),
}
# Each fleet member's trajectory in its colour of the recording (common/classes.py).
MEMBER_COLOURS = tuple(tuple(c / 255 for c in rgb) for rgb in MEMBER_RGB)


class PlotError(ValueError):
    """A figure breaks one of the module's rules (e.g. it has no legend)."""


@dataclass
class Series:
    """One line of a `line_plot`. `yerr`: symmetric errors, or a (lower, upper) pair of lists of
    distances below and above y (e.g. mean to min and max)."""

    label: str
    x: list[float]
    y: list[float | None]
    yerr: list[float] | tuple[list[float], list[float]] | None = None
    dashed: bool = False
    colour: tuple[int, int, int] | None = None
    extra: dict = field(default_factory=dict)


def new_figure(width_in: float = 7.2, height_in: float = 4.6) -> Figure:
    """An empty off-screen (Agg) figure of the given size in inches, no pyplot state."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def has_legend(fig: Figure) -> bool:
    return bool(fig.legends) or any(ax.get_legend() is not None for ax in fig.axes)


def save(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write `fig` as an image (PNG unless the suffix says otherwise); refuses a legendless one."""
    path = Path(path)
    if not has_legend(fig):
        title = fig.axes[0].get_title() if fig.axes else ""
        raise PlotError(f"refusing to write {path.name}: figure {title!r} has no legend")
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = path.suffix.lstrip(".").lower() or "png"
    if fmt not in fig.canvas.get_supported_filetypes():
        raise PlotError(f"cannot write {path}: {fmt!r} is not an image type (use .png)")
    fig.savefig(path, dpi=dpi, format=fmt)
    return path


def rgb01(colour) -> tuple[float, float, float]:
    """A 0..255 RGB triple (the class table's colours) as matplotlib's 0..1 floats."""
    return tuple(float(c) / 255.0 for c in colour)


# -- lines ---------------------------------------------------------------------------------------


def _dodge(series: list[Series]) -> float:
    """Horizontal shift between series: a 25th of the smallest x step, so error bars and markers
    of series with equal values sit side by side instead of on top of each other (Fig. 6 hid
    octree-max exactly under octree-bayes), while every point stays near its own x."""
    xs = sorted({float(x) for s in series for x in s.x})
    steps = np.diff(xs)
    return float(steps.min()) / 25.0 if len(steps) else 0.03


def draw_lines(ax: Axes, series: list[Series]) -> None:
    n = len(series)
    dodge = _dodge(series) if n > 1 else 0.0
    for k, s in enumerate(series):
        pts = [(float(x), float(y), i) for i, (x, y) in enumerate(zip(s.x, s.y)) if y is not None]
        if not pts:
            continue
        x = np.array([p[0] for p in pts]) + (k - (n - 1) / 2) * dodge
        y = np.array([p[1] for p in pts])
        err = None
        if s.yerr is not None:
            idx = [p[2] for p in pts]
            if isinstance(s.yerr, tuple):
                err = np.array([[s.yerr[0][i] for i in idx], [s.yerr[1][i] for i in idx]], float)
            else:
                err = np.array([s.yerr[i] for i in idx], float)
        ax.errorbar(
            x,
            y,
            yerr=err,
            label=s.label,
            color=rgb01(s.colour) if s.colour else None,
            marker=MARKERS[k % len(MARKERS)],
            # later series: smaller hollow markers, so an equal value shows both
            markersize=8 - min(k, 3),
            markerfacecolor="none" if k % 2 else None,
            linestyle="--" if s.dashed else LINESTYLES[k % len(LINESTYLES)],
            linewidth=1.8,
            capsize=3 if err is not None else 0,
            zorder=3 + k,
        )


def line_plot(
    series: list[Series],
    title: str,
    xlabel: str,
    ylabel: str,
    xticklabels: dict[float, str] | None = None,
    ylim: tuple[float, float] | None = None,
    note: str | None = None,
) -> Figure:
    """Series over numeric (or, with `xticklabels`, named) x positions; `note` goes under the
    legend (what the error bars are, n)."""
    fig = new_figure()
    ax = fig.add_subplot()
    draw_lines(ax, series)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if xticklabels:
        ax.set_xticks(list(xticklabels), list(xticklabels.values()))
    if ylim:
        ax.set_ylim(*ylim)
    ax.grid(True, alpha=0.3)
    ax.legend(title=note, title_fontsize="small", fontsize="small")
    return fig


# -- maps --------------------------------------------------------------------------------------


def class_handles(classes: ClassTable, ids) -> list:
    """Legend patches for the classes `ids`, in the table's own colours and names."""
    from matplotlib.patches import Patch

    return [
        Patch(facecolor=rgb01(classes[i].colour), edgecolor="black", linewidth=0.4, label=name)
        for i, name in ((int(i), classes[int(i)].name) for i in sorted(set(ids)))
        if int(i) in classes
    ]


def class_rgb(classes: ClassTable, ids: np.ndarray) -> np.ndarray:
    """RGB u1 of a class-id raster through the table's colour lookup (ids past it: the last)."""
    return classes.colour_lut[np.minimum(np.asarray(ids), classes.size - 1)]


def map_figure(
    rgb: np.ndarray,
    origin_xy,
    resolution_m: float,
    title: str,
    legend: list,
    trajectory: np.ndarray | None = None,
    goals: np.ndarray | None = None,
    overlays: dict[str, np.ndarray] | None = None,
    outline: np.ndarray | None = None,
    outline_label: str = "object outline",
    inches: float = 7.0,
    trajectories: dict[str, np.ndarray] | None = None,
) -> Figure:
    """A raster indexed [ix, iy] (RGB u1 per cell; cell (i, j) centred at origin + (i, j) * res)
    drawn with x to the right and y up in metres, equal aspect, a scale bar.

    `legend`: handles of what the raster shows (e.g. `class_handles`); `overlays`: name ->
    boolean mask of the raster's shape painted in that name's `OVERLAY` colour (unknown,
    obstacle, safety zone, frontier) and labelled; `outline`: a mask whose border is drawn;
    `trajectory` (N, 2) m, its first pose marked as the start; `goals` (K, 2) m;
    `trajectories`: a fleet's, member name -> (N, 2) m, each in its own `MEMBER_COLOURS` colour
    with its start, the legend naming the members."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    nx, ny = rgb.shape[:2]
    img = np.asarray(rgb, float) / 255.0
    handles = list(legend)
    for name, mask in (overlays or {}).items():
        mask = np.asarray(mask, bool)
        if mask.any():
            img[mask] = OVERLAY[name]
            handles.append(
                Patch(facecolor=OVERLAY[name], edgecolor="black", linewidth=0.4, label=name)
            )
    x0 = origin_xy[0] - 0.5 * resolution_m
    y0 = origin_xy[1] - 0.5 * resolution_m
    extent = (x0, x0 + nx * resolution_m, y0, y0 + ny * resolution_m)
    fig = new_figure(inches + 2.4, inches)
    ax = fig.add_subplot()
    ax.imshow(np.transpose(img, (1, 0, 2)), origin="lower", extent=extent, interpolation="nearest")
    if outline is not None and np.any(outline):
        xs = origin_xy[0] + np.arange(nx) * resolution_m
        ys = origin_xy[1] + np.arange(ny) * resolution_m
        ax.contour(
            xs, ys, np.asarray(outline, float).T, levels=[0.5], colors="black", linewidths=0.6
        )
        handles.append(Line2D([], [], color="black", linewidth=0.8, label=outline_label))
    if trajectory is not None and len(trajectory):
        tr = np.asarray(trajectory, float).reshape(-1, 2)
        if len(tr) >= 2:
            (line,) = ax.plot(
                tr[:, 0], tr[:, 1], color=OVERLAY["trajectory"], linewidth=1.8, label="trajectory"
            )
            line.set_path_effects(halo())
            handles.append(line)
        handles.append(
            ax.plot(
                tr[0, 0],
                tr[0, 1],
                "o",
                markersize=9,
                color=OVERLAY["start"],
                markeredgecolor="black",
                label="start",
                linestyle="none",
            )[0]
        )
    for k, (name, tr) in enumerate((trajectories or {}).items()):
        tr = np.asarray(tr, float).reshape(-1, 2)
        if not len(tr):
            continue
        colour = MEMBER_COLOURS[k % len(MEMBER_COLOURS)]
        (line,) = ax.plot(
            tr[:, 0], tr[:, 1], color=colour, linewidth=1.8, label=f"{name}: trajectory, start"
        )
        line.set_path_effects(halo())
        ax.plot(tr[0, 0], tr[0, 1], "o", markersize=9, color=colour, markeredgecolor="black")
        handles.append(line)
    if goals is not None and len(goals):
        g = np.asarray(goals, float).reshape(-1, 2)
        handles.append(
            ax.plot(
                g[:, 0],
                g[:, 1],
                "*",
                markersize=11,
                color=OVERLAY["goals"],
                markeredgecolor="black",
                linestyle="none",
                label=f"goals (n = {len(g)})",
            )[0]
        )
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    span = extent[1] - extent[0]
    bar = next((b for b in (50, 20, 10, 5, 2, 1, 0.5, 0.2, 0.1) if b <= span / 4), span / 4)
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            bar,
            f"{bar:g} m",
            "lower right",
            pad=0.4,
            frameon=True,
            size_vertical=span / 200,
        )
    )
    ax.legend(
        handles=handles,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        fontsize="small",
        frameon=False,
    )
    return fig


def halo():
    """Path effects that outline a line in black, so that it shows over any class colour."""
    from matplotlib import patheffects

    return [patheffects.Stroke(linewidth=3.2, foreground="black"), patheffects.Normal()]


def world_map(
    classes: ClassTable,
    class_ids: np.ndarray,
    origin_xy,
    resolution_m: float,
    title: str,
    rgb: np.ndarray | None = None,
    trajectory: np.ndarray | None = None,
    goals: np.ndarray | None = None,
    trajectories: dict[str, np.ndarray] | None = None,
) -> Figure:
    """Ground truth seen from above: the top class of every cell (or a shaded `rgb` of it) with
    the classes present in the legend, the outline of objects (so a tree crown reads as an
    object, not as terrain), trajectory (or a fleet's `trajectories`), start and goals."""
    ids = np.asarray(class_ids)
    objects = classes.obstacle_lut[np.minimum(ids, classes.size - 1)]
    return map_figure(
        class_rgb(classes, ids) if rgb is None else rgb,
        origin_xy,
        resolution_m,
        title,
        class_handles(classes, np.unique(ids)),
        trajectory,
        goals,
        outline=objects,
        outline_label="object outline (seen from above)",
        trajectories=trajectories,
    )


def graph_map(
    classes: ClassTable,
    labels: np.ndarray,
    flags: np.ndarray,
    origin_xy,
    resolution_m: float,
    title: str,
    trajectory: np.ndarray | None = None,
    goals: np.ndarray | None = None,
    trajectories: dict[str, np.ndarray] | None = None,
) -> Figure:
    """The navigation graph (labels, flags: bit 1 known, 2 obstacle, 4 safety zone, 8 doubtful;
    cells corner-anchored at `origin_xy`): known nodes in their class colour, unknown, obstacle,
    safety-zone and doubtful nodes and the frontier (known free nodes next to unknown ones)
    labelled."""
    from scipy import ndimage

    labels, flags = np.asarray(labels), np.asarray(flags)
    known = (flags & 1) != 0
    obstacle = known & ((flags & 2) != 0)
    safety = known & ((flags & 4) != 0) & ~obstacle
    doubtful = known & ((flags & 8) != 0) & ~obstacle & ~safety
    free = known & ~obstacle & ~safety
    free &= classes.traversable_lut[np.minimum(labels, classes.size - 1)] | doubtful
    # unknown space around the box too: the box is cut at the last known node
    unknown_padded = np.pad(~known, 1, constant_values=True)
    near_unknown = ndimage.binary_dilation(unknown_padded, np.ones((3, 3), bool))[1:-1, 1:-1]
    frontier = free & near_unknown
    rgb = class_rgb(classes, labels).copy()
    shown = known & ~obstacle & ~safety & ~frontier & ~doubtful
    return map_figure(
        rgb,
        np.asarray(origin_xy, float) + 0.5 * resolution_m,
        resolution_m,
        title,
        class_handles(classes, np.unique(labels[shown])),
        trajectory,
        goals,
        overlays={
            "unknown": ~known,
            "obstacle": obstacle,
            "safety zone": safety,
            "doubtful": doubtful & ~frontier,
            "frontier": frontier,
        },
        trajectories=trajectories,
    )


def progress_plot(
    t_s: np.ndarray,
    explored_m2: np.ndarray,
    distance_m: np.ndarray,
    report_explored_m2: float | None = None,
) -> Figure:
    """The explorer's progress over robot time, on two panels: its explored area (its own graph's
    known free nodes) and the distance it drove. `report_explored_m2`: the report's usable
    coverage against ground truth (m2), drawn as a reference line (it measures another thing)."""
    fig = new_figure(7.2, 5.6)
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(
        t_s,
        explored_m2,
        marker="o",
        markersize=3,
        linestyle="-",
        label="explorer's graph: known free nodes",
    )
    if report_explored_m2 is not None:
        top.axhline(
            report_explored_m2,
            color="black",
            linestyle="--",
            linewidth=1,
            label=f"report: usable ∩ reachable ground truth ({report_explored_m2:.1f} m²)",
        )
    top.set_ylabel("explored area (m²)")
    top.set_title("Exploration progress (one run)")
    top.legend(fontsize="small", loc="lower right")
    bottom.plot(
        t_s,
        distance_m,
        marker="s",
        markersize=3,
        linestyle="--",
        color="tab:orange",
        label="distance driven (explorer's pose)",
    )
    bottom.set_ylabel("distance (m)")
    bottom.set_xlabel("robot time (s) since the explorer started")
    bottom.legend(fontsize="small", loc="lower right")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    return fig
