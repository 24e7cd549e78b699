"""The planner's one-pass window gather and enter costs against the obvious reference
(`NavGrid.box` and numpy), on grids with unallocated tiles and boxes not aligned to tiles."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.planner import TilePools, Window, _enter_costs, _gather_window


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
    _gather_window(TilePools.of(grid), x0, y0, Window(labels, flags, known_h))
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


def test_patches_refresh_the_cached_window_like_a_rebuild():
    """After a graph patch the planner refreshes only the patched nodes of its cached window and
    enter costs (`NavGrid.changes_since`); every answer must equal a fresh planner's, which
    builds both whole."""
    from smana.common.classes import ClassTable
    from smana.common.navgrid import NavGrid
    from smana.services.planner.planner import PlanError, Planner

    classes = ClassTable.load("garden3drms")
    rng = np.random.default_rng(5)
    grid = NavGrid((0.0, 0.0), (96, 80), 0.2, tile_size=16)
    ix, iy = np.meshgrid(np.arange(96), np.arange(80), indexing="ij")
    cells = np.stack([ix.ravel(), iy.ravel()], 1).astype(np.int32)
    n = len(cells)
    grid.apply_patch(cells, rng.choice([1, 2], n), rng.normal(0, 0.02, n), np.full(n, FLAG_KNOWN))
    planner = Planner(grid, classes)
    start, goal = (0.5, 0.5), (18.5, 15.5)
    planner.plan(start, goal)  # builds the caches
    for round_ in range(25):
        k = int(rng.integers(1, 300))
        pc = cells[rng.choice(n, k, replace=False)]
        flags = rng.choice(
            [FLAG_KNOWN, FLAG_KNOWN | FLAG_OBSTACLE, FLAG_KNOWN | FLAG_SAFETY_ZONE], k
        )
        keep_ends = ~(((pc[:, 0] == 2) & (pc[:, 1] == 2)) | ((pc[:, 0] == 92) & (pc[:, 1] == 77)))
        flags = np.where(keep_ends, flags, FLAG_KNOWN).astype(np.uint8)
        grid.apply_patch(pc, rng.choice([1, 2, 4], k), rng.normal(0, 0.02, k), flags)
        fresh = Planner(grid, classes)
        for allow_unknown in (False, True):
            try:
                got = planner.plan(start, goal, allow_unknown=allow_unknown)
            except PlanError as exc:
                got = exc.code
            try:
                want = fresh.plan(start, goal, allow_unknown=allow_unknown)
            except PlanError as exc:
                want = exc.code
            if isinstance(want, str):
                assert got == want, round_
            else:
                assert got.cost_total == pytest.approx(want.cost_total, rel=1e-12), round_
        labels, flags_w, known_h = planner._cache
        box = planner._cache_key[1]
        want_l, want_h, want_f = grid.box(*box)
        np.testing.assert_array_equal(labels, want_l)
        np.testing.assert_array_equal(flags_w, want_f)


def test_grid_change_log():
    from smana.common.navgrid import CHANGE_LOG, NavGrid

    g = NavGrid((0.0, 0.0), (40, 40), 0.2, tile_size=8)
    v0 = g.version
    g.apply_patch([[1, 2], [30, 31]], [1, 1], [0.0, 0.0], [1, 1])
    g.apply_patch([[5, 5]], [2], [0.0], [1])
    got = g.changes_since(v0)
    assert sorted(map(tuple, got.tolist())) == [(1, 2), (5, 5), (30, 31)]
    assert len(g.changes_since(g.version)) == 0
    g.changed(None)  # a writer that cannot say which nodes
    assert g.changes_since(v0) is None
    v1 = g.version
    for _ in range(CHANGE_LOG + 1):
        g.apply_patch([[0, 0]], [1], [0.0], [1])
    assert g.changes_since(v1) is None  # the log does not reach back that far
