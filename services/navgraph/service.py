"""The navgraph service: zenoh wiring around `NavGraph` (the algorithm lives in `graph.py`).

Input: `mapper/delta` (MapDelta), every one in order (FIFO, never latest-wins: a lost delta is a
hole in the graph). The delta stream is followed per producer (the mapper session that numbered
it, `common/plausibility.py::SequenceFollower`): a gap is counted (event `delta_gap`) and asks for
a resync; a delta from another producer (a restarted mapper, or a stranger), one whose number goes
back or jumps far ahead is refused (`producer`, `sequence`) and asks for a resync, so no number a
peer sends can freeze or wipe the graph. (Stamps are the clouds' and only labels here: the mapper
checked them, and a delta refused for its stamp would leave a hole.) Labels outside the class
table are read as unknown and counted (`unknown_labels`); voxels outside the graph bounds are
counted in the stats (a map may reach further than the graph).
A delta is read by what its values hold (`MapDelta.values_kind`), not by the back-end that made it;
one whose kind the graph cannot read is refused as `value` (by the codec, or by
`NavGraph.integrate_delta`) before it changes anything.

At start the service asks the mapper for a snapshot of its occupied voxels (`mapper/snapshot`),
so a navgraph started or restarted after the mapper does not miss what was mapped before; deltas
that the snapshot already covers (sequence number not above the snapshot's) are dropped as
`covered`.

It resynchronises the same way whenever deltas may have been lost or the stream is in doubt (see
above), and when the mapper's liveliness token comes back after vanishing (the mapper restarted,
or the link to a robot dropped and returned). The graph is rebuilt from the snapshot and the nodes
that differ from the old graph go out as one patch, so consumers stay incremental and no voxel is
lost from the base's view. Resyncs are at most one every `RESYNC_MIN_PERIOD_S`.

Output: one `GraphPatch` on `navgraph/patch` per delta that changed a node (label, height,
flags or label distribution, safety-zone changes included), published reliably (congestion
control BLOCK). Each node carries the distribution of the voxel that sets its label (GraphPatch
v2: `alt_labels`, `p_label`, `p_alt`). Heights of nodes that are not known travel as 0 (the codec
carries finite numbers only).

Queries (msgpack or JSON, see `common/service.py`):
- `navgraph/graph`: the known nodes as one GraphPatch (seq = the last patch's), optionally in a
  world box `{"box": [x0, y0, x1, y1]}` or `?box=x0,y0,x1,y1`;
- `navgraph/node`: `{"x": .., "y": ..}` or `?x=..;y=..` -> the node's state and its column;
- `navgraph/stats`: graph and service figures.
"""

from __future__ import annotations

import time

import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import MAX_PAYLOAD_BYTES, GraphPatch, MapDelta
from smana.common.navgrid import FLAG_KNOWN
from smana.common.plausibility import APPLY, COVERED, SequenceFollower
from smana.common.query import QueryError, request
from smana.common.service import Reject, ReplyError, Request, Service, run_service
from smana.services.navgraph.graph import NavGraph, same_nodes, warm_up

BYTES_PER_PATCH_NODE = 8 + 2 + 4 + 1 + 2 + 1 + 1  # cell, label, height, flags, distribution
RESYNC_MIN_PERIOD_S = 1.0  # a stream in doubt asks for snapshots at most this often


def to_patch(
    graph: NavGraph, cells, labels, heights, flags, seq: int, stamp_s: float, producer: str = ""
):
    """A GraphPatch of nodes, with their label distributions as the graph holds them now;
    unknown heights (NaN) travel as 0."""
    heights = np.where(np.isnan(heights) | ((flags & FLAG_KNOWN) == 0), 0.0, heights)
    alt_labels, p_label, p_alt = graph.grid.read_risk(np.asarray(cells).reshape(-1, 2))
    return GraphPatch(
        stamp_s=float(stamp_s),
        seq=int(seq),
        resolution_m=graph.resolution_m,
        origin_xy=graph.grid.origin_xy.astype(np.float64),
        cells=np.ascontiguousarray(cells, np.int32),
        labels=np.ascontiguousarray(labels, np.uint16),
        heights=heights.astype(np.float32),
        flags=np.ascontiguousarray(flags, np.uint8),
        producer=producer,
        alt_labels=alt_labels,
        p_label=p_label,
        p_alt=p_alt,
    )


def parse_numbers(value, n: int, what: str) -> list[float]:
    try:
        if isinstance(value, str):
            value = value.split(",")
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ReplyError("value", f"{what} must be {n} numbers") from None
    if len(out) != n or not all(np.isfinite(out)):
        raise ReplyError("value", f"{what} must be {n} finite numbers, got {value!r}")
    return out


