"""`GraphCopy`, the planner's and the explorer's copy of navgraph's graph: patches in their
producer's order, gaps applied then resynced, strangers and other geometries refused, snapshots
re-anchoring the stream."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.graph_copy import GraphCopy
from smana.common.messages import GraphPatch
from smana.common.navgrid import FLAG_KNOWN, NavGrid
from smana.common.service import Reject


def _grid() -> NavGrid:
    return NavGrid.from_bounds([-5.0, -5.0], [5.0, 5.0], 0.2)


def _patch(grid, seq, cell=(10, 10), producer="navgraph-a", resolution_m=None) -> GraphPatch:
    return GraphPatch(
        seq=seq,
        resolution_m=grid.resolution_m if resolution_m is None else resolution_m,
        origin_xy=np.asarray(grid.origin_xy, float),
        cells=np.array([cell], np.int32),
        labels=np.array([2], np.uint16),
        heights=np.array([0.1], np.float32),
        flags=np.array([FLAG_KNOWN], np.uint8),
        producer=producer,
    )


def test_patches_in_order_are_applied_and_a_gap_is_applied_then_resynced():
    notes = []
    copy = GraphCopy(_grid(), lambda kind, msg: notes.append(kind))
    assert copy.receive(_patch(copy.grid, 1)) == ""
    assert copy.grid.n_known() == 1 and copy.last_seq == 1
    why = copy.receive(_patch(copy.grid, 5, cell=(11, 10)))
    assert why and copy.want_resync and copy.grid.n_known() == 2 and copy.last_seq == 5


def test_a_stranger_a_step_back_and_another_geometry_are_refused_without_a_change():
    copy = GraphCopy(_grid(), lambda kind, msg: None)
    copy.receive(_patch(copy.grid, 3))
    before = copy.grid.n_known()
    with pytest.raises(Reject) as stranger:
        copy.receive(_patch(copy.grid, 4, cell=(12, 12), producer="someone-else"))
    with pytest.raises(Reject) as back:
        copy.receive(_patch(copy.grid, 2, cell=(12, 12)))
    with pytest.raises(Reject) as geometry:
        copy.receive(_patch(copy.grid, 4, cell=(12, 12), resolution_m=0.5))
    assert (stranger.value.kind, back.value.kind, geometry.value.kind) == (
        "producer",
        "sequence",
        "geometry",
    )
    assert copy.grid.n_known() == before and copy.last_seq == 3


def test_a_snapshot_re_anchors_the_stream_and_covers_older_patches():
    notes = []
    copy = GraphCopy(_grid(), lambda kind, msg: notes.append(kind))
    assert not copy.usable_snapshot({"not": "a patch"})
    assert not copy.usable_snapshot(_patch(copy.grid, 9, resolution_m=0.5))
    assert notes == ["bad_graph_reply", "geometry"]
    snap = _patch(copy.grid, 9, producer="navgraph-b")
    assert copy.usable_snapshot(snap)
    copy.adopt(snap)
    assert copy.last_seq == 9 and not copy.want_resync
    assert copy.receive(_patch(copy.grid, 8, producer="navgraph-b")) is None  # covered
    assert copy.receive(_patch(copy.grid, 10, cell=(1, 1), producer="navgraph-b")) == ""
