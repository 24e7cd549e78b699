"""The risk-aware planner (planner.risk): enter costs from a node's class distribution in every
mode against a slow per-node reference, paths exact against Dijkstra on those costs, today's paths
bit for bit when the distribution is certain or absent, and the worked example of docs/risk.md."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.planner import RISK_MODES, Planner
from smana.services.planner.reference import dijkstra_cost
from tests.support.enter_cost_reference import cvar, risk_enter_costs

# The garden's classes plus a flat class that must not be entered (infinite cost, not an obstacle)
WATER = 9
CLASSES = ClassTable.from_dict(
    {
        "name": "garden-water",
        "class": [
            {"id": 0, "name": "unknown", "kind": "unknown"},
            {"id": 1, "name": "grass", "kind": "traversable", "cost": 2.0},
            {"id": 2, "name": "terrain", "kind": "traversable", "cost": 1.0},
            {"id": 4, "name": "hedge", "kind": "obstacle"},
            {"id": WATER, "name": "water", "kind": "traversable", "cost": float("inf")},
        ],
    }
)
GRASS, TERRAIN, HEDGE = 1, 2, 4


def make_grid(labels, heights, flags, risk=None, tile=8) -> NavGrid:
    """A grid of the dense arrays; with `risk` = (alt, p_label, p_alt) its risk layers too."""
    grid = NavGrid((0.0, 0.0), labels.shape, 0.2, tile_size=tile)
    cells = np.argwhere(np.ones(labels.shape, bool))
    risk = None if risk is None else [r.ravel() for r in risk]
    grid.apply_patch(cells, labels.ravel(), heights.ravel(), flags.ravel(), risk=risk)
    return grid


def random_world(rng, n=24, m=20, certain=False):
    labels = rng.choice(
        [GRASS, TERRAIN, WATER, HEDGE, 0], size=(n, m), p=[0.4, 0.4, 0.08, 0.07, 0.05]
    )
    labels = labels.astype(np.uint16)
    heights = np.cumsum(rng.normal(0, 0.03, size=(n, m)), axis=0).astype(np.float32)
    flags = np.where(labels == HEDGE, FLAG_OBSTACLE, 0) | FLAG_KNOWN
    flags[rng.random((n, m)) < 0.05] |= FLAG_SAFETY_ZONE
    flags[rng.random((n, m)) < 0.08] = 0  # unknown nodes
    flags = flags.astype(np.uint8)
    # every kind of second class: none, grass, terrain, water, a hedge, an id outside the table
    alt = rng.choice([0, GRASS, TERRAIN, WATER, HEDGE, 200], size=(n, m)).astype(np.uint16)
    p_label = rng.integers(0, 256, size=(n, m)).astype(np.uint8)
    p_label[rng.random((n, m)) < 0.3] = 255
    if certain:
        p_label[:] = 255
    p_alt = rng.integers(0, 256, size=(n, m)).astype(np.uint8)  # may sum past 255: clipped
    for c in ((0, 0), (n - 1, m - 1)):
        labels[c], flags[c], p_label[c] = TERRAIN, FLAG_KNOWN, 255
    return labels, heights, flags, (alt, p_label, p_alt)


def random_config(rng, mode) -> PlannerConfig:
    return PlannerConfig(
        h_f=float(rng.uniform(0, 0.5)),
        t_f=float(rng.uniform(0.2, 1.5)),
        max_step_m=0.15,
        unknown_cost=float(rng.uniform(0, 5)),
        risk=mode,
        risk_alpha=float(rng.uniform(0.02, 1.0)),
        max_risk=float(rng.uniform(0, 0.6)),
        risk_forbidden_cost=float(rng.uniform(3, 40)),
        risk_other_forbidden=float(rng.uniform(0, 1)),
    )


@pytest.mark.parametrize("mode", RISK_MODES)
def test_every_mode_exact_against_the_reference(mode):
    """The kernel's enter costs equal the per-node reference on random distributions (every
    kind of second class, unnamed mass, probabilities summing past 1), and the path found costs
    what Dijkstra finds on the reference's costs."""
    rng = np.random.default_rng(RISK_MODES.index(mode))
    for trial in range(6):
        labels, heights, flags, risk = random_world(rng)
        config = random_config(rng, mode)
        allow_unknown = bool(trial % 2)
        planner = Planner(make_grid(labels, heights, flags, risk), CLASSES, config)
        r = planner.plan((0.1, 0.1), (4.7, 3.9), allow_unknown=allow_unknown)
        want = risk_enter_costs(labels, flags, *risk, CLASSES, config, allow_unknown)
        got = planner._enter_cache[0]
        assert (np.isinf(got) == np.isinf(want)).all()
        finite = np.isfinite(want)
        np.testing.assert_allclose(got[finite], want[finite], rtol=1e-12)
        known_h = np.where(flags & FLAG_KNOWN, heights, np.nan)  # the planner's view
        best = dijkstra_cost(want, known_h, (0, 0), (23, 19), 0.2, config.h_f, 0.15)
        if np.isfinite(best):
            assert r.ok and r.cost_total == pytest.approx(best, rel=1e-9)
        else:
            assert not r.ok and r.error == "unreachable"


