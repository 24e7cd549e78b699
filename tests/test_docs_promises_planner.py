"""docs/tutorial.md: `smana plan ... --cost grass=4`: "grass four times as costly, this query
only". A query's class costs change its own path and leave the planner's costs as they were for
the next query (the grid and the paper's grass detour of tests/test_planner_planner.py)."""

from __future__ import annotations

import numpy as np

from smana.services.planner.planner import Planner
from tests.test_planner_planner import CLASSES, GRASS, TERRAIN, dense_grid


def test_a_querys_class_costs_are_for_that_query_only():
    labels = np.full((40, 30), TERRAIN, np.uint16)
    labels[19:21, :14] = GRASS
    planner = Planner(dense_grid(labels), CLASSES)
    before = planner.plan((1.0, 0.5), (7.0, 0.5))
    assert before.ok and before.label_share["grass"] > 0
    detour = planner.plan((1.0, 0.5), (7.0, 0.5), class_costs={GRASS: 4.0})
    assert detour.ok and "grass" not in detour.label_share
    after = planner.plan((1.0, 0.5), (7.0, 0.5))
    assert after.cost_total == before.cost_total
    np.testing.assert_array_equal(after.path, before.path)
