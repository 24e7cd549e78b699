"""The graph reads a MapDelta by what its values hold (`values_kind`), never by back-end name; a
kind it cannot read is refused before it changes anything, and the service counts the refusal."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.config.navgraph import NavgraphConfig
from smana.common.messages import VALUES_KINDS, MapDelta, encode
from smana.services.navgraph import graph as graph_module
from smana.services.navgraph.graph import NavGraph
from smana.services.navgraph.service import NavgraphService

CLASSES = ClassTable.load("garden3drms")
GRASS = 1


def small_graph() -> NavGraph:
    return NavGraph(CLASSES, NavgraphConfig(bounds_min_xy=[0, 0], bounds_max_xy=[4, 4]))


def column_delta(values_kind: str, backend: str = "a-back-end-the-graph-never-heard-of"):
    """Four voxels over one node: only the second is occupied; the first three lie within the
    0.2 m band of the graph resolution when the values are signed distances (the old rule)."""
    centres = np.array([[1.05, 1.05, 0.05 + 0.1 * k] for k in range(4)], np.float32)
    return MapDelta(
        seq=1,
        backend=backend,
        resolution_m=0.1,
        centres=centres,
        labels=np.full(4, GRASS, np.uint16),
        confidences=np.ones(4, np.float32),
        occupied=np.array([0, 1, 0, 0], np.uint8),
        values=np.array([0.15, 0.05, -0.19, -0.25], np.float32),
        values_kind=values_kind,
    )


def test_the_graph_reads_every_kind_the_messages_carry():
    assert set(graph_module.SURFACE_INPUTS) == set(VALUES_KINDS)


def test_signed_distances_use_the_extracted_surface_whatever_the_back_end_is_called():
    """The map's extraction (`occupied`) is the surface: no band of small distances around it."""
    delta = column_delta("signed_distance")
    by_kind = small_graph().integrate_delta(delta)
    by_hand = small_graph().integrate(delta.centres, delta.labels, delta.occupied)
    assert by_kind.heights.tolist() == by_hand.heights.tolist() == [pytest.approx(0.15)]
    assert by_kind.n_surface == 1


def test_a_tsdf_delta_gives_the_graph_one_voxel_per_crossing():
    """End to end: a flat floor integrated by the TSDF gives nodes at the floor's height, one
    surface voxel per column, under the old band rule it gave two or three."""
    from smana.services.mapper.backends.tsdf import TsdfConfig
    from smana.services.mapper.semantic_map import SemanticMap

    # one scan of one ray per floor point: a one-ray surface (the default waits for 3 rays)
    m = SemanticMap("tsdf", 0.1, 10.0, config=TsdfConfig(min_weight=1e-4))
    s = np.arange(0.55, 3.5, 0.1)
    xx, yy = np.meshgrid(s, s, indexing="ij")
    floor = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.03)], -1).astype(np.float32)
    origin = (2.05, 2.05, 1.55)
    for p in floor:  # ray by ray: the fast integrator would leave holes in one dense cloud
        m.integrate(p[None], np.array([GRASS]), None, origin)
    rows = m.occupied_voxels()
    g = small_graph()
    up = g.integrate_delta(
        MapDelta(
            seq=1,
            backend="tsdf",
            resolution_m=0.1,
            centres=rows.centres,
            labels=rows.labels,
            confidences=rows.confidences,
            occupied=rows.occupied,
            values=rows.values,
            values_kind="signed_distance",
        )
    )
    assert up.n_surface == len(rows.centres)
    cols = {}
    for c in rows.centres.tolist():
        cols.setdefault((round(c[0], 2), round(c[1], 2)), []).append(c[2])
    assert all(v == [pytest.approx(0.05)] for v in cols.values())  # z = 0.03 m lies in voxel 0
    assert g.node(2.05, 2.05)["height"] == pytest.approx(0.05)


def test_log_odds_values_are_not_read_as_distances():
    up = small_graph().integrate_delta(column_delta("log_odds"))
    assert up.n_surface == 1 and up.heights.tolist() == [pytest.approx(0.15)]


def test_a_kind_the_graph_cannot_read_is_refused_and_counted(monkeypatch):
    service = NavgraphService(SmanaConfig())
    published = []
    service.patch_pub = SimpleNamespace(put=published.append)  # no zenoh: keep the patches

    def handle(delta):
        service.books.received += 1
        service.books.in_flight += 1  # as the main loop does when it takes a sample
        service._handle_payload(service.on_delta, MapDelta, encode(delta), False)

    # A kind the codec does not know is refused on decoding ...
    handle(column_delta("voxblox_esdf"))
    # ... and one the codec knows but this graph cannot read, by the graph, unchanged.
    monkeypatch.delitem(graph_module.SURFACE_INPUTS, "signed_distance")
    handle(column_delta("signed_distance"))
    assert service.books.rejected["value"] == 2 and service.graph.grid.n_known() == 0
    handle(column_delta("log_odds"))
    b = service.books
    assert b.accepted == 1 and service.graph.grid.n_known() == 1 and len(published) == 1
    assert b.received == b.accepted + sum(b.dropped.values()) + sum(b.rejected.values())