@pytest.mark.parametrize("mode", RISK_MODES)
def test_certain_or_absent_distributions_give_todays_paths_bit_for_bit(mode):
    """A graph without risk layers, or with every label certain (p_label 255, whatever the
    second class says), gives the very paths and costs of the planner without risk."""
    rng = np.random.default_rng(10 + RISK_MODES.index(mode))
    for _ in range(4):
        labels, heights, flags, risk = random_world(rng, certain=True)
        config = random_config(rng, mode)
        plain = Planner(make_grid(labels, heights, flags), CLASSES, dataclasses.replace(config))
        today = plain.plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True, risk="expected")
        for grid in (make_grid(labels, heights, flags), make_grid(labels, heights, flags, risk)):
            r = Planner(grid, CLASSES, config).plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True)
            assert r.ok == today.ok and r.cost_total == today.cost_total
            np.testing.assert_array_equal(r.cells, today.cells)


def test_label_mode_ignores_the_distribution_bit_for_bit():
    """risk "label" on a graph of doubtful nodes plans exactly as the planner without the layers."""
    rng = np.random.default_rng(30)
    for _ in range(3):
        labels, heights, flags, risk = random_world(rng)
        config = random_config(rng, "label")
        plain = Planner(make_grid(labels, heights, flags), CLASSES, config)
        today = plain.plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True)
        grid = make_grid(labels, heights, flags, risk)
        r = Planner(grid, CLASSES, config).plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True)
        assert r.ok == today.ok and r.cost_total == today.cost_total
        np.testing.assert_array_equal(r.cells, today.cells)


def one_node(p_label, alt, p_alt, **config):
    """Enter cost of one grass node with the given distribution, beside certain terrain."""
    labels = np.array([[TERRAIN, GRASS]], np.uint16)
    flags = np.full((1, 2), FLAG_KNOWN, np.uint8)
    risk = (
        np.array([[0, alt]], np.uint16),
        np.array([[255, p_label]], np.uint8),
        np.array([[0, p_alt]], np.uint8),
    )
    grid = make_grid(labels, np.zeros((1, 2), np.float32), flags, risk)
    r = Planner(grid, CLASSES, PlannerConfig(**config)).plan((0.1, 0.1), (0.1, 0.3))
    return r.cost_traversability if r.ok else np.inf


def test_worked_example_60_percent_grass_40_percent_water():
    """docs/risk.md: a node 60 % grass, 40 % water; t_f 0.8, grass T 2, water priced at 20."""
    node = (153, WATER, 102)  # 0.6 and 0.4 x 255
    assert one_node(*node, risk="expected") == pytest.approx(0.8 * (0.6 * 2 + 0.4 * 20))  # 7.36
    assert one_node(*node, risk="cvar", risk_alpha=0.2) == pytest.approx(0.8 * 20)  # 16
    assert one_node(*node, risk="cvar", risk_alpha=0.5) == pytest.approx(
        0.8 * (0.4 * 20 + 0.1 * 2) / 0.5  # 13.12
    )
    assert one_node(*node, risk="chance", max_risk=0.1) == np.inf
    assert one_node(*node, risk="chance", max_risk=0.4) == pytest.approx(7.36)
    # without the layers (or certain), or under "label", it is planned as grass: 0.8 x 2
    assert one_node(*node, risk="label") == pytest.approx(1.6)
    assert one_node(255, WATER, 102, risk="cvar") == pytest.approx(1.6)
    # unnamed mass: 90 % grass and 10 % nobody knows what, priced at unknown_cost 2 in expected,
    # counted as forbidden in the chance constraint as risk_other_forbidden says
    assert one_node(230, 0, 0, risk="expected") == pytest.approx(1.6)
    assert one_node(230, 0, 0, risk="chance", max_risk=0.05) == np.inf
    assert one_node(230, 0, 0, risk="chance", max_risk=0.05, risk_other_forbidden=0.2) < np.inf


