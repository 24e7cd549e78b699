"""The slow, obvious reference for the view-gain kernel (`frontier.view_gains`): one node at a
time, in plain Python, from the sector's definition rather than from `FovModel`'s precomputed
offsets and masks.

Used by the tests (the kernel must agree with it) and by `smana bench explorer`.
"""

from __future__ import annotations

import math

import numpy as np

from smana.common.config.explorer import ViewConfig


def view_gains_reference(
    unknown: np.ndarray,
    opaque: np.ndarray | None,
    candidates,
    resolution_m: float,
    view: ViewConfig,
    samples_per_cell: int = 2,
) -> np.ndarray:
    """Unknown area (m^2) each candidate sees at each of `view.n_yaw` headings, shape (C, K).

    A node counts when it is unknown, not the candidate's own node, between `min_range_m` and
    `max_range_m` of it, within +-fov/2 of the heading, and (with `opaque`) the straight line
    between the two node centres, sampled `samples_per_cell` times per node length, meets no
    opaque node other than the target itself.
    """
    nx, ny = unknown.shape
    yaws = [k * 2 * math.pi / view.n_yaw for k in range(view.n_yaw)]
    half_fov = math.radians(view.fov_deg) / 2 + 1e-9  # the kernel's edge epsilon
    r = int(math.ceil(view.max_range_m / resolution_m))
    cands = np.asarray(candidates, np.int64).reshape(-1, 2)
    counts = np.zeros((len(cands), len(yaws)), np.int64)
    for c, (cx, cy) in enumerate(cands.tolist()):
        for i in range(max(0, cx - r), min(nx, cx + r + 1)):
            for j in range(max(0, cy - r), min(ny, cy + r + 1)):
                dx, dy = i - cx, j - cy
                if (dx, dy) == (0, 0) or not unknown[i, j]:
                    continue
                d = math.hypot(dx, dy) * resolution_m
                if d > view.max_range_m or d < view.min_range_m:
                    continue
                if opaque is not None and _blocked(opaque, cx, cy, i, j, samples_per_cell):
                    continue
                for k, yaw in enumerate(yaws):
                    diff = (math.atan2(dy, dx) - yaw + math.pi) % (2 * math.pi) - math.pi
                    if abs(diff) <= half_fov:
                        counts[c, k] += 1
    return counts * resolution_m * resolution_m


def _blocked(opaque: np.ndarray, cx: int, cy: int, i: int, j: int, samples_per_cell: int) -> bool:
    dx, dy = i - cx, j - cy
    steps = math.ceil(math.hypot(dx, dy) * samples_per_cell)
    for s in range(1, steps):
        # node (i, j) spans [i - 0.5, i + 0.5) in node units around its centre
        px = math.floor(cx + s / steps * dx + 0.5)
        py = math.floor(cy + s / steps * dy + 0.5)
        if (px, py) != (i, j) and opaque[px, py]:
            return True
    return False
