"""A service's copy of the navigation graph, kept from navgraph's patch stream.

The planner and the explorer each hold one (`GraphCopy`): patches are applied in their producer's
order (`SequenceFollower`: a gap is applied and a resync asked; another producer, a number that goes
back or leaps is refused), a patch on another grid geometry is refused, and a whole-graph snapshot
from `navgraph/graph` (`adopt`) re-anchors the stream. A grid with the label-distribution layers
(`NavGrid.has_risk`, the planner's) receives each node's distribution with it. What a service
does around it (when it asks for a snapshot, what it counts) stays in the service.
"""

from __future__ import annotations

from collections.abc import Callable

from smana.common.messages import GraphPatch
from smana.common.navgrid import NavGrid
from smana.common.plausibility import APPLY, COVERED, SequenceFollower
from smana.common.service import Reject


class GraphCopy:
    def __init__(self, grid: NavGrid, note: Callable[[str, str], None]):
        self.grid = grid
        self.stream = SequenceFollower()
        self._note = note  # Service.note: events that are not a message's fate

    def check_geometry(self, patch: GraphPatch) -> None:
        if why := self.grid.geometry_mismatch(patch.resolution_m, patch.origin_xy):
            raise Reject("geometry", f"graph patch {patch.seq}: {why}; check [navgraph]")

    def apply(self, patch: GraphPatch) -> None:
        # the label distributions go to a grid that keeps them (NavGrid.add_risk_layers)
        risk = patch.risk() if self.grid.has_risk() else None
        n_out = self.grid.apply_patch(
            patch.cells, patch.labels, patch.heights, patch.flags, risk=risk
        )
        if n_out:
            self._note("out_of_bounds", f"{n_out} patch cells outside the graph bounds")

    def receive(self, patch: GraphPatch) -> str | None:
        """One patch of the stream. Returns None when the patch was already in the graph (covered
        by the last snapshot), else "" or, when it was applied across a gap, what is missing;
        raises `Reject` for a patch that must not be applied (a resync is then wanted)."""
        self.check_geometry(patch)
        action, why = self.stream.check(patch.producer, patch.seq)
        if action == COVERED:
            return None
        if action != APPLY:
            raise Reject(action, f"graph patch {patch.seq}: {why}; resync asked")
        self.apply(patch)
        self.stream.advance(patch.producer, patch.seq)
        return why

    def usable_snapshot(self, reply) -> bool:
        """Whether a `navgraph/graph` reply can replace the graph (noted when it cannot)."""
        if not isinstance(reply, GraphPatch):
            self._note("bad_graph_reply", "navgraph/graph did not answer with a GraphPatch")
            return False
        try:
            self.check_geometry(reply)
        except Reject as exc:
            self._note("geometry", str(exc))
            return False
        return True

    def adopt(self, snapshot: GraphPatch) -> None:
        """Apply a whole-graph snapshot (checked by `usable_snapshot`) and follow its stream on."""
        self.apply(snapshot)
        self.stream.synced(snapshot.producer, snapshot.seq)

    @property
    def want_resync(self) -> bool:
        return self.stream.want_resync

    @property
    def last_seq(self) -> int | None:
        return self.stream.last
