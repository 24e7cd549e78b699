"""Figures 11 and 12 of the paper, drawn with OpenCV (matplotlib is not a dependency).

Figure 11: average CPU use with standard deviation (log scale) and peak RAM of the map and graph
processes, per back-end and resolution. Figure 12: average integration time per point with
standard deviation, map and graph, same groups (log scale).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

WHITE, BLACK, GREY = (255, 255, 255), (0, 0, 0), (200, 200, 200)
SERIES_COLOURS = [(180, 119, 31), (14, 127, 255)]  # BGR: blue (map), orange (graph)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text(img, s, org, scale=0.45, colour=BLACK, thick=1):
    cv2.putText(img, s, (int(org[0]), int(org[1])), FONT, scale, colour, thick, cv2.LINE_AA)


def _nice_ticks(lo: float, hi: float, log: bool) -> list[float]:
    if log:
        return [10.0**e for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)]
    step = 10 ** math.floor(math.log10(max(hi - lo, 1e-12)))
    for m in (1, 2, 5, 10):
        if (hi - lo) / (step * m) <= 6:
            step *= m
            break
    return list(np.arange(0.0, hi + step * 0.5, step))


def bar_panel(img, box, groups, series, values, errors, title, ylabel, log=False):
    """Grouped bars with error bars inside `box` = (x0, y0, x1, y1) of `img`.

    values/errors: [n_series][n_groups]; NaN bars are left out.
    """
    x0, y0, x1, y1 = box
    left, bottom, top = x0 + 70, y1 - 70, y0 + 40
    right = x1 - 15
    vals = np.asarray(values, float)
    errs = np.nan_to_num(np.asarray(errors, float))
    finite = vals[np.isfinite(vals)]
    hi = float(np.max(finite + 0)) if finite.size else 1.0
    hi = max(hi, float(np.nanmax(vals + errs)) if finite.size else 1.0)
    if log:
        pos = finite[finite > 0]
        lo = 10 ** math.floor(math.log10(pos.min())) if pos.size else 1e-3
        hi = 10 ** math.ceil(math.log10(hi)) if hi > 0 else 1.0
        hi = max(hi, lo * 10)
    else:
        lo, hi = 0.0, hi * 1.15 if hi > 0 else 1.0

    def ypix(v):
        if log:
            v = max(v, lo)
            f = (math.log10(v) - math.log10(lo)) / (math.log10(hi) - math.log10(lo))
        else:
            f = (v - lo) / (hi - lo)
        return int(bottom - f * (bottom - top))

    _text(img, title, (left, y0 + 22), 0.55, BLACK, 1)
    for t in _nice_ticks(lo, hi, log):
        if lo <= t <= hi * 1.0001:
            y = ypix(t)
            cv2.line(img, (left, y), (right, y), GREY, 1)
            label = f"{t:g}" if (t >= 0.01 or t == 0) else f"{t:.0e}"
            _text(img, label, (x0 + 5, y + 4), 0.4)
    cv2.line(img, (left, top), (left, bottom), BLACK, 1)
    cv2.line(img, (left, bottom), (right, bottom), BLACK, 1)
    # y label, written vertically
    lab = np.full((20, 8 * len(ylabel) + 10, 3), 255, np.uint8)
    _text(lab, ylabel, (3, 15), 0.45)
    lab = cv2.rotate(lab, cv2.ROTATE_90_COUNTERCLOCKWISE)
    ly = max(top, (top + bottom - lab.shape[0]) // 2)
    h = min(lab.shape[0], img.shape[0] - ly)
    img[ly : ly + h, x0 + 48 : x0 + 48 + lab.shape[1]] = lab[:h]

    n_g, n_s = len(groups), len(series)
    gw = (right - left) / max(n_g, 1)
    bw = gw * 0.7 / n_s
    for g, name in enumerate(groups):
        gx = left + g * gw + gw * 0.15
        for s in range(n_s):
            v = vals[s][g]
            if not np.isfinite(v):
                continue
            bx = int(gx + s * bw)
            cv2.rectangle(img, (bx, ypix(v)), (int(bx + bw - 2), bottom), SERIES_COLOURS[s], -1)
            e = errs[s][g]
            if e > 0:
                cx = int(bx + bw / 2)
                ya, yb = ypix(v + e), ypix(max(v - e, lo if log else 0.0))
                cv2.line(img, (cx, ya), (cx, yb), BLACK, 1)
                cv2.line(img, (cx - 4, ya), (cx + 4, ya), BLACK, 1)
                cv2.line(img, (cx - 4, yb), (cx + 4, yb), BLACK, 1)
        for k, part in enumerate(name.split("\n")):
            _text(img, part, (int(left + g * gw + 4), bottom + 18 + 16 * k), 0.4)
    for s, sname in enumerate(series):  # legend
        lx = right - 150
        ly = top + 8 + 18 * s
        cv2.rectangle(img, (lx, ly - 9), (lx + 14, ly + 3), SERIES_COLOURS[s], -1)
        _text(img, sname, (lx + 20, ly + 2), 0.42)


def _groups(rows):
    return [f"{r['backend']}\n{r['map_res']:g}/{r['graph_res']:g} m" for r in rows]


def figure_11(rows: list[dict], path: str | Path) -> Path:
    """CPU (log scale, with sd) and peak RAM of the map and graph processes."""
    w = max(900, 130 * len(rows) + 120)
    img = np.full((900, w, 3), 255, np.uint8)
    g = _groups(rows)
    bar_panel(
        img,
        (0, 0, w, 450),
        g,
        ["map", "graph"],
        [[r["cpu_map"] for r in rows], [r["cpu_graph"] for r in rows]],
        [[r["cpu_map_std"] for r in rows], [r["cpu_graph_std"] for r in rows]],
        "Average CPU use with standard deviation (100 % = one core)",
        "CPU %",
        log=True,
    )
    bar_panel(
        img,
        (0, 450, w, 900),
        g,
        ["map", "graph"],
        [[r["rss_map_mb"] for r in rows], [r["rss_graph_mb"] for r in rows]],
        [[0] * len(rows), [0] * len(rows)],
        "Peak RAM (RSS)",
        "MB",
    )
    cv2.imwrite(str(path), img)
    return Path(path)


def figure_12(rows: list[dict], path: str | Path) -> Path:
    """Integration time per point (with sd), map and graph, log scale."""
    w = max(900, 130 * len(rows) + 120)
    img = np.full((480, w, 3), 255, np.uint8)
    bar_panel(
        img,
        (0, 0, w, 480),
        _groups(rows),
        ["map", "graph"],
        [[r["map_us_pt"] for r in rows], [r["graph_us_pt"] for r in rows]],
        [[r["map_us_pt_std"] for r in rows], [r["graph_us_pt_std"] for r in rows]],
        "Average integration time per point with standard deviation",
        "us / point",
        log=True,
    )
    cv2.imwrite(str(path), img)
    return Path(path)
