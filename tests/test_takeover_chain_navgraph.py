"""Ten take-overs of the navgraph in a row, at the worst moments: after each, the new navgraph's
graph is the one the mapper's map makes, node for node.

A mapper runs throughout on an isolated loopback router (tests/conftest.py); navgraph processes
are started as hot spares the way `smana up` starts one (`SMANA_STANDBY_FD`, a line on stdin to
take over). The test feeds the mapper synthetic clouds itself (tests/test_takeover.py's ground
and box), each acknowledged by its MapDelta. Kills (SIGKILL) come while idle, with a map delta
in flight to the navgraph, right after a take-over (before it resynchronised), during a
take-over's resynchronisation, from a spare told to take over before it prepared; once a clean
stop (SIGINT). After each, the new navgraph's whole graph (`navgraph/graph`) equals a graph built
in this process from the mapper's snapshot: the same known nodes, labels, heights and flags. After
a take-over it follows the mapper again: the next clouds reach its graph."""

from __future__ import annotations

import signal

import numpy as np
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import encode
from smana.common.navgrid import FLAG_OBSTACLE
from smana.common.query import request
from smana.services.navgraph.graph import NavGraph
from tests.conftest import wait_for
from tests.support.hot_spare import HotSpare, SpareChain
from tests.test_mapper_service import DeltaInbox
from tests.test_takeover import make_cloud

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

SETS = ["mapper.resolution_m=0.2", "navgraph.resolution_m=0.2"]
MOMENTS = [
    "idle",
    "delta_in_flight",
    "right_after_takeover",
    "during_resync",
    "fresh_spare",
    "clean_stop",
    "idle",
    "delta_in_flight",
    "during_resync",
    "idle",
]


def Spare(stack) -> HotSpare:  # noqa: N802 - it stands for the class it makes
    """A navgraph process standing by (prepared) until `go()`."""
    return HotSpare(stack, "navgraph", [a for s in SETS for a in ("--set", s)])


def _height(h) -> float | None:
    return None if np.isnan(h) else float(h)


class Chain(SpareChain):
    def __init__(self, stack):
        self.stack = stack
        self.config = SmanaConfig.load(overrides=SETS)
        self.classes = ClassTable.load(self.config.general.class_table)
        self.pub = stack.session.declare_publisher(keys.cloud(stack.robot))
        self.inbox = DeltaInbox(stack, keys.map_delta(stack.robot))
        self.seq = 0
        super().__init__(lambda: Spare(stack))

    def mapper_clouds(self) -> int:
        return request(self.stack.session, keys.query(self.stack.robot, "mapper", "stats"))[
            "clouds"
        ]

    def put(self):
        self.seq += 1
        cloud = make_cloud(self.seq, 600)
        self.pub.put(encode(cloud))
        return cloud

    def send(self, n: int) -> None:
        """`n` clouds, each acknowledged by the mapper (its delta back) before the next."""
        for _ in range(n):
            cloud = self.put()
            want = self.mapper_clouds() + 1

            def acked(c=cloud, w=want) -> bool:
                if self.mapper_clouds() < w:  # a put before the subscription reached the router
                    self.pub.put(encode(c))
                try:
                    self.inbox.wait_for(c.seq, 2.0)
                except TimeoutError:
                    return False
                return True

            assert wait_for(acked, 60, 0.01)

    def reference(self) -> dict:
        """{cell: (label, height, flags)} of a graph built here from the mapper's snapshot, as
        the graph query carries it (NaN heights as None: they never compare equal)."""
        snap = request(self.stack.session, keys.query(self.stack.robot, "mapper", "snapshot"))
        graph = NavGraph(self.classes, self.config.navgraph)
        graph.integrate_delta(snap)
        g = graph.grid
        labels, heights, flags = (np.asarray(a) for a in g.box(0, 0, *g.shape))
        cells = np.argwhere(flags != 0)  # known, or in a safety zone: what the graph query gives
        return {
            # a node in a safety zone but not seen travels with height 0 (navgraph's to_patch)
            (int(i), int(j)): (
                int(labels[i, j]),
                _height(heights[i, j]) if flags[i, j] & 1 else 0.0,
                int(flags[i, j]),
            )
            for i, j in cells
        }

    def graph(self) -> dict:
        """{cell: (label, height, flags)} of the navgraph's whole graph."""
        p = request(self.stack.session, keys.query(self.stack.robot, "navgraph", "graph"))
        return {
            (int(c[0]), int(c[1])): (int(lab), _height(h), int(f))
            for c, lab, h, f in zip(p.cells, p.labels, p.heights, p.flags, strict=True)
        }

    def check(self, moment: str, incremental: bool = False) -> None:
        """The navgraph's graph equals the reference, once it has settled. `incremental`: it has
        integrated deltas since its resync, so an obstacle node's label (which the votes over
        updates pick among the box's classes) is left out; flags, heights and every other label
        must still agree."""
        last: list = []

        def same() -> bool:
            want, got = self.reference(), self.graph()
            if incremental:
                want = {
                    k: (v[0] if not v[2] & FLAG_OBSTACLE else -1, *v[1:]) for k, v in want.items()
                }
                got = {
                    k: (v[0] if not v[2] & FLAG_OBSTACLE else -1, *v[1:]) for k, v in got.items()
                }
            last[:] = [want, got]
            return want == got

        if not wait_for(same, 30, 0.2):
            want, got = last
            only_want = sorted(set(want.items()) - set(got.items()), key=repr)[:4]
            only_got = sorted(set(got.items()) - set(want.items()), key=repr)[:4]
            diff = f"wanted only {only_want}, got only {only_got}"
            raise AssertionError(f"{moment}: {len(want)} nodes wanted, {len(got)} got; {diff}")


def test_ten_navgraph_takeovers_in_a_row_leave_the_graph_the_map_makes(zenoh_stack):
    s = zenoh_stack
    s.service("mapper", *[a for x in SETS for a in ("--set", x)])
    s.wait_alive("mapper", timeout_s=120)
    chain = Chain(s)
    chain.spare()
    chain.take_over()
    chain.wait_running()
    chain.spare()
    for i, moment in enumerate(MOMENTS):
        chain.send(2)
        old = chain.active
        if moment == "delta_in_flight":
            chain.put()  # its delta is on its way to a navgraph about to die
            old.kill()
            assert wait_for(
                lambda: chain.inbox.items and chain.inbox.items[-1].cloud_seq == chain.seq, 30
            )
        elif moment == "clean_stop":
            assert old.kill(signal.SIGINT) == 0, old.log()
        else:
            old.kill()
        if moment == "during_resync":
            doomed = chain.take_over()
            doomed.kill()  # at once: while it asks for the snapshot and rebuilds
        if moment == "fresh_spare":  # told to take over before it prepared
            chain.spares.insert(0, Spare(s))
        chain.take_over(prepared=moment != "fresh_spare")
        chain.wait_running()
        chain.check(moment)
        if moment == "right_after_takeover":  # once more, before it followed any delta
            chain.spare()
            chain.active.kill()
            chain.take_over()
            chain.wait_running()
            chain.check("after the second take-over")
        # it follows the mapper again
        chain.send(2)
        chain.check(f"{moment}, two clouds later", incremental=True)
        while len(chain.spares) < (2 if MOMENTS[(i + 1) % len(MOMENTS)] == "during_resync" else 1):
            chain.spare()
        print(f"take-over {i + 1} ({moment}): graph equal to the map's")
    for sp in chain.spares:
        sp.kill()
    assert chain.active.kill(signal.SIGINT) == 0