def test_cvar_at_alpha_one_is_the_expected_cost_and_rises_as_alpha_falls():
    rng = np.random.default_rng(5)
    for _ in range(20):
        pl = int(rng.integers(0, 255))
        pa = int(rng.integers(0, 256 - pl))
        alt = int(rng.choice([0, TERRAIN, WATER]))
        expected = one_node(pl, alt, pa, risk="expected")
        assert one_node(pl, alt, pa, risk="cvar", risk_alpha=1.0) == pytest.approx(expected)
        costs = [one_node(pl, alt, pa, risk="cvar", risk_alpha=a) for a in (0.9, 0.5, 0.1)]
        tol = 1e-12 * expected
        assert expected <= costs[0] + tol
        assert all(a <= b + tol for a, b in zip(costs, costs[1:], strict=False))


def test_reference_cvar_by_hand():
    assert cvar([(10.0, 0.25), (2.0, 0.75)], 0.5) == pytest.approx((2.5 + 0.5) / 0.5)
    assert cvar([(10.0, 0.25), (2.0, 0.75)], 1.0) == pytest.approx(4.0)
    assert cvar([(10.0, 0.25), (2.0, 0.75)], 0.1) == pytest.approx(10.0)


def band_world():
    """Terrain 30 x 30 with a band of doubtful grass (90 % grass, 10 % water) across x = 2.8 m
    for y < 5 m; the way round goes past its end."""
    labels = np.full((30, 30), TERRAIN, np.uint16)
    labels[14:16, :25] = GRASS
    p_label = np.full((30, 30), 255, np.uint8)
    p_label[14:16, :25] = 230
    alt = np.where(p_label < 255, WATER, 0).astype(np.uint16)
    p_alt = np.where(p_label < 255, 25, 0).astype(np.uint8)
    flags = np.full((30, 30), FLAG_KNOWN, np.uint8)
    return make_grid(labels, np.zeros((30, 30), np.float32), flags, (alt, p_label, p_alt))


def test_chance_constraint_goes_round_what_expected_crosses():
    grid = band_world()
    ends = ((1.0, 0.5), (5.0, 0.5))

    def band_nodes(r):
        return int(((r.cells[:, 0] >= 14) & (r.cells[:, 0] < 16) & (r.cells[:, 1] < 25)).sum())

    crossed = Planner(grid, CLASSES).plan(*ends)
    assert crossed.ok and band_nodes(crossed) == 2
    safe = Planner(grid, CLASSES, PlannerConfig(risk="chance", max_risk=0.05)).plan(*ends)
    assert safe.ok and band_nodes(safe) == 0 and safe.cost_distance > 2 * crossed.cost_distance
    bold = Planner(grid, CLASSES, PlannerConfig(risk="chance", max_risk=0.2)).plan(*ends)
    assert bold.ok and band_nodes(bold) == 2
    # a goal inside the band is refused, saying why
    r = Planner(grid, CLASSES, PlannerConfig(risk="chance", max_risk=0.05)).plan(
        (1.0, 0.5), (2.9, 0.5)
    )
    assert not r.ok and r.error == "goal_blocked" and "max_risk" in r.message


def test_per_query_mode_and_a_bad_one():
    grid = band_world()
    planner = Planner(grid, CLASSES, PlannerConfig(max_risk=0.05))  # risk "expected"
    assert planner.plan((1.0, 0.5), (5.0, 0.5)).cost_distance < 4.1  # across the band
    r = planner.plan((1.0, 0.5), (5.0, 0.5), risk="chance")  # P(water) 0.098 > 0.05: round it
    assert r.ok and r.cost_distance > 8.0
    bad = planner.plan((1.0, 0.5), (5.0, 0.5), risk="worst")
    assert not bad.ok and bad.error == "malformed" and "planner.risk" in bad.message
    assert "\n" not in bad.message


