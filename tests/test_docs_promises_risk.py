"""docs/risk.md's sentences no other test held:

- "In every mode, as without risk: obstacle and safety-zone nodes are never entered, unknown nodes
  only with `allow_unknown`, and a node whose most likely class is forbidden is closed";
- "`risk_alpha` is a probability in (0, 1]", "`max_risk` is a probability in [0, 1]: 0 closes
  every node with any forbidden share, 1 closes none";
- "`PathRequest` carries no risk field".

Each on a two-node graph (a certain terrain start, the node under test) planned in process.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from smana.common.config import ConfigError, SmanaConfig
from smana.common.config.planner import PlannerConfig
from smana.common.messages import PathRequest
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE
from smana.services.planner.planner import RISK_MODES, Planner
from tests.test_planner_risk import CLASSES, GRASS, TERRAIN, WATER, make_grid


def enter(label, flags, p_label=255, alt=0, p_alt=0, allow_unknown=False, **config) -> float:
    """The traversability cost of entering one node from a certain terrain node beside it
    (inf when the planner does not enter it)."""
    labels = np.array([[TERRAIN, label]], np.uint16)
    grid_flags = np.array([[FLAG_KNOWN, flags]], np.uint8)
    risk = (
        np.array([[0, alt]], np.uint16),
        np.array([[255, p_label]], np.uint8),
        np.array([[0, p_alt]], np.uint8),
    )
    grid = make_grid(labels, np.zeros((1, 2), np.float32), grid_flags, risk)
    planner = Planner(grid, CLASSES, PlannerConfig(**config))
    r = planner.plan((0.1, 0.1), (0.1, 0.3), allow_unknown=allow_unknown)
    return r.cost_traversability if r.ok else np.inf


@pytest.mark.parametrize("mode", RISK_MODES)
def test_in_every_mode_obstacles_safety_zones_unknown_and_forbidden_labels_stay_closed(mode):
    # a doubtful grass node is entered in every mode: the cases below are closed for their flag
    assert enter(GRASS, FLAG_KNOWN, 200, TERRAIN, 55, risk=mode) < np.inf
    doubt = {"p_label": 200, "alt": TERRAIN, "p_alt": 55, "risk": mode}
    assert enter(GRASS, FLAG_KNOWN | FLAG_OBSTACLE, **doubt) == np.inf
    assert enter(GRASS, FLAG_KNOWN | FLAG_SAFETY_ZONE, **doubt) == np.inf
    # unknown: only with allow_unknown
    assert enter(0, 0, risk=mode) == np.inf
    assert enter(0, 0, allow_unknown=True, risk=mode) < np.inf
    # most likely water (a forbidden class), the rest terrain: closed, however cheap the rest
    assert enter(WATER, FLAG_KNOWN, 153, TERRAIN, 102, risk=mode) == np.inf


def test_risk_alpha_and_max_risk_are_probabilities():
    for ok in ("planner.risk_alpha=1.0", "planner.max_risk=0.0", "planner.max_risk=1.0"):
        SmanaConfig.load(None, [ok])
    for bad in ("planner.risk_alpha=0", "planner.risk_alpha=1.01", "planner.max_risk=-0.01",
                "planner.max_risk=1.01"):  # fmt: skip
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            SmanaConfig.load(None, [bad])


def test_max_risk_0_closes_any_forbidden_share_and_1_closes_none():
    # grass with a 1/255 share of water: closed at 0, entered above it
    assert enter(GRASS, FLAG_KNOWN, 254, WATER, 1, risk="chance", max_risk=0.0) == np.inf
    assert enter(GRASS, FLAG_KNOWN, 254, WATER, 1, risk="chance", max_risk=0.01) < np.inf
    # grass with a 49 % share of water, or 30 % water and 19 % unnamed: entered at 1
    assert enter(GRASS, FLAG_KNOWN, 130, WATER, 125, risk="chance", max_risk=1.0) < np.inf
    assert enter(GRASS, FLAG_KNOWN, 130, WATER, 77, risk="chance", max_risk=1.0) < np.inf


def test_a_path_request_carries_no_risk_field():
    assert not [f.name for f in dataclasses.fields(PathRequest) if "risk" in f.name]
