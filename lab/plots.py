"""Small PNG plots drawn with OpenCV (a dependency already), so reports need no matplotlib.

`line_plot` draws series with optional error bars over numeric or named x positions, with axes,
ticks, a title and a legend; `top_down` draws a class raster seen from above with a trajectory
and markers. Both return an RGB uint8 image; `save_png` writes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

PALETTE = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
]
FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass
class Series:
    label: str
    x: list[float]
    y: list[float | None]
    yerr: list[float] | None = None
    dashed: bool = False
    colour: tuple[int, int, int] | None = None
    extra: dict = field(default_factory=dict)


def _nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    if not math.isfinite(lo) or not math.isfinite(hi):
        return np.array([0.0, 1.0])
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw), default=mag * 10)
    return np.arange(math.floor(lo / step) * step, hi + step * 0.999, step)


def _text(img, s, org, scale=0.45, colour=(30, 30, 30), thick=1, anchor="left"):
    (w, h), _ = cv2.getTextSize(s, FONT, scale, thick)
    x, y = org
    if anchor == "centre":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, s, (int(x), int(y + h // 2)), FONT, scale, colour, thick, cv2.LINE_AA)


def line_plot(
    series: list[Series],
    title: str,
    xlabel: str,
    ylabel: str,
    xticklabels: dict[float, str] | None = None,
    size: tuple[int, int] = (720, 460),
    ylim: tuple[float, float] | None = None,
) -> np.ndarray:
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 80, 20, 40, 90
    xs = [x for s in series for x in s.x]
    ys = [
        y + (e or 0) * sgn
        for s in series
        for y, e in zip(s.y, s.yerr or [0] * len(s.y), strict=True)
        if y is not None
        for sgn in (-1, 1)
    ]
    if not xs or not ys:
        _text(img, f"{title}: no data", (w // 2, h // 2), 0.6, anchor="centre")
        return img
    x0, x1 = min(xs), max(xs)
    pad_x = (x1 - x0) * 0.08 or 0.5
    x0, x1 = x0 - pad_x, x1 + pad_x
    y0, y1 = ylim if ylim else (min(ys), max(ys))
    yt = _nice_ticks(y0, y1)
    if not ylim:
        y0, y1 = float(yt[0]), float(yt[-1])

    def px(x, y):
        u = left + (x - x0) / (x1 - x0) * (w - left - right)
        v = top + (1 - (y - y0) / ((y1 - y0) or 1)) * (h - top - bottom)
        return int(round(u)), int(round(v))

    cv2.rectangle(img, (left, top), (w - right, h - bottom), (120, 120, 120), 1)
    for t in yt:
        if y0 - 1e-9 <= t <= y1 + 1e-9:
            _, v = px(x0, t)
            cv2.line(img, (left, v), (w - right, v), (230, 230, 230), 1)
            _text(img, f"{t:g}", (left - 6, v), anchor="right")
    ticks = xticklabels or {x: f"{x:g}" for x in sorted(set(xs))}
    for x, lab in ticks.items():
        u, _ = px(x, y0)
        cv2.line(img, (u, h - bottom), (u, h - bottom + 5), (120, 120, 120), 1)
        _text(img, lab, (u, h - bottom + 16), anchor="centre")
    _text(img, title, (w // 2, 18), 0.55, anchor="centre", thick=1)
    _text(img, xlabel, ((left + w - right) // 2, h - bottom + 38), anchor="centre")
    # y label: drawn horizontally above the axis (OpenCV cannot rotate text cheaply)
    _text(img, ylabel, (left - 70, top - 16), 0.42)
    lx, ly = left + 8, h - 22
    for k, s in enumerate(series):
        col = s.colour or PALETTE[k % len(PALETTE)]
        data = [
            (x, y, e)
            for x, y, e in zip(s.x, s.y, s.yerr or [None] * len(s.y), strict=True)
            if y is not None
        ]
        pts = [px(x, y) for x, y, _ in data]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            if s.dashed:
                n = max(1, int(math.hypot(b[0] - a[0], b[1] - a[1]) // 8))
                for i in range(0, n, 2):
                    p = (a[0] + (b[0] - a[0]) * i // n, a[1] + (b[1] - a[1]) * i // n)
                    q = (a[0] + (b[0] - a[0]) * (i + 1) // n, a[1] + (b[1] - a[1]) * (i + 1) // n)
                    cv2.line(img, p, q, col, 2, cv2.LINE_AA)
            else:
                cv2.line(img, a, b, col, 2, cv2.LINE_AA)
        for (u, v), (x, y, e) in zip(pts, data, strict=True):
            if e:
                _, a = px(x, y - e)
                _, b = px(x, y + e)
                cv2.line(img, (u, a), (u, b), col, 1, cv2.LINE_AA)
                cv2.line(img, (u - 4, a), (u + 4, a), col, 1)
                cv2.line(img, (u - 4, b), (u + 4, b), col, 1)
            cv2.circle(img, (u, v), 4, col, -1, cv2.LINE_AA)
        cv2.line(img, (lx, ly), (lx + 22, ly), col, 2)
        _text(img, s.label, (lx + 28, ly), 0.42)
        lx += 40 + cv2.getTextSize(s.label, FONT, 0.42, 1)[0][0]
        if lx > w - 120:
            lx, ly = left + 8, ly + 0  # one legend row is enough for smana's plots
    return img


def top_down(
    class_rgb: np.ndarray,
    origin_xy: tuple[float, float],
    resolution_m: float,
    tracks: list[tuple[np.ndarray, tuple[int, int, int]]] = (),
    markers: list[tuple[np.ndarray, tuple[int, int, int], int]] = (),
    title: str = "",
    pixels: int = 640,
) -> np.ndarray:
    """A raster indexed [ix, iy] (RGB per cell, cell (i, j) centred at origin + (i, j) * res),
    drawn with x to the right and y up, plus polylines and point markers in world metres."""
    nx, ny = class_rgb.shape[:2]
    scale = max(1, pixels // max(nx, ny))
    img = np.ascontiguousarray(np.transpose(class_rgb, (1, 0, 2))[::-1])
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    img = np.ascontiguousarray(img)

    def to_px(xy: np.ndarray) -> np.ndarray:
        ij = (np.asarray(xy, float) - np.asarray(origin_xy)) / resolution_m
        u = (ij[:, 0] + 0.5) * scale
        v = (ny - 0.5 - ij[:, 1]) * scale
        return np.stack([u, v], axis=1).round().astype(np.int32)

    for xy, col in tracks:
        if len(xy) >= 2:
            cv2.polylines(img, [to_px(xy).reshape(-1, 1, 2)], False, col, 2, cv2.LINE_AA)
    for xy, col, r in markers:
        for u, v in to_px(np.asarray(xy).reshape(-1, 2)):
            cv2.circle(img, (int(u), int(v)), r, col, -1, cv2.LINE_AA)
    if title:
        bar = np.full((28, img.shape[1], 3), 255, np.uint8)
        _text(bar, title, (img.shape[1] // 2, 13), 0.5, anchor="centre")
        img = np.vstack([bar, img])
    return img


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")
    return path