@pytest.mark.parametrize("mode", RISK_MODES)
def test_patched_distributions_refresh_the_cached_costs(mode):
    """After a patch of the risk layers only the patched nodes are refreshed, and the costs equal
    the reference's on the whole new graph (the incremental path of the cache)."""
    rng = np.random.default_rng(20 + RISK_MODES.index(mode))
    labels, heights, flags, risk = random_world(rng, 40, 40)
    config = random_config(rng, mode)
    grid = make_grid(labels, heights, flags, risk)
    planner = Planner(grid, CLASSES, config)
    planner.plan((0.1, 0.1), (7.9, 7.9))
    cells = np.argwhere(np.ones((3, 4), bool)) + (10, 12)
    alt, p_label, p_alt = (a.copy() for a in risk)
    alt[10:13, 12:16] = WATER
    p_label[10:13, 12:16] = rng.integers(100, 255, size=(3, 4))
    p_alt[10:13, 12:16] = 255 - p_label[10:13, 12:16]
    risk = [a[10:13, 12:16].ravel() for a in (alt, p_label, p_alt)]
    grid.apply_patch(cells, *grid.read_cells(cells), risk=risk)
    assert grid.changes_since(planner._enter_key[0]) is not None  # the incremental path runs
    planner.plan((0.1, 0.1), (7.9, 7.9))
    want = risk_enter_costs(labels, flags, alt, p_label, p_alt, CLASSES, config)
    got = planner._enter_cache[0]
    assert (np.isinf(got) == np.isinf(want)).all()
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], rtol=1e-12)


def test_the_default_risk_is_label_so_doubtful_graphs_plan_as_before():
    """planner.risk defaults to "label" until the risk experiment chooses a mode: a default
    Planner on a graph of doubtful nodes plans exactly as on the graph without the layers (the
    paper's experiments' data regenerate identically), and "expected" would not here."""
    assert PlannerConfig().risk == "label"
    rng = np.random.default_rng(31)
    changed = 0
    for _ in range(3):
        labels, heights, flags, risk = random_world(rng)
        today = Planner(make_grid(labels, heights, flags), CLASSES).plan(
            (0.1, 0.1), (4.7, 3.9), allow_unknown=True
        )
        grid = make_grid(labels, heights, flags, risk)
        r = Planner(grid, CLASSES).plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True)
        assert r.ok == today.ok and r.cost_total == today.cost_total
        np.testing.assert_array_equal(r.cells, today.cells)
        e = Planner(grid, CLASSES).plan((0.1, 0.1), (4.7, 3.9), allow_unknown=True, risk="expected")
        changed += e.ok != today.ok or e.cost_total != today.cost_total
    assert changed  # the graphs are doubtful enough for the mode to matter