def graph_difference(old, new, old_risk=None, new_risk=None):
    """The nodes whose state differs between two exports (cells, labels, heights, flags), their
    label distributions (`NavGrid.read_risk` of the exports' cells) compared too when given;
    nodes only in `old` come out as unknown (flags 0)."""
    oc, ol, oh, of = old
    nc, nl, nh, nf = new
    width = int(max(oc[:, 0].max(initial=0), nc[:, 0].max(initial=0))) + 1
    okey = oc[:, 1].astype(np.int64) * width + oc[:, 0]
    nkey = nc[:, 1].astype(np.int64) * width + nc[:, 0]
    common, oi, ni = np.intersect1d(okey, nkey, assume_unique=True, return_indices=True)
    differ = ~same_nodes(ol[oi], oh[oi], of[oi], nl[ni], nh[ni], nf[ni])
    for a, b in zip(old_risk or (), new_risk or (), strict=True):
        differ |= a[oi] != b[ni]
    changed = ni[differ]
    added = np.setdiff1d(np.arange(len(nkey)), ni, assume_unique=True)
    gone = np.setdiff1d(np.arange(len(okey)), oi, assume_unique=True)
    take = np.concatenate([changed, added])
    cells = np.concatenate([nc[take], oc[gone]])
    labels = np.concatenate([nl[take], np.zeros(len(gone), nl.dtype)])
    heights = np.concatenate([nh[take], np.zeros(len(gone), nh.dtype)])
    flags = np.concatenate([nf[take], np.zeros(len(gone), nf.dtype)])
    return cells, labels, heights, flags


