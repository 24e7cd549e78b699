"""Issue 29, item 3: "the costmap shows risk". Under `planner.risk` other than "label", the ROS 2
costmaps (OccupancyGrid and nav2_msgs/Costmap) price each node as the planner does, from the
node's label distribution (common/risk.py, held equal here to the planner's per-node reference);
under "label" they are as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE
from smana.common.risk import risk_class_costs
from tests.support.enter_cost_reference import risk_enter_costs

WET = ClassTable.load("garden3drms_wet")
GRASS, TERRAIN, HEDGE, WATER = 1, 2, 4, 9
MODES = [
    {"risk": "label"},
    {"risk": "expected"},
    {"risk": "cvar", "risk_alpha": 0.2},
    {"risk": "cvar", "risk_alpha": 0.7},
    {"risk": "chance", "max_risk": 0.1},
    {"risk": "chance", "max_risk": 0.4, "risk_other_forbidden": 0.5},
]


def _windows(rng, n=40):
    """Random known windows: every class of the wet table as label and as second class, random
    probabilities (certain ones among them), some obstacles and safety zones."""
    labels = rng.choice([0, GRASS, TERRAIN, HEDGE, 5, WATER], (n, n)).astype(np.uint16)
    alt = rng.choice([0, GRASS, TERRAIN, HEDGE, WATER, 40], (n, n)).astype(np.uint16)
    p_label = rng.integers(60, 256, (n, n)).astype(np.uint8)
    p_label[rng.random((n, n)) < 0.2] = 255
    p_alt = rng.integers(0, 256, (n, n)).astype(np.uint8)
    flags = np.full((n, n), FLAG_KNOWN, np.uint8)
    flags[rng.random((n, n)) < 0.05] |= FLAG_OBSTACLE
    flags[rng.random((n, n)) < 0.05] |= FLAG_SAFETY_ZONE
    return labels, flags, alt, p_label, p_alt


@pytest.mark.parametrize("fields", MODES, ids=lambda f: "-".join(map(str, f.values())))
def test_the_costmaps_class_costs_are_the_planners_node_by_node(fields):
    """common/risk.py against services/planner/reference.py (the planner kernels' reference):
    the enter cost of every open node is t_f x the T the costmap shows, closed nodes are inf.
    The planner's clearance cost beside the safety zone is off: the costmap's class costs are
    the classes' (a Nav2 stack inflates in its own inflation layer)."""
    config = dataclasses.replace(PlannerConfig(clearance_cost=0.0), **fields)
    labels, flags, alt, p_label, p_alt = _windows(np.random.default_rng(7))
    want = risk_enter_costs(labels, flags, alt, p_label, p_alt, WET, config)
    got = risk_class_costs(labels, alt, p_label, p_alt, WET.cost_lut, config) * config.t_f
    free = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    assert np.array_equal(np.isinf(got[free]), np.isinf(want[free]))
    ok = free & np.isfinite(want)
    assert ok.sum() > 150  # the comparison covers many open nodes
    np.testing.assert_allclose(got[ok], want[ok], rtol=1e-12, atol=1e-12)


def _grid(risk=True):
    """Three known nodes on one row: terrain (certain), grass (certain), grass 60 % / water 40 %."""
    from smana.common.navgrid import NavGrid

    grid = NavGrid.from_bounds((0.0, 0.0), (2.0, 2.0), 0.5)
    if risk:
        grid.add_risk_layers()
    cells = np.array([[0, 0], [1, 0], [2, 0]])
    labels = np.array([TERRAIN, GRASS, GRASS], np.uint16)
    flags = np.full(3, FLAG_KNOWN, np.uint8)
    dist = (
        np.array([0, 0, WATER], np.uint16),
        np.array([255, 255, 153], np.uint8),  # 153 / 255 = 0.6
        np.array([0, 0, 102], np.uint8),
    )
    grid.apply_patch(cells, labels, np.zeros(3, np.float32), flags, risk=dist if risk else None)
    return grid


def _row(values, grid, cells=((0, 0), (1, 0), (2, 0))):
    """The costmap's values (row-major from the known box's corner, x fastest) at `cells`."""
    ix0, iy0, ix1, iy1 = grid.known_box()
    data = np.asarray(values).reshape(iy1 - iy0, ix1 - ix0)
    return [int(data[j - iy0, i - ix0]) for i, j in cells]


def test_the_costmaps_show_the_planners_risk_mode():
    pytest.importorskip("rosbags")
    from smana.services.ros2 import convert, rmw

    types, lut, grid = rmw.RosTypes(), WET.cost_lut, _grid()

    def both(**fields):
        p = dataclasses.replace(PlannerConfig(), **fields)
        occ = convert.occupancy_grid(types, grid, lut, 1.0, planner=p)
        raw = convert.nav2_costmap(types, grid, lut, 1.0, 1.0, planner=p)
        return _row(occ.data, grid), _row(raw.data, grid)

    # terrain T 1 (the table's cheapest), grass T 2 (its dearest): 0 and the top of the scale
    label = both(risk="label")
    assert label == ([0, 98, 98], [0, 252, 252])  # the doubtful node shows as its label
    assert label == both()  # the default mode
    assert _row(convert.occupancy_grid(types, grid, lut, 1.0).data, grid) == [0, 98, 98]
    # under a risk mode the scale reaches the forbidden mass's T (20): certain nodes sit low
    lo, hi = 1.0, 20.0
    grass = round((2.0 - lo) / (hi - lo) * 98), round((2.0 - lo) / (hi - lo) * 252)
    expected = 0.6 * 2.0 + 0.4 * 20.0  # docs/risk.md's worked example: 9.2
    occ, raw = both(risk="expected")
    assert occ == [0, grass[0], round((expected - lo) / (hi - lo) * 98)]
    assert raw == [0, grass[1], round((expected - lo) / (hi - lo) * 252)]
    assert both(risk="cvar", risk_alpha=0.2) == ([0, grass[0], 98], [0, grass[1], 252])
    assert both(risk="chance", max_risk=0.1) == ([0, grass[0], 100], [0, grass[1], 254])
    # a grid without distributions reads as certain: each node its label's cost
    plain = _grid(risk=False)
    occ = convert.occupancy_grid(types, plain, lut, 1.0, planner=PlannerConfig(risk="chance"))
    assert _row(occ.data, plain) == [0, grass[0], grass[0]]


def test_the_ros2_service_keeps_the_distributions_under_a_risk_mode():
    """The ros2 service's graph copy keeps each node's distribution when planner.risk is not
    "label", and its costmaps show that mode; under "label" it keeps none (as before)."""
    pytest.importorskip("rosbags")
    from smana.common.config import SmanaConfig
    from smana.common.messages import GraphPatch
    from smana.services.ros2 import rmw
    from smana.services.ros2.service import Ros2Service

    patch = GraphPatch(
        seq=1,
        resolution_m=0.2,
        origin_xy=np.array([-50.0, -50.0]),
        cells=np.array([[250, 250], [251, 250]], np.int32),
        labels=np.array([GRASS, GRASS], np.uint16),
        heights=np.zeros(2, np.float32),
        flags=np.full(2, FLAG_KNOWN, np.uint8),
        producer="navgraph",
        alt_labels=np.array([0, WATER], np.uint16),
        p_label=np.array([255, 153], np.uint8),
        p_alt=np.array([0, 102], np.uint8),
    )
    table = 'general.class_table="garden3drms_wet"'
    out = {}
    for mode in ("label", "chance"):
        svc = Ros2Service(SmanaConfig.load(None, [table, f'planner.risk="{mode}"']))
        assert svc.grid.has_risk() == (mode != "label")
        svc.types = rmw.RosTypes()
        svc.graph.receive(patch)
        cells = ((250, 250), (251, 250))
        out[mode] = (
            _row(svc._costmap_message().data, svc.grid, cells),
            _row(svc._costmap_raw_message().data, svc.grid, cells),
        )
    assert out["label"] == ([98, 98], [252, 252])
    assert out["chance"][0][1] == 100 and out["chance"][1][1] == 254
    assert out["chance"][0][0] < 98