@pytest.mark.parametrize("mode", RISK_MODES)
def test_the_risk_pass_reads_the_layers_in_place_across_tiles_and_offsets(mode):
    """The risk kernels read the grid's tile pools directly: a known area that starts off the
    tile grid, inside bounds with unallocated tiles (read as unknown and certain), a window
    grown past it (allow_unknown), every tile size; the costs equal the reference's on the
    window, after a patch too."""
    rng = np.random.default_rng(40 + RISK_MODES.index(mode))
    for tile in (4, 8, 16):
        labels, heights, flags, risk = random_world(rng, 37, 29)
        config = random_config(rng, mode)
        grid = NavGrid((0.0, 0.0), (70, 60), 0.2, tile_size=tile)
        at = np.array([13 + tile // 2, 9 + tile // 3])
        cells = np.argwhere(np.ones(labels.shape, bool)) + at
        grid.apply_patch(
            cells, labels.ravel(), heights.ravel(), flags.ravel(), risk=[r.ravel() for r in risk]
        )
        planner = Planner(grid, CLASSES, config)
        a, b = grid.cell_centre(*at), grid.cell_centre(*(at + (36, 28)))
        for allow_unknown in (False, True):
            planner.plan(a, b, allow_unknown=allow_unknown)
            x0, y0, x1, y1 = planner._cache_key[1]
            assert (x0, y0) != (0, 0) or allow_unknown  # the window starts inside the grid
            w_labels, _, w_flags = grid.box(x0, y0, x1, y1)
            window = np.argwhere(np.ones((x1 - x0, y1 - y0), bool)) + (x0, y0)
            w_risk = [r.reshape(x1 - x0, y1 - y0) for r in grid.read_risk(window)]
            want = risk_enter_costs(w_labels, w_flags, *w_risk, CLASSES, config, allow_unknown)
            got = planner._enter_cache[0]
            assert got.shape == want.shape and (np.isinf(got) == np.isinf(want)).all()
            finite = np.isfinite(want)
            np.testing.assert_allclose(got[finite], want[finite], rtol=1e-12)
            # the minimum is taken before the clearance cost (which only adds): a lower bound
            plain = dataclasses.replace(config, clearance_cost=0.0)
            low = risk_enter_costs(w_labels, w_flags, *w_risk, CLASSES, plain, allow_unknown)
            assert planner._enter_cache[1] == pytest.approx(low[finite].min(), rel=1e-12)
        # a patch of distributions on a few nodes: the incremental path, then the same check
        few = cells[rng.choice(len(cells), 30, replace=False)]
        new_risk = (
            rng.choice([0, GRASS, TERRAIN, WATER, 200], 30).astype(np.uint16),
            rng.integers(0, 256, 30).astype(np.uint8),
            rng.integers(0, 256, 30).astype(np.uint8),
        )
        grid.apply_patch(few, *grid.read_cells(few), risk=new_risk)
        assert grid.changes_since(planner._enter_key[0]) is not None
        planner.plan(a, b, allow_unknown=True)
        x0, y0, x1, y1 = planner._cache_key[1]
        w_labels, _, w_flags = grid.box(x0, y0, x1, y1)
        window = np.argwhere(np.ones((x1 - x0, y1 - y0), bool)) + (x0, y0)
        w_risk = [r.reshape(x1 - x0, y1 - y0) for r in grid.read_risk(window)]
        want = risk_enter_costs(w_labels, w_flags, *w_risk, CLASSES, config, True)
        got = planner._enter_cache[0]
        assert (np.isinf(got) == np.isinf(want)).all()
        finite = np.isfinite(want)
        np.testing.assert_allclose(got[finite], want[finite], rtol=1e-12)


def _divided_risk_cost(c_label, alt, pl, pa, lut, model):
    """A doubtful node's enter cost as the kernels computed it before their tables: a division
    per probability and the second class looked up in the cost table (Python floats are the
    same IEEE doubles, with no fused multiply-add)."""
    named = 0 < alt < len(lut)
    pa = min(pa, 255 - pl) if named else 0
    p1, p2, r = pl / 255, pa / 255, (255 - pl - pa) / 255
    c2 = float(lut[alt]) if named else 0.0
    forbidden = c2 == np.inf
    if forbidden:
        c2 = model.forbidden_cost
    if model.mode == 2 and (p2 if forbidden else 0.0) + r * model.other_forbidden > model.max_risk:
        return np.inf
    if model.mode == 1:
        atoms = [(c_label, p1), (c2, p2), (model.other_cost, r)]
        for a, b in ((0, 1), (1, 2), (0, 1)):  # the kernel's three compare-and-swaps
            if atoms[b][0] > atoms[a][0]:
                atoms[a], atoms[b] = atoms[b], atoms[a]
        (c0, q0), (c1, q1), (c2_, q2) = atoms
        take0 = min(q0, model.alpha)
        take1 = min(q1, model.alpha - take0)
        take2 = max(0.0, model.alpha - take0 - take1)
        return (take0 * c0 + take1 * c1 + take2 * c2_) / model.alpha
    return p1 * c_label + p2 * c2 + r * model.other_cost


@pytest.mark.parametrize("mode", ["expected", "cvar", "chance"])
def test_the_tables_give_the_divided_costs_bit_for_bit(mode):
    """The risk pass reads k / 255 and the second class's cost from tables: every doubtful
    node's cost equals, to the bit, the per-node divisions and look-ups it replaced."""
    from smana.services.planner.planner import risk_model

    rng = np.random.default_rng(50 + RISK_MODES.index(mode))
    for _ in range(3):
        labels, heights, flags, risk = random_world(rng, 40, 40)
        # the risk tables alone: the clearance cost (the same added to both) off
        config = dataclasses.replace(random_config(rng, mode), clearance_cost=0.0)
        planner = Planner(make_grid(labels, heights, flags, risk), CLASSES, config)
        planner.plan((0.1, 0.1), (7.9, 7.9))
        got = planner._enter_cache[0]
        plain = Planner(make_grid(labels, heights, flags), CLASSES, config)
        plain.plan((0.1, 0.1), (7.9, 7.9))
        c_label = plain._enter_cache[0]  # t_f * T(label), or closed
        lut = np.where(np.isfinite(CLASSES.cost_lut), CLASSES.cost_lut * config.t_f, np.inf)
        model = risk_model(config)
        alt, p_label, p_alt = risk
        doubtful = 0
        for (i, j), c in np.ndenumerate(c_label):
            want = c
            if np.isfinite(c) and flags[i, j] & FLAG_KNOWN and p_label[i, j] < 255:
                args = (int(alt[i, j]), int(p_label[i, j]), int(p_alt[i, j]))
                want = _divided_risk_cost(float(c), *args, lut, model)
                doubtful += 1
            assert got[i, j] == want or (np.isnan(want) and np.isnan(got[i, j])), (i, j)
        assert doubtful > 500
