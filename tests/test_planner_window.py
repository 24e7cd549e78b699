"""The planner's one-pass window gather and enter costs against the obvious reference
(`NavGrid.box` and numpy), on grids with unallocated tiles and boxes not aligned to tiles."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.enter_costs import EnterCosts, enter_costs
from smana.services.planner.window import TilePools, Window, gather_window


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
    gather_window(TilePools.of(grid), x0, y0, Window(labels, flags, known_h))
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
    lowest = enter_costs(labels, flags, EnterCosts(lut, allow_unknown, 2.0, 10.0), enter)
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
    costs = EnterCosts(lut, allow_unknown, 2.0, 10.0)
    none = enter_costs(labels, blocked_all, costs, np.empty(labels.shape))
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


def _garden_grid(rng, nx=90, ny=70):
    grid = NavGrid((0.0, 0.0), (nx, ny), 0.2, tile_size=16)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    cells = np.stack([ix.ravel(), iy.ravel()], 1).astype(np.int32)
    n = len(cells)
    flags = np.where(rng.random(n) < 0.1, FLAG_KNOWN | FLAG_OBSTACLE, FLAG_KNOWN)
    flags[[0, n - 1]] = FLAG_KNOWN  # the query ends below
    grid.apply_patch(cells, rng.choice([1, 2], n), rng.normal(0, 0.02, n), flags.astype(np.uint8))
    return grid, cells


def _no_builds(monkeypatch):
    """Make every window and enter-cost build kernel fail: a query that calls one fails."""
    from smana.services.planner import planner as mod

    def built(*args):
        raise AssertionError("the query built its window or enter costs")

    for name in ("gather_window", "gather_cells", "enter_costs", "enter_cells"):
        monkeypatch.setattr(mod, name, built)
    for name in ("enter_costs_risk", "enter_cells_risk"):
        monkeypatch.setattr(mod, name, built)


def test_a_prepared_planner_builds_nothing_on_its_first_query(monkeypatch):
    """Planner() and Planner.prepare() build ahead what the first query after a graph change
    would build (window, enter costs under the last query's costs), so that query builds
    nothing; its answer is the kernel's on the grid's dense arrays, to the bit."""
    from smana.common.classes import ClassTable
    from smana.common.config.planner import PlannerConfig
    from smana.services.planner.astar import astar
    from smana.services.planner.planner import Planner

    classes = ClassTable.load("garden3drms")
    rng = np.random.default_rng(11)
    grid, cells = _garden_grid(rng)
    start, goal = (0.1, 0.1), (17.9, 13.9)
    # prepares; the clearance cost off, so that the answer compares with the kernel's on the
    # class costs alone
    planner = Planner(grid, classes, PlannerConfig(clearance_cost=0.0))
    with monkeypatch.context() as m:
        _no_builds(m)
        first = planner.plan(start, goal)
    assert first.ok
    labels, heights, flags = grid.box(0, 0, *grid.shape)
    lut = classes.costs({}) * planner.config.t_f
    enter = np.where((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0, np.inf, lut[labels])
    known_h = np.where(flags & FLAG_KNOWN, heights, np.nan)
    want = astar(
        enter,
        known_h.astype(np.float32).astype(np.float64),
        (0, 0),
        (89, 69),
        0.2,
        planner.config.h_f,
        planner.config.max_step_m,
        planner.config.heuristic,
    )
    assert first.cost_total == want.cost and np.array_equal(first.cells, want.cells)
    # A patch, then prepare (the service's tick): the next query builds nothing either, also
    # under the last query's costs when they were not the defaults; with the clearance cost on
    # (the default), whose ring round each patched node the patch refreshes too.
    planner = Planner(grid, classes)
    for kw in ({}, {"t_f": 1.7, "allow_unknown": True}):
        planner.plan(start, goal, **kw)
        pc = cells[rng.choice(len(cells), 200, replace=False)]
        pc = pc[(pc.sum(1) > 0) & (pc.sum(1) < 158)]
        grid.apply_patch(pc, *grid.read_cells(pc))
        planner.prepare()
        with monkeypatch.context() as m:
            _no_builds(m)
            got = planner.plan(start, goal, **kw)
        assert (
            got.ok and got.cost_total == Planner(grid, classes).plan(start, goal, **kw).cost_total
        )


def _risk_layers(rng, n):
    """Half the nodes doubtful (P 0.5 to 1), a second class (grass, terrain or an obstacle
    class) holding part of the rest."""
    p_label = np.where(rng.random(n) < 0.5, rng.integers(128, 256, n), 255).astype(np.uint8)
    alt = rng.choice([1, 2, 8], n).astype(np.uint16)
    p_alt = ((255 - p_label.astype(np.int64)) * rng.uniform(0, 1, n)).astype(np.uint8)
    return alt, p_label, p_alt


@pytest.mark.parametrize("mode", ["expected", "cvar", "chance", "label"])
def test_a_prepared_planner_builds_nothing_on_its_first_query_in_every_risk_mode(mode, monkeypatch):
    """On a graph with risk layers, Planner() and Planner.prepare() also gather the layers and
    run the risk enter-cost pass ahead, under the configured mode and under the last query's
    mode: the first query builds nothing, and its cost is Dijkstra's on the reference's costs."""
    from smana.common.classes import ClassTable
    from smana.common.config.planner import PlannerConfig
    from smana.services.planner.planner import RISK_MODES, Planner
    from smana.services.planner.reference import dijkstra_cost
    from tests.support.enter_cost_reference import risk_enter_costs

    assert mode in RISK_MODES
    classes = ClassTable.load("garden3drms")
    rng = np.random.default_rng(12)
    grid, cells = _garden_grid(rng)
    grid.apply_patch(cells, *grid.read_cells(cells), risk=_risk_layers(rng, len(cells)))
    start, goal = (0.1, 0.1), (17.9, 13.9)
    config = PlannerConfig(risk=mode, max_risk=0.3)

    def want(p):
        labels, heights, flags = grid.box(0, 0, *grid.shape)
        risk = [grid.read_risk(cells)[k].reshape(grid.shape) for k in range(3)]
        enter = risk_enter_costs(labels, flags, *risk, classes, p)
        known_h = np.where(flags & FLAG_KNOWN, heights, np.nan).astype(np.float64)
        return dijkstra_cost(enter, known_h, (0, 0), (89, 69), 0.2, p.h_f, p.max_step_m)

    planner = Planner(grid, classes, config)  # prepares
    with monkeypatch.context() as m:
        _no_builds(m)
        first = planner.plan(start, goal)
    assert first.ok and first.cost_total == pytest.approx(want(config), rel=1e-9)
    # A query in another mode, a patch with distributions, prepare (the service's tick): the
    # next query in that mode builds nothing either.
    other = RISK_MODES[(RISK_MODES.index(mode) + 1) % len(RISK_MODES)]
    planner.plan(start, goal, risk=other)
    pc = cells[rng.choice(len(cells), 200, replace=False)]
    pc = pc[(pc.sum(1) > 0) & (pc.sum(1) < 158)]
    grid.apply_patch(pc, *grid.read_cells(pc), risk=_risk_layers(rng, len(pc)))
    planner.prepare()
    with monkeypatch.context() as m:
        _no_builds(m)
        got = planner.plan(start, goal, risk=other)
    p = PlannerConfig(risk=other, max_risk=0.3)
    assert got.ok and got.cost_total == pytest.approx(want(p), rel=1e-9)


def test_the_service_prepares_its_planner_on_the_tick_after_a_patch(monkeypatch):
    from smana.common.config import SmanaConfig
    from smana.services.planner.service import PlannerService

    svc = PlannerService(SmanaConfig())
    svc.tick()  # an empty grid: nothing to build
    assert svc.planner._cache_key is None
    nx, ny = svc.grid.shape
    cells = np.argwhere(np.ones((min(nx, 40), min(ny, 40)), bool)).astype(np.int32)
    k = len(cells)
    svc.grid.apply_patch(cells, np.full(k, 2), np.zeros(k), np.full(k, FLAG_KNOWN, np.uint8))
    svc.tick()
    assert svc.planner._cache_key[0] == svc.grid.version
    start = svc.grid.cell_centre(1, 1)
    goal = svc.grid.cell_centre(38, 30)
    with monkeypatch.context() as m:
        _no_builds(m)
        assert svc.planner.plan(start, goal).ok


def test_prepare_keeps_the_last_querys_window_and_refreshes_a_patch_in_place(monkeypatch):
    """A query whose goal lies beyond the known area has a larger window; `prepare` after a
    patch builds that window again, refreshing only the patched nodes, not the known area's."""
    from smana.common.classes import ClassTable
    from smana.services.planner import planner as mod
    from smana.services.planner.planner import Planner

    classes = ClassTable.load("garden3drms")
    rng = np.random.default_rng(3)
    grid = NavGrid((0.0, 0.0), (200, 120), 0.2, tile_size=16)
    ix, iy = np.meshgrid(np.arange(90), np.arange(70), indexing="ij")
    cells = np.stack([ix.ravel(), iy.ravel()], 1).astype(np.int32)
    k = len(cells)
    grid.apply_patch(cells, np.full(k, 2), rng.normal(0, 0.02, k), np.full(k, FLAG_KNOWN, np.uint8))
    planner = Planner(grid, classes)
    start, goal = (0.1, 0.1), (35.1, 21.1)  # cell (175, 105): unknown, far outside the known box
    first = planner.plan(start, goal, allow_unknown=True)
    assert first.ok
    pc = cells[rng.choice(k, 100, replace=False)]
    grid.apply_patch(pc, *grid.read_cells(pc))
    with monkeypatch.context() as m:
        for name in ("gather_window", "enter_costs"):  # whole builds: not allowed
            m.setattr(mod, name, lambda *a: (_ for _ in ()).throw(AssertionError("rebuilt")))
        planner.prepare()
    with monkeypatch.context() as m:
        _no_builds(m)
        again = planner.plan(start, goal, allow_unknown=True)
    assert again.cost_total == first.cost_total and np.array_equal(again.cells, first.cells)


@pytest.mark.parametrize("seed", range(4))
def test_the_whole_window_clearance_pass_equals_the_per_node_one(seed):
    """`add_clearance_all` (from the blocked areas' edges) gives the per-node pass's costs to
    the bit, on windows whose blocked nodes are closed, as the enter costs always have them."""
    from smana.services.planner.enter_costs import add_clearance, add_clearance_all

    rng = np.random.default_rng(seed)
    n = 60
    flags = np.where(rng.random((n, n)) < 0.12, FLAG_OBSTACLE, 0)
    flags = (flags | np.where(rng.random((n, n)) < 0.1 * seed, FLAG_SAFETY_ZONE, 0)).astype(
        np.uint8
    )
    out = np.where(rng.random((n, n)) < 0.05, np.inf, rng.random((n, n)))
    out[(flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0] = np.inf
    for ring in (1, 2, 3):
        per_node = out.copy()
        cells = np.argwhere(np.isfinite(out)).astype(np.int32)
        add_clearance(flags, per_node, cells, ring, 0.8)
        whole = out.copy()
        add_clearance_all(flags, whole, ring, 0.8)
        assert np.array_equal(per_node, whole)
        assert (whole >= out).all() and (whole > out).any()