class NavgraphService(Service):
    name = "navgraph"
    prepare_in_background = True  # prepare() only compiles kernels: live meanwhile
    tick_period_s = 1.0

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        self.classes = ClassTable.load(config.general.class_table)
        self.graph = self._new_graph()
        self.patch_seq = 0
        self.deltas_in = SequenceFollower()
        self.last_stamp_s = 0.0
        self._next_resync = 0.0
        self.deltas = 0
        self.deltas_skipped = 0
        self.voxels_out_of_bounds = 0
        self.columns_lost = 0
        self.times_ms: list[float] = []
        self.resyncs = 0
        self.snapshot_queries = 0  # asked of the mapper (its books count them as received)
        self._resync_reason = ""  # set from callbacks and on_delta; done in tick()
        self._mapper_was_down = False

    def prepare(self) -> None:
        # Before the liveliness token: whoever waits for navgraph gets a compiled one.
        self.startup_step = "loading (or compiling) the numba kernels"
        self.log.info("kernels ready in %.1f s", warm_up(self.classes))

    def _new_graph(self) -> NavGraph:
        return NavGraph(self.classes, self.config.navgraph)

    def setup(self) -> None:
        r = self.robot
        self.patch_pub = self.publisher(keys.graph_patch(r), reliable_block=True)
        self.subscribe(keys.map_delta(r), self.on_delta, MapDelta)
        self.queryable(keys.query(r, "navgraph", "graph"), self.on_graph)
        self.queryable(keys.query(r, "navgraph", "node"), self.on_node)
        self.queryable(keys.query(r, "navgraph", "stats"), lambda req: self.stats())
        self._initial_map()
        self._declared.append(
            self.session.liveliness().declare_subscriber(
                keys.alive(r, "mapper"), self._on_mapper_token
            )
        )

    def _on_mapper_token(self, sample) -> None:
        # A zenoh callback: only flags; tick() does the work on the main loop.
        import zenoh

        if sample.kind == zenoh.SampleKind.DELETE:
            self._mapper_was_down = True
        elif self._mapper_was_down:
            self._mapper_was_down = False
            self._resync_reason = "the mapper is back (restart or link drop)"

    def tick(self) -> None:
        if self.deltas_in.want_resync and not self._resync_reason:
            self._resync_reason = self.deltas_in.want_resync
        if self._resync_reason and time.monotonic() >= self._next_resync:
            self._next_resync = time.monotonic() + RESYNC_MIN_PERIOD_S
            reason, self._resync_reason = self._resync_reason, ""
            self.resync(reason)

    def resync(self, reason: str) -> bool:
        """Rebuild the graph from the mapper's snapshot; publish the nodes that changed."""
        try:
            snap = self._snapshot(5.0)
        except QueryError as exc:
            self.log.warning("resync (%s) failed: no snapshot (%s)", reason, exc.kind)
            if exc.kind == "warming_up":  # a mapper live before its kernels: ask again
                self._resync_reason = self._resync_reason or reason
            return False
        if snap is None:
            return False
        old = self.graph.export()
        old_risk = self.graph.grid.read_risk(old[0])
        self.graph = self._new_graph()
        up = self.graph.integrate_delta(snap)
        new = self.graph.export()
        new_risk = self.graph.grid.read_risk(new[0])
        cells, labels, heights, flags = graph_difference(old, new, old_risk, new_risk)
        self.deltas_in.synced(snap.producer, snap.seq)
        self.resyncs += 1
        self.log.info(
            "resynced from the mapper's snapshot (%s): %d voxels, %d nodes changed",
            reason,
            len(snap.centres),
            len(cells),
        )
        self.columns_lost += up.n_columns_lost
        if len(cells):
            self._publish(cells, labels, heights, flags, snap.stamp_s)
        return True

    def _publish(self, cells, labels, heights, flags, stamp_s: float) -> None:
        self.patch_seq += 1
        self.last_stamp_s = max(self.last_stamp_s, float(stamp_s))
        self.patch_pub.put(
            to_patch(
                self.graph, cells, labels, heights, flags, self.patch_seq, stamp_s, self.producer
            )
        )

    def _snapshot(self, timeout_s: float) -> MapDelta | None:
        """The mapper's snapshot, or None when its reply is not one (noted); QueryError when
        there is no reply."""
        self.snapshot_queries += 1
        snap = request(self.session, keys.query(self.robot, "mapper", "snapshot"), None, timeout_s)
        if not isinstance(snap, MapDelta):
            self.note("bad_snapshot", "mapper snapshot is not a MapDelta")
            return None
        return snap

    def _initial_map(self) -> None:
        """Integrate the mapper's current map, if a mapper is already running."""
        try:
            snap = self._snapshot(3.0)
        except QueryError as exc:
            self.log.info("no map snapshot (%s): starting from deltas", exc.kind)
            return
        if snap is None:
            return
        self.deltas_in.synced(snap.producer, snap.seq)
        self.log.info("starting from the mapper's snapshot: %d voxels", len(snap.centres))
        self._integrate(snap)

    # -- the delta path ----------------------------------------------------------------------

    def on_delta(self, delta: MapDelta):
        # Checks first: a refused delta changes nothing.
        action, why = self.deltas_in.check(delta.producer, delta.seq)
        if action == COVERED:
            self.deltas_skipped += 1  # already in the snapshot we synced from
            return ("dropped", "covered")
        if action != APPLY:
            raise Reject(action, f"map delta {delta.seq}: {why}; resync asked")
        self._integrate(delta)  # checks the delta before it changes anything
        self.deltas_in.advance(delta.producer, delta.seq)
        if why:  # applied across a gap; the resync fills it
            self.note("delta_gap", f"map deltas: {why}")

    def _integrate(self, delta: MapDelta) -> None:
        up = self.graph.integrate_delta(delta)  # checks its input before changing anything
        self.deltas += 1
        self.times_ms.append(up.time_ms)
        del self.times_ms[:-100]
        self.voxels_out_of_bounds += up.n_out_of_bounds
        self.columns_lost += up.n_columns_lost
        if up.n_unknown_labels:
            self.note(
                "unknown_labels",
                f"delta {delta.seq}: {up.n_unknown_labels} labels not in the class table "
                f"{self.classes.name}, read as unknown",
            )
        if len(up.cells):
            self._publish(up.cells, up.labels, up.heights, up.flags, delta.stamp_s)

    # -- queries -----------------------------------------------------------------------------

    def on_graph(self, req: Request) -> GraphPatch:
        body = req.body()
        box = body.get("box", req.params.get("box"))
        if box is not None:
            box = parse_numbers(box, 4, "box (x0, y0, x1, y1)")
            if box[2] < box[0] or box[3] < box[1]:
                raise ReplyError("value", "box needs x0 <= x1 and y0 <= y1")
        cells, labels, heights, flags = self.graph.export(box)
        if len(cells) * BYTES_PER_PATCH_NODE > MAX_PAYLOAD_BYTES - 4096:
            raise ReplyError("value", f"{len(cells)} nodes do not fit one reply: ask for a box")
        return to_patch(
            self.graph,
            cells,
            labels,
            heights,
            flags,
            self.patch_seq,
            self.last_stamp_s,
            self.producer,
        )

    def on_node(self, req: Request) -> dict:
        body = req.body()
        x = body.get("x", req.params.get("x"))
        y = body.get("y", req.params.get("y"))
        if x is None or y is None:
            raise ReplyError("value", "node query needs x and y (metres)")
        x, y = parse_numbers([x, y], 2, "x, y")
        node = self.graph.node(x, y)
        if node is None:
            raise ReplyError("out_of_bounds", f"({x}, {y}) is outside the graph bounds")
        ix, iy = node["cell"]
        node["column"] = [list(c) for c in self.graph.column(ix, iy)]
        if np.isnan(node["height"]):
            node["height"] = None  # JSON has no NaN
        return node

    def stats(self) -> dict:
        t = np.array(self.times_ms) if self.times_ms else np.zeros(1)
        return {
            **self.graph.stats(),
            "deltas": self.deltas,
            "deltas_skipped": self.deltas_skipped,
            "resyncs": self.resyncs,
            "snapshot_queries": self.snapshot_queries,
            "patch_seq": self.patch_seq,
            "voxels_out_of_bounds": self.voxels_out_of_bounds,
            "columns_lost": self.columns_lost,
            "integrate_ms_median": float(np.median(t)),
            "integrate_ms_last": float(t[-1]),
        }

    def status_details(self) -> dict:
        s = self.stats()
        keep = ("nodes_known", "tiles", "bytes", "deltas", "patch_seq", "integrate_ms_median")
        return {k: s[k] for k in keep}


def main(config: SmanaConfig) -> int:
    """Run the navgraph service until SIGINT/SIGTERM."""
    return run_service(NavgraphService, config)
