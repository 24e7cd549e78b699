"""A graph export in a world box: any finite box works, however far it reaches (found by `smana
bench fuzz`: {"box": [0, 0, 1, 1e308]} overflowed converting to cells, an `internal` error)."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.services.navgraph.graph import NavGraph


@pytest.fixture(scope="module")
def graph():
    g = NavGraph(ClassTable.load("garden3drms"), NavgraphConfig())
    xs, ys = np.meshgrid(np.arange(-2, 2, 0.1) + 0.05, np.arange(-2, 2, 0.1) + 0.05)
    centres = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1).astype(np.float32)
    n = len(centres)
    g.integrate(centres, np.full(n, 2, np.uint16), np.ones(n, np.uint8))
    return g


def _set(cells):
    return {tuple(c) for c in cells.tolist()}


@pytest.mark.parametrize("far", [1e308, 1e20, 1e6, 100.0])
def test_a_far_box_is_the_whole_graph(graph, far):
    everything = _set(graph.export()[0])
    assert everything and _set(graph.export((-far, -far, far, far))[0]) == everything


def test_a_box_beyond_the_bounds_is_empty(graph):
    assert len(graph.export((1e300, 1e300, 1e308, 1e308))[0]) == 0
    assert len(graph.export((-1e308, -1e308, -1e300, -1e300))[0]) == 0


def test_a_box_inside_keeps_its_cells(graph):
    cells = graph.export((0.0, 0.0, 1.0, 1.0))[0]
    centres = (cells + 0.5) * 0.2 - 50
    assert len(cells) and (centres >= -0.2).all() and (centres <= 1.2).all()
