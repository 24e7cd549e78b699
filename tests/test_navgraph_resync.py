"""navgraph resynchronises from the mapper's snapshot when deltas may have been lost: here the
mapper dies without saving and comes back empty, so every node from before is a ghost that the
resync must remove; afterwards the graph equals the graph of the mapper's whole map. Both run
in-process on the fake zenoh (the crash: the mapper's session vanishes, nothing saved)."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import GraphPatch, MapDelta
from smana.common.query import request
from smana.services.navgraph.graph import NavGraph
from smana.services.navgraph.service import graph_difference
from tests.conftest import wait_for

sys.path.insert(0, str(Path(__file__).parent / "support"))
from publish_clouds import patch_cloud  # noqa: E402

from smana.common.messages import encode  # noqa: E402


def test_graph_difference_marks_changed_added_and_gone():
    old = (
        np.array([[0, 0], [1, 0], [2, 3]], np.int32),
        np.array([1, 2, 1], np.uint16),
        np.array([0.1, 0.2, 0.3], np.float32),
        np.array([1, 1, 3], np.uint8),
    )
    new = (
        np.array([[1, 0], [2, 3], [5, 5]], np.int32),
        np.array([2, 4, 1], np.uint16),
        np.array([0.2, 0.3, 0.0], np.float32),
        np.array([1, 3, 1], np.uint8),
    )
    cells, labels, heights, flags = graph_difference(old, new)
    got = {tuple(c): (int(lab), int(f)) for c, lab, f in zip(cells.tolist(), labels, flags)}
    # (1, 0) is unchanged; (2, 3) changed label; (5, 5) is new; (0, 0) is gone -> unknown.
    assert got == {(2, 3): (4, 3), (5, 5): (1, 1), (0, 0): (0, 0)}


def graph_nodes(patch: GraphPatch) -> dict:
    return {
        tuple(c): (int(lab), int(f))
        for c, lab, f in zip(patch.cells.tolist(), patch.labels, patch.flags)
    }


def test_resync_after_the_mapper_comes_back_empty(fake_stack, tmp_path):
    s = fake_stack
    args = [
        "--set",
        "mapper.autosave_period_s=0",
        "--set",
        f'mapper.save_path="{tmp_path}/m.npz"',
        "--set",
        'mapper.load=""',
    ]
    mapper = s.service("mapper", *args)
    s.service("navgraph")
    s.wait_alive("mapper")
    s.wait_alive("navgraph")
    graph_key = keys.query(s.robot, "navgraph", "graph")

    def publish(i, seq):
        s.session.put(keys.cloud(s.robot), encode(patch_cloud(i, seq)))

    for i in range(3):  # latest wins: each cloud is handled before the next is sent
        publish(i, i + 1)
        assert s.drained("mapper")
    assert wait_for(lambda: len(request(s.session, graph_key).cells) >= 300, 20)
    before = graph_nodes(request(s.session, graph_key))

    s.stop(mapper, signal.SIGKILL)  # no save: the new mapper starts with an empty map
    s.procs = [(n, p) for n, p in s.procs if p is not mapper]
    s.service("mapper", *args)
    s.wait_alive("mapper")
    publish(7, 1)  # somewhere new

    def resynced():
        st = request(s.session, keys.query(s.robot, "navgraph", "stats"))
        return st["resyncs"] >= 1

    assert wait_for(resynced, 20), s.log("navgraph")
    snap = request(s.session, keys.query(s.robot, "mapper", "snapshot"))
    assert isinstance(snap, MapDelta)

    def matches_mapper():
        nc = SmanaConfig().navgraph
        ref = NavGraph(ClassTable.load("garden3drms"), nc)
        ref.integrate_delta(request(s.session, keys.query(s.robot, "mapper", "snapshot")))
        cells, labels, _, flags = ref.export()
        want = {tuple(c): (int(lab), int(f)) for c, lab, f in zip(cells.tolist(), labels, flags)}
        return graph_nodes(request(s.session, graph_key)) == want and len(want) >= 100

    assert wait_for(matches_mapper, 20), s.log("navgraph")
    after = graph_nodes(request(s.session, graph_key))
    assert not set(before) & set(after)  # every ghost from before the crash is gone
