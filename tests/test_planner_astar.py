"""A* kernel against scipy's Dijkstra on the same graph (the slow, obvious reference)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smana.services.planner.astar import astar, path_costs, search
from smana.services.planner.reference import dijkstra_cost


@st.composite
def grids(draw):
    nx = draw(st.integers(1, 12))
    ny = draw(st.integers(1, 12))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    # Enter costs like t_f * T(l): terrain 0.8, grass 1.6, free 0 (t_f = 0), blocked.
    p_block = draw(st.sampled_from([0.0, 0.15, 0.35]))
    costs = rng.choice([0.0, 0.8, 1.6, 3.2], size=(nx, ny))
    costs[rng.random((nx, ny)) < p_block] = np.inf
    heights = rng.normal(0.0, draw(st.sampled_from([0.0, 0.1, 0.4])), size=(nx, ny))
    heights[rng.random((nx, ny)) < 0.1] = np.nan  # unknown heights
    start = (draw(st.integers(0, nx - 1)), draw(st.integers(0, ny - 1)))
    goal = (draw(st.integers(0, nx - 1)), draw(st.integers(0, ny - 1)))
    return costs, heights, start, goal


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    case=grids(),
    res=st.sampled_from([0.1, 0.2, 0.5]),
    h_f=st.sampled_from([0.0, 0.1, 2.0]),
    max_step=st.sampled_from([None, 0.15, 0.5]),
    heuristic=st.sampled_from(["euclidean", "octile"]),
)
def test_astar_cost_equals_dijkstra(case, res, h_f, max_step, heuristic):
    costs, heights, start, goal = case
    got = astar(costs, heights, start, goal, res, h_f, max_step, heuristic)
    want = dijkstra_cost(costs, heights, start, goal, res, h_f, max_step)
    if math.isinf(want):
        assert not got.found and len(got.cells) == 0
        return
    assert got.cost == pytest.approx(want, rel=1e-9, abs=1e-12)
    cells = got.cells
    assert tuple(cells[0]) == start and tuple(cells[-1]) == goal
    steps = np.abs(np.diff(cells, axis=0))
    assert (steps.max(axis=1) == 1).all()  # 8-neighbours, no repeats
    assert np.isfinite(costs[cells[1:, 0], cells[1:, 1]]).all()
    dh = np.abs(np.diff(heights[cells[:, 0], cells[:, 1]]))
    if max_step is not None:
        assert not (dh[~np.isnan(dh)] > max_step).any()
    # The breakdown recomputed edge by edge adds up to the cost A* accumulated.
    assert sum(path_costs(cells, costs, heights, res, h_f)) == pytest.approx(got.cost, rel=1e-9)


def test_heuristics_expand_no_more_than_dijkstra_and_octile_less():
    rng = np.random.default_rng(7)
    costs = rng.choice([0.8, 1.6], size=(120, 120))
    costs[rng.random(costs.shape) < 0.2] = np.inf
    costs[0, 0] = costs[-1, -1] = 0.8
    heights = np.zeros_like(costs)
    e = astar(costs, heights, (0, 0), (119, 119), 0.2, heuristic="euclidean")
    o = astar(costs, heights, (0, 0), (119, 119), 0.2, heuristic="octile")
    assert e.cost == pytest.approx(o.cost, rel=1e-12)
    assert o.nodes_expanded < e.nodes_expanded <= np.isfinite(costs).sum()


def test_max_step_height_blocks_a_cliff_and_the_path_goes_round():
    costs = np.full((9, 9), 0.8)
    heights = np.zeros((9, 9))
    heights[4, :8] = 1.0  # a wall of 1 m steps with one gap at the end
    r = astar(costs, heights, (0, 4), (8, 4), 0.2, h_f=0.1, max_step_m=0.3)
    assert r.found and (r.cells[:, 1] == 8).any()
    r2 = astar(costs, heights, (0, 4), (8, 4), 0.2, h_f=0.1, max_step_m=None)
    assert r2.cost < r.cost and not (r2.cells[:, 1] == 8).any()


def test_bad_inputs_raise():
    c, h = np.zeros((3, 3)), np.zeros((3, 3))
    with pytest.raises(ValueError, match="outside"):
        astar(c, h, (0, 0), (3, 0), 0.2)
    with pytest.raises(ValueError, match="shape"):
        astar(c, np.zeros((2, 3)), (0, 0), (1, 1), 0.2)
    with pytest.raises(ValueError, match="enter_cost"):
        astar(np.full((3, 3), -1.0), h, (0, 0), (1, 1), 0.2)
    with pytest.raises(ValueError, match="heuristic"):
        astar(c, h, (0, 0), (1, 1), 0.2, heuristic="manhattan")
    with pytest.raises(ValueError, match="max_step"):
        astar(c, h, (0, 0), (1, 1), 0.2, max_step_m=0.0)


@pytest.mark.parametrize("seed", range(8))
def test_many_ties_and_improvements_stay_exact(seed):
    """Equal f everywhere (pyastar2d's cost: weights entered, no distance term, as the benchmark
    runs it) and improved open nodes: the stack tier and decrease-key paths, against Dijkstra."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 70))
    w = rng.choice([1.0, 1.0, 1.8, 2.0], size=(n, n))
    w[rng.random((n, n)) < 0.2 * (seed % 3)] = np.inf
    heights = np.zeros((n, n))
    start, goal = (0, 0), (n - 1, int(rng.integers(0, n)))
    w[start] = w[goal] = 1.0
    finite = w[np.isfinite(w)]
    for res, h_f in ((0.0, 0.0), (0.2, 0.0)):
        got = search(w, heights, start, goal, res, h_f, np.inf, "octile", float(finite.min()))
        want = dijkstra_cost(w, heights, start, goal, res, h_f)
        if math.isinf(want):
            assert not got.found
            continue
        assert got.cost == pytest.approx(want, rel=1e-12)
        steps = np.diff(got.cells, axis=0)
        dist = res * np.hypot(steps[:, 0], steps[:, 1]).sum()
        assert w[got.cells[1:, 0], got.cells[1:, 1]].sum() + dist == pytest.approx(got.cost)
