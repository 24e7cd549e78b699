"""The planner's one-pass window gather and enter costs against the obvious reference
(`NavGrid.box` and numpy), on grids with unallocated tiles and boxes not aligned to tiles."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.planner import _enter_costs, _gather_window


def _grid(rng, nx, ny, tile):
    grid = NavGrid((0.0, 0.0), (nx, ny), 0.2, tile_size=tile)
    cells = np.argwhere(rng.random((nx, ny)) < 0.5)  # leaves some tiles unallocated
    k = len(cells)
    flags = rng.choice([0, FLAG_KNOWN, FLAG_KNOWN | FLAG_OBSTACLE, FLAG_SAFETY_ZONE], k)
    grid.apply_patch(cells, rng.integers(0, 10, k), rng.normal(size=k), flags.astype(np.uint8))
    return grid


@pytest.mark.parametrize("seed", range(6))
def test_gather_window_equals_navgrid_box(seed):
    rng = np.random.default_rng(seed)
    nx, ny, tile = int(rng.integers(5, 70)), int(rng.integers(5, 70)), int(rng.integers(1, 17))
    grid = _grid(rng, nx, ny, tile)
    x0, y0 = int(rng.integers(0, nx)), int(rng.integers(0, ny))
    x1, y1 = int(rng.integers(x0 + 1, nx + 1)), int(rng.integers(y0 + 1, ny + 1))
    shape = (x1 - x0, y1 - y0)
    # Filled in place over garbage, as the planner refills its window after a graph change.
    labels = rng.integers(0, 9, shape).astype(np.uint16)
    flags = rng.integers(0, 9, shape).astype(np.uint8)
    known_h = rng.normal(size=shape).astype(np.float32)
    _gather_window(
        grid.tile_map,
        grid.layer("labels"),
        grid.layer("heights"),
        grid.layer("flags"),
        grid.tile_size,
        x0,
        y0,
        labels,
        flags,
        known_h,
    )
    want_l, want_h, want_f = grid.box(x0, y0, x1, y1)
    np.testing.assert_array_equal(labels, want_l)
    np.testing.assert_array_equal(flags, want_f)
    want_known = np.where(want_f & FLAG_KNOWN, want_h, np.nan).astype(np.float64)
    np.testing.assert_array_equal(known_h, want_known)  # NaN where unknown, on both sides


@pytest.mark.parametrize("allow_unknown", [False, True])
def test_enter_costs_and_their_minimum(allow_unknown):
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 12, (30, 20)).astype(np.uint16)
    flags = rng.choice([0, FLAG_KNOWN, FLAG_KNOWN | FLAG_OBSTACLE, FLAG_SAFETY_ZONE], (30, 20))
    flags = flags.astype(np.uint8)
    lut = np.array([np.inf, 1.6, 0.8, 2.4, np.inf, np.inf, 0.4, np.inf, np.inf, 3.0])
    enter = np.full(labels.shape, -1.0)
    lowest = _enter_costs(labels, flags, lut, allow_unknown, 2.0, enter)
    blocked = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0
    known = (flags & FLAG_KNOWN) != 0
    want = np.where(labels < len(lut), lut[np.minimum(labels, len(lut) - 1)], np.inf)
    if allow_unknown:
        want = np.where(known & (labels == 0), 2.0, want)
    want = np.where(known, want, 2.0 if allow_unknown else np.inf)
    want = np.where(blocked, np.inf, want)
    np.testing.assert_array_equal(enter, want)
    assert lowest == want[np.isfinite(want)].min()
    blocked_all = np.full_like(flags, FLAG_OBSTACLE)
    none = _enter_costs(labels, blocked_all, lut, allow_unknown, 2.0, np.empty(labels.shape))
    assert none == 0.0
