"""Path queries on a grid: the paper's grass detour, unknown space, cost breakdown, every error."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, NavGrid
from smana.services.navgraph.graph import NavGraph
from smana.services.planner.planner import Planner
from smana.services.planner.reference import dijkstra_cost
from tests.support.enter_cost_reference import add_clearance

CLASSES = ClassTable.load("garden3drms")
GRASS, TERRAIN, HEDGE = 1, 2, 4


def dense_grid(labels, heights=None, known=None, res=0.2, tile=16):
    nx, ny = labels.shape
    grid = NavGrid((0.0, 0.0), (nx, ny), res, tile_size=tile)
    heights = np.zeros((nx, ny)) if heights is None else heights
    known = np.ones((nx, ny), bool) if known is None else known
    cells = np.argwhere(known)
    lab = labels[known]
    flags = FLAG_KNOWN | (CLASSES.obstacle_lut[lab] * FLAG_OBSTACLE)
    grid.apply_patch(cells, lab, heights[known], flags.astype(np.uint8))
    return grid


def test_grass_detour_once_grass_costs_more():
    """Paper 4.3: raising the grass cost makes the planner go round a grass patch on terrain."""
    labels = np.full((40, 30), TERRAIN, np.uint16)
    labels[19:21, :14] = GRASS
    planner = Planner(dense_grid(labels), CLASSES)
    across = planner.plan((1.0, 0.5), (7.0, 0.5))  # default grass cost 2
    assert across.ok and across.label_share["grass"] > 0
    around = planner.plan((1.0, 0.5), (7.0, 0.5), class_costs={GRASS: 4.0})
    assert around.ok and "grass" not in around.label_share
    assert around.cost_distance > across.cost_distance  # longer, but cheaper at the new cost
    assert around.path[:, 1].max() > 2.8
    # The straight line crosses two grass nodes: at cost 4 it would cost 2 * 0.8 * 2 more.
    assert around.cost_total < across.cost_total + 2 * 0.8 * 2.0
    assert around.cost_total > across.cost_total


def test_cost_breakdown_adds_up_and_matches_dijkstra():
    rng = np.random.default_rng(3)
    labels = rng.choice([GRASS, TERRAIN, HEDGE], size=(30, 25), p=[0.4, 0.5, 0.1]).astype(np.uint16)
    labels[:2, :2] = labels[-2:, -2:] = TERRAIN
    # float32 like the grid stores them, so both searches see the same heights.
    heights = np.cumsum(rng.normal(0, 0.03, size=(30, 25)), axis=0).astype(np.float32)
    grid = dense_grid(labels, heights)
    planner = Planner(grid, CLASSES, PlannerConfig(h_f=0.5, t_f=0.8, max_step_m=0.1))
    r = planner.plan((0.1, 0.1), (5.9, 4.9))
    assert r.ok, r.message
    parts = r.cost_distance + r.cost_height + r.cost_traversability
    assert parts == pytest.approx(r.cost_total, rel=1e-9)
    enter = np.where(labels == HEDGE, np.inf, 0.8 * CLASSES.cost_lut[np.minimum(labels, 8)])
    # plus the clearance cost beside the hedges' nodes, node by node
    flags = np.asarray(grid.box(0, 0, 30, 25)[2])
    enter = add_clearance(enter, flags, planner.config, 0.2)
    want = dijkstra_cost(enter, heights, (0, 0), (29, 24), 0.2, 0.5, 0.1)
    assert r.cost_total == pytest.approx(want, rel=1e-9)
    assert sum(r.label_share.values()) == pytest.approx(1.0)
    np.testing.assert_allclose(r.path[0, :2], [0.1, 0.1], atol=1e-6)
    np.testing.assert_allclose(r.path[:, 2], heights[r.cells[:, 0], r.cells[:, 1]], atol=1e-6)


def test_unknown_space_only_when_asked():
    labels = np.full((20, 20), TERRAIN, np.uint16)
    known = np.ones((20, 20), bool)
    known[8:12, :] = False  # an unseen band across the map
    planner = Planner(dense_grid(labels, known=known), CLASSES)
    no = planner.plan((0.5, 2.0), (3.5, 2.0))
    assert not no.ok and no.error == "unreachable"
    yes = planner.plan((0.5, 2.0), (3.5, 2.0), allow_unknown=True, unknown_cost=3.0)
    assert yes.ok and yes.label_share["unknown"] == pytest.approx(4 / 16)
    # 15 steps of 0.2 m, entering 11 terrain nodes at 0.8 * 1 and 4 unknown at 0.8 * 3.
    assert yes.cost_traversability == pytest.approx(0.8 * (11 + 4 * 3.0))
    assert yes.cost_distance == pytest.approx(3.0)
    goal_unknown = planner.plan((0.5, 2.0), (2.0, 2.0))
    assert goal_unknown.error == "goal_blocked" and "unknown" in goal_unknown.message
    assert planner.plan((0.5, 2.0), (2.0, 2.0), allow_unknown=True).ok


def obstacle_graph():
    g = NavGraph(
        CLASSES,
        NavgraphConfig(
            bounds_min_xy=[0, 0],
            bounds_max_xy=[4, 4],
            resolution_m=0.2,
            robot_radius_m=0.4,
            tile_size=8,
        ),
    )
    xy = np.stack(np.meshgrid(np.arange(40), np.arange(40), indexing="ij"), -1).reshape(-1, 2)
    vox = np.column_stack([(xy + 0.5) * 0.1, np.full(len(xy), 0.05)]).astype(np.float32)
    g.integrate(vox, np.full(len(vox), TERRAIN, np.uint16), np.ones(len(vox), np.uint8))
    # A hedge across the middle from y = 0 to y = 3 m, one node thick.
    hedge = np.array([[2.05, 0.05 + 0.1 * k, 0.45] for k in range(30)], np.float32)
    g.integrate(hedge, np.full(len(hedge), HEDGE, np.uint16), np.ones(len(hedge), np.uint8))
    return g


def test_every_error_reply():
    g = obstacle_graph()
    planner = Planner(g.grid, CLASSES)
    empty = Planner(NavGrid((0, 0), (10, 10), 0.2), CLASSES)
    cases = {
        "no_graph": empty.plan((0.5, 0.5), (1.0, 1.0)),
        "out_of_bounds": planner.plan((0.5, 0.5), (4.5, 1.0)),
        "start_blocked": planner.plan((2.1, 1.0), (0.5, 0.5)),
        "goal_blocked": planner.plan((0.5, 0.5), (1.8, 1.0)),
        "malformed": planner.plan((np.nan, 0.5), (1.0, 1.0)),
    }
    for code, r in cases.items():
        assert not r.ok and r.error == code, (code, r)
    assert "obstacle" in cases["start_blocked"].message
    assert "safety zone" in cases["goal_blocked"].message
    assert "outside the graph bounds" in cases["out_of_bounds"].message
    for bad in [{"class_costs": {HEDGE: 1.0}}, {"h_f": -1.0}, {"max_step_m": 0.0}]:
        assert planner.plan((0.5, 0.5), (1.0, 1.0), **bad).error == "malformed"
    assert planner.plan((0.5, 0.5, 0.0, 1.0), (1.0, 1.0)).error == "malformed"
    # Nearest free node: brute force over every enterable node.
    r = cases["goal_blocked"]
    labels, _, flags = g.grid.box(0, 0, 20, 20)
    free = np.argwhere(((flags & 6) == 0) & (flags & 1).astype(bool))
    d = np.hypot(*(free - np.array([9, 5])).T)
    assert np.hypot(*(g.grid.world_to_cell(r.nearest_free)[:2] - np.array([9, 5]))) == d.min()
    assert "nearest free node" in r.message
    # The hedge stops 1 m short of the top: a path goes round it; closing the gap makes the
    # goal unreachable.
    ok = planner.plan((0.5, 0.5), (3.5, 0.5))
    assert ok.ok and ok.path[:, 1].max() > 3.0
    wall = np.array([[2.05, 3.05 + 0.1 * k, 0.45] for k in range(10)], np.float32)
    g.integrate(wall, np.full(len(wall), HEDGE, np.uint16), np.ones(len(wall), np.uint8))
    r = planner.plan((0.5, 0.5), (3.5, 0.5))
    assert not r.ok and r.error == "unreachable"


def test_window_cache_follows_grid_changes():
    labels = np.full((16, 16), TERRAIN, np.uint16)
    grid = dense_grid(labels)
    planner = Planner(grid, CLASSES)
    assert planner.plan((0.1, 0.1), (3.1, 0.1)).cost_distance == pytest.approx(3.0)
    grid.apply_patch(np.array([[8, 0], [8, 1]]), [HEDGE, HEDGE], [0, 0], [3, 3])
    r = planner.plan((0.1, 0.1), (3.1, 0.1))
    assert r.ok and r.cost_distance > 3.0


def test_a_doubtful_wall_is_dear_but_passable():
    """Doubtful nodes (an obstacle class the graph has not confirmed) cost `doubtful_cost`: a path
    goes round a doubtful wall when the detour is cheaper, and through it when there is none;
    the cost matches Dijkstra over the same enter costs."""
    from smana.common.navgrid import FLAG_DOUBTFUL

    labels = np.full((30, 20), TERRAIN, np.uint16)
    labels[14:16, :] = HEDGE  # a wall of hedge labels across the whole width
    nx, ny = labels.shape
    grid = NavGrid((0.0, 0.0), (nx, ny), 0.2, tile_size=16)
    flags = np.full(labels.shape, FLAG_KNOWN, np.uint8)
    flags[labels == HEDGE] |= FLAG_DOUBTFUL
    grid.apply_patch(np.argwhere(flags > 0), labels.ravel(), np.zeros(nx * ny), flags.ravel())
    assert PlannerConfig().doubtful_cost == 10.0
    assert CLASSES.cost_lut[TERRAIN] == 1.0 and CLASSES.cost_lut[GRASS] == 2.0
    planner = Planner(grid, CLASSES, PlannerConfig())
    r = planner.plan((0.5, 2.0), (5.5, 2.0))
    assert r.ok, r.message
    enter = np.where(labels == HEDGE, 0.8 * 10.0, 0.8 * CLASSES.cost_lut[labels])
    want = dijkstra_cost(enter, np.zeros(labels.shape), (2, 10), (27, 10), 0.2, 0.0)
    assert r.cost_total == pytest.approx(want, rel=1e-6)
    # confirmed, the same wall closes the way
    flags[labels == HEDGE] = FLAG_KNOWN | FLAG_OBSTACLE
    grid.apply_patch(np.argwhere(flags > 0), labels.ravel(), np.zeros(nx * ny), flags.ravel())
    assert not Planner(grid, CLASSES).plan((0.5, 2.0), (5.5, 2.0)).ok


def test_paths_keep_off_an_obstacle_where_there_is_room():
    """The clearance cost: along a hedge, with room beside it, a path keeps more than
    `clearance_m` from the hedge; with the cost off it runs along its side. In a passage too
    narrow for that it still goes through (the cost is dear, not closed)."""
    labels = np.full((40, 12), TERRAIN, np.uint16)
    labels[5:35, 0] = HEDGE  # a hedge along x at the bottom edge
    grid = dense_grid(labels)
    start, goal = (0.3, 0.3), (7.7, 0.3)
    hug = Planner(grid, CLASSES, PlannerConfig(clearance_cost=0.0)).plan(start, goal)
    keep = Planner(grid, CLASSES).plan(start, goal)  # clearance 1 over 0.4 m: the defaults
    assert hug.ok and keep.ok
    beside = (hug.cells[:, 0] >= 5) & (hug.cells[:, 0] < 35)
    assert hug.cells[beside, 1].min() == 1  # right beside the hedge
    beside = (keep.cells[:, 0] >= 5) & (keep.cells[:, 0] < 35)
    assert keep.cells[beside, 1].min() >= 3  # beyond the 2-node ring of the clearance cost
    # a passage one node wide between two hedges: dear, still the way
    labels = np.full((40, 3), TERRAIN, np.uint16)
    labels[5:35, 0] = labels[5:35, 2] = HEDGE
    narrow = Planner(dense_grid(labels), CLASSES).plan((0.3, 0.3), (7.7, 0.3))
    assert narrow.ok


def test_an_empty_graph_is_planned_across_as_unknown_ground():
    """With allow_unknown (Nav2's default for its planners) a graph with no node yet is all
    unknown ground: the straight path across it, every node at unknown_cost."""
    empty = Planner(NavGrid((0, 0), (20, 20), 0.2, tile_size=16), CLASSES)
    r = empty.plan((0.5, 0.5), (3.5, 0.5), allow_unknown=True, unknown_cost=2.0)
    assert r.ok and r.label_share == {"unknown": 1.0}, r.message
    assert r.cost_distance == pytest.approx(3.0)
    assert r.cost_traversability == pytest.approx(15 * 0.8 * 2.0)  # t_f * unknown_cost
    assert empty.plan((0.5, 0.5), (3.5, 0.5)).error == "no_graph"


def test_a_start_not_seen_yet_leaves_from_the_nearest_known_free_node():
    """Without allow_unknown, a robot on a node not seen yet (the ground under it at start) is
    planned from the nearest known free node within SNAP_START_M; the path still begins at the
    start. Farther than that, the start stays closed in."""
    labels = np.full((20, 20), TERRAIN, np.uint16)
    known = np.ones((20, 20), bool)
    known[:4, :4] = False  # a hole around the start at node (1, 1)
    planner = Planner(dense_grid(labels, known=known), CLASSES)
    r = planner.plan((0.3, 0.3), (3.5, 3.5))
    assert r.ok, r.message
    np.testing.assert_array_equal(r.cells[0], [1, 1])
    assert known[tuple(r.cells[1])]  # the second node is a known one: the nearest
    d = np.hypot(*(np.argwhere(known) - np.array([1, 1])).T).min()
    assert np.hypot(*(r.cells[1] - np.array([1, 1]))) == pytest.approx(d)
    parts = r.cost_distance + r.cost_height + r.cost_traversability
    assert parts == pytest.approx(r.cost_total, rel=1e-9)
    known[:8, :8] = False  # the nearest known node 1.4 m away: no snap, no path
    far = Planner(dense_grid(labels, known=known), CLASSES).plan((0.3, 0.3), (3.5, 3.5))
    assert not far.ok and far.error == "unreachable"
