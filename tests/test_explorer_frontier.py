"""Frontier detection, candidate sampling, FOV-mask gains and view selection vs slow references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config.explorer import ExplorerConfig, ViewConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.reference import view_gains_reference

TRAV = np.zeros(9, bool)
TRAV[[1, 2]] = True  # garden: grass, terrain


def _grid(known_box, shape=(12, 10), label=2):
    labels = np.zeros(shape, np.uint16)
    flags = np.zeros(shape, np.uint8)
    (x0, x1), (y0, y1) = known_box
    labels[x0:x1, y0:y1] = label
    flags[x0:x1, y0:y1] = fr.KNOWN
    return labels, flags


# -- masks and frontier -------------------------------------------------------------------------


def test_traversable_mask_excludes_obstacles_safety_unknown_and_bad_labels():
    labels, flags = _grid(((0, 6), (0, 6)))
    labels[1, 1] = 4  # hedge
    flags[1, 1] |= fr.OBSTACLE
    flags[2, 2] |= fr.SAFETY_ZONE
    labels[3, 3] = 300  # outside the lookup table
    free = fr.traversable_mask(labels, flags, TRAV)
    assert not free[1, 1] and not free[2, 2] and not free[3, 3]
    assert not free[7, 7]  # unknown
    assert free[0, 0] and free[5, 5]
    assert free.sum() == 36 - 3


def test_reachable_is_eight_connected_and_empty_from_a_blocked_start():
    free = np.zeros((5, 5), bool)
    free[0, 0] = free[1, 1] = free[2, 2] = True  # diagonal chain
    free[4, 0] = True  # island
    r = fr.reachable_mask(free, (0, 0))
    assert r[2, 2] and not r[4, 0]
    assert not fr.reachable_mask(free, (3, 3)).any()
    assert not fr.reachable_mask(free, (9, 9)).any()


def _frontier_reference(reachable, unknown):
    out = []
    nx, ny = reachable.shape
    for i in range(nx):
        for j in range(ny):
            if not reachable[i, j]:
                continue
            near = any(
                0 <= i + a < nx and 0 <= j + b < ny and unknown[i + a, j + b]
                for a in (-1, 0, 1)
                for b in (-1, 0, 1)
            )
            if near:
                out.append((i, j))
    return np.array(out, np.int64).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(5))
def test_frontier_cells_match_reference(seed):
    rng = np.random.default_rng(seed)
    reachable = rng.random((15, 11)) < 0.5
    unknown = ~reachable & (rng.random((15, 11)) < 0.5)
    got = fr.frontier_cells(reachable, unknown)
    want = _frontier_reference(reachable, unknown)
    assert sorted(map(tuple, got)) == sorted(map(tuple, want))


def test_grid_border_is_not_a_frontier():
    reachable = np.ones((4, 4), bool)
    assert len(fr.frontier_cells(reachable, np.zeros((4, 4), bool))) == 0


def test_sample_candidates_one_per_block_nearest_centre():
    rng = np.random.default_rng(3)
    cells = np.unique(rng.integers(0, 30, (200, 2)), axis=0)
    out = fr.sample_candidates(cells, 4)
    blocks = {tuple(b) for b in cells // 4}
    assert len(out) == len(blocks)
    assert len({tuple(b) for b in out // 4}) == len(out)
    for c in out:
        b = c // 4
        centre = b * 4 + 1.5
        same = cells[(cells // 4 == b).all(axis=1)]
        assert ((c - centre) ** 2).sum() == ((same - centre) ** 2).sum(axis=1).min()
    assert np.array_equal(fr.sample_candidates(cells, 1), cells)
    with pytest.raises(ValueError):
        fr.sample_candidates(cells, 0)


# -- gains --------------------------------------------------------------------------------------


@pytest.mark.parametrize("occlusion", [False, True])
def test_view_gains_match_reference(occlusion):
    rng = np.random.default_rng(7)
    unknown = rng.random((24, 20)) < 0.5
    opaque = (~unknown) & (rng.random((24, 20)) < 0.2)
    fov = fr.FovModel.build(
        0.2, ViewConfig(fov_deg=57.0, max_range_m=2.0, min_range_m=0.3, n_yaw=8)
    )
    cands = np.array([[5, 5], [12, 10], [0, 0], [23, 19], [20, 3]])
    gains, best = fr.view_gains(unknown, opaque if occlusion else None, cands, fov)
    assert gains.shape == (5, 8)
    ref = view_gains_reference(unknown, opaque if occlusion else None, cands, 0.2, fov.view)
    for c, cand in enumerate(cands):
        for k, yaw in enumerate(fov.yaws):
            want = ref[c, k]
            assert gains[c, k] == pytest.approx(want), (cand, yaw)
        assert best[c] == fov.yaws[np.argmax(gains[c])]


def test_a_wall_hides_what_is_behind_it():
    unknown = np.zeros((30, 30), bool)
    unknown[20:, :] = True  # unknown beyond x = 20
    opaque = np.zeros((30, 30), bool)
    opaque[18, :] = True  # a hedge across the view
    fov = fr.FovModel.build(
        0.1, ViewConfig(fov_deg=57.0, max_range_m=2.5, min_range_m=0.0, n_yaw=4)
    )
    g_open, _ = fr.view_gains(unknown, None, [[10, 15]], fov)
    g_wall, _ = fr.view_gains(unknown, opaque, [[10, 15]], fov)
    assert g_open[0, 0] > 1.0  # facing +x sees the unknown strip without the wall
    assert g_wall[0, 0] == 0.0
    assert g_open[0, 2] == 0.0  # facing -x sees nothing unknown


def test_full_disc_area_with_a_360_degree_fov():
    fov = fr.FovModel.build(
        0.05, ViewConfig(fov_deg=360.0, max_range_m=1.0, min_range_m=0.0, n_yaw=1)
    )
    unknown = np.ones((60, 60), bool)
    gains, _ = fr.view_gains(unknown, None, [[30, 30]], fov)
    assert gains[0, 0] == pytest.approx(math.pi, rel=0.03)


def test_view_gains_rejects_bad_input():
    fov = fr.FovModel.build(0.2, ViewConfig(min_range_m=0.0))
    with pytest.raises(ValueError):
        fr.view_gains(np.zeros((5, 5), bool), None, [[5, 0]], fov)
    with pytest.raises(ValueError):
        fr.view_gains(np.zeros((5, 5), bool), np.zeros((4, 5), bool), [[0, 0]], fov)
    with pytest.raises(ValueError):
        fr.FovModel.build(0.2, ViewConfig(fov_deg=0))
    with pytest.raises(ValueError):
        fr.FovModel.build(0.2, ViewConfig(max_range_m=1.0, min_range_m=2.0))
    g, b = fr.view_gains(np.zeros((5, 5), bool), None, np.zeros((0, 2)), fov)
    assert g.shape == (0, 16) and b.shape == (0,)


# -- selection ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(20))
def test_select_view_is_exact_branch_and_bound(seed):
    """select_view equals the brute-force reference: every candidate costed and scored."""
    rng = np.random.default_rng(seed)
    n = 25
    xy = rng.uniform(-5, 5, (n, 2))
    gains = rng.uniform(0, 10, n)
    detour = rng.uniform(1.0, 3.0, n)  # path cost = detour * straight distance * 1.5 >= bound
    unreachable = rng.random(n) < 0.15
    robot = np.array([0.3, -0.2])
    score = fr.ViewScore(rng.uniform(5, 12), rng.uniform(5, 30), rng.uniform(0, 2))
    queried = []

    def cost(goal):
        i = int(np.flatnonzero((xy == goal).all(axis=1))[0])
        queried.append(i)
        if unreachable[i]:
            return None
        return detour[i] * 1.5 * np.hypot(*(goal - robot)), f"path{i}"

    choice = fr.select_view(
        xy,
        np.arange(n)[:, None].repeat(2, 1),
        gains,
        np.zeros(n),
        robot,
        cost,
        score,
        min_gain_m2=1.0,
        cost_per_m_lower_bound=1.5,
        max_queries=n,
    )
    n_asked = len(queried)
    reference = [
        (gains[i] / score.view_area_m2 - score.weight * c[0] / score.cost_per_view_range, c[1])
        for i in range(n)
        if gains[i] >= 1.0 and (c := cost(xy[i])) is not None
    ]
    best = max(reference, key=lambda r: r[0])
    assert choice is not None
    assert choice.score == pytest.approx(best[0])
    assert choice.path == best[1]
    assert choice.n_queries == n_asked <= n


def test_path_cost_weight_trades_a_big_view_across_grass_for_a_near_one_on_terrain():
    """A big gain 8 m away across grass against a small gain 2 m away on terrain, costed with the
    planner's eq. 1 (t_f 0.8, T(terrain) 1, T(grass) 2, res 0.2): the view gain alone (w = 0)
    takes the far one, the default weight the near one, and so did neither the old score."""
    flat, bound = fr.path_cost_scale(0.8, np.array([np.inf, 2.0, 1.0]), 0.2)
    assert (flat, bound) == pytest.approx((5.0, 1 + 4 / math.sqrt(2)))
    fov = fr.FovModel.build(0.2, ViewConfig())
    xy = np.array([[8.0, 0.0], [0.0, 2.0]])
    gains = np.array([0.9, 0.35]) * fov.view_area_m2
    per_m = {0: 1 + 0.8 * 2 / 0.2, 1: flat}  # grass, terrain

    def cost(goal):
        i = int(np.flatnonzero((xy == goal).all(axis=1))[0])
        return per_m[i] * np.hypot(*goal), i

    def choose(weight):
        score = fr.ViewScore(fov.view_area_m2, flat * ViewConfig().max_range_m, weight)
        c = fr.select_view(xy, xy, gains, [0, 0], [0, 0], cost, score, 0.4, bound, max_queries=5)
        return c.path

    assert choose(0.0) == 0
    assert choose(ExplorerConfig().path_cost_weight) == 1
    old = gains - 0.05 * np.array([cost(p)[0] for p in xy])  # gain_m2 - 0.05 * cost, as it was
    assert np.argmax(old) == 0


def test_view_area_is_the_all_unknown_gain():
    fov = fr.FovModel.build(0.2, ViewConfig())
    gains, _ = fr.view_gains(np.ones((61, 61), bool), None, [[30, 30]], fov)
    assert gains.max() == pytest.approx(fov.view_area_m2)
    # the sector's area, up to the grid's discretisation
    sector = math.radians(57) / 2 * (4.0**2 - 0.3**2)
    assert fov.view_area_m2 == pytest.approx(sector, rel=0.05)


def test_select_view_none_when_nothing_is_worth_it_and_honours_query_cap():
    xy = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    calls = []
    score = fr.ViewScore(8.0, 20.0, 1.0)

    def cost(goal):
        calls.append(goal)
        return None

    assert (
        fr.select_view(xy, xy, [0.1, 0.2, 0.3], [0, 0, 0], [0, 0], cost, score, 0.5, max_queries=9)
        is None
    )
    assert calls == []
    assert (
        fr.select_view(xy, xy, [5, 5, 5], [0, 0, 0], [0, 0], cost, score, 0.5, max_queries=2)
        is None
    )
    assert len(calls) == 2


# -- nearest-frontier distance field ------------------------------------------------------------


def _dijkstra_reference(free, starts, start_d, res):
    """scipy's Dijkstra on the 8-connected graph of free nodes, one run per start."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    nx, ny = free.shape
    rows, cols, w = [], [], []
    for i, j in np.argwhere(free):
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                p, q = i + a, j + b
                if (a or b) and 0 <= p < nx and 0 <= q < ny and free[p, q]:
                    rows.append(i * ny + j)
                    cols.append(p * ny + q)
                    w.append(res * math.hypot(a, b))
    graph = coo_matrix((w, (rows, cols)), shape=(nx * ny, nx * ny)).tocsr()
    out = np.full(nx * ny, np.inf)
    for (i, j), d0 in zip(starts, start_d, strict=True):
        out = np.minimum(out, d0 + dijkstra(graph, indices=i * ny + j))
    return out.reshape(nx, ny)


@pytest.mark.parametrize("seed", range(8))
def test_travel_distance_matches_scipy_dijkstra(seed):
    rng = np.random.default_rng(seed)
    free = rng.random((23, 17)) < 0.7
    cand = np.argwhere(free)
    starts = cand[rng.choice(len(cand), size=int(rng.integers(1, 4)), replace=False)]
    start_d = rng.uniform(0, 0.5, len(starts))
    got = fr.travel_distance_m(free, starts, start_d, 0.2)
    want = _dijkstra_reference(free, starts, start_d, 0.2)
    assert np.array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=1e-9)
    assert np.isinf(got[~free]).all()


def test_travel_distance_checks_its_inputs():
    free = np.ones((4, 4), bool)
    free[1, 1] = False
    assert np.isinf(fr.travel_distance_m(free, np.zeros((0, 2)), np.zeros(0), 0.2)).all()
    for starts, d in (([[1, 1]], [0.0]), ([[4, 0]], [0.0]), ([[0, 0]], [-1.0]), ([[0, 0]], [])):
        with pytest.raises(ValueError):
            fr.travel_distance_m(free, starts, d, 0.2)
