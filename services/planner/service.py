"""The planner service: zenoh wiring around `Planner` (the algorithm lives in `planner.py` and
`astar.py`).

Input: `navgraph/patch` (GraphPatch), applied in order to the planner's own `NavGrid` copy, label
distributions included (its RISK_LAYERS; a version-1 patch reads as certain). The
patch stream is followed per producer (the navgraph session that numbered it,
`common/plausibility.py::SequenceFollower`). At start, on a gap in the patch sequence, when a
patch comes from another producer (navgraph restarted) or its number goes back or jumps far ahead
(refused: `producer`, `sequence`), and when navgraph's liveliness token appears, the planner asks
navgraph for the whole graph (`navgraph/graph`) and drops the patches that reply already covers
(`covered`). A patch whose resolution or origin differs from `[navgraph]` in the config is
rejected (`geometry`).

Query `planner/path`: a PathRequest in msgpack, or JSON from any zenoh tool (only `start` and
`goal` are required, e.g. `{"start": [0, 0], "goal": [5, 3]}`), or selector parameters
`?start=x,y;goal=x,y`. The reply is always a PathReply (in the query's encoding): the path, or
`ok = false` with an error code (`out_of_bounds`, `start_blocked`, `goal_blocked`, `unreachable`,
`no_graph`, `malformed`) and a message saying what and where (for a blocked start or goal:
obstacle, safety zone or unknown space, and the nearest free node in `nearest_free`).
Also `planner/stats`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.graph_copy import GraphCopy
from smana.common.messages import (
    SCHEMA_VERSION,
    GraphPatch,
    MessageError,
    PathReply,
    PathRequest,
    Pose,
    from_dict,
)
from smana.common.navgrid import NavGrid
from smana.common.query import QueryError, request
from smana.common.service import Reject, Request, Service, run_service
from smana.services.planner.planner import MALFORMED, Planner, PlanResult, warm_up


def reply_of(request_id: str, r: PlanResult) -> PathReply:
    return PathReply(
        request_id=request_id,
        ok=r.ok,
        error=r.error,
        message=r.message,
        path=np.ascontiguousarray(r.path, np.float32).reshape(-1, 3),
        cost_total=float(r.cost_total),
        cost_distance=float(r.cost_distance),
        cost_height=float(r.cost_height),
        cost_traversability=float(r.cost_traversability),
        label_share={k: float(v) for k, v in r.label_share.items()},
        nodes_expanded=int(r.nodes_expanded),
        time_ms=float(r.time_ms),
        nearest_free=np.asarray(r.nearest_free, np.float64).reshape(-1),
    )


def request_from_params(params: dict[str, str]) -> PathRequest:
    """A PathRequest from selector parameters (start=x,y;goal=x,y and optional fields), checked
    by the codec like any other request."""

    def numbers(name):
        try:
            return [float(v) for v in params[name].split(",")]
        except ValueError:
            raise MessageError("value", f"{name} must be numbers separated by commas") from None

    def number(name):
        try:
            return float(params[name])
        except ValueError:
            raise MessageError("value", f"{name} must be a number") from None

    raw: dict = {"_type": PathRequest.TYPE, "_v": SCHEMA_VERSION}
    for name in ("start", "goal"):
        if name not in params:
            raise MessageError("missing_field", f"PathRequest.{name}")
        raw[name] = numbers(name)
    for name in ("h_f", "t_f", "unknown_cost", "max_step_m"):
        if name in params:
            raw[name] = number(name)
    if "request_id" in params:
        raw["request_id"] = params["request_id"]
    if "allow_unknown" in params:
        raw["allow_unknown"] = params["allow_unknown"].lower() in ("1", "true", "yes")
    return from_dict(raw, PathRequest, wire=False)


class PlannerService(Service):
    name = "planner"
    prepare_in_background = True  # prepare() only compiles kernels: live meanwhile
    tick_period_s = 0.2

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        nc = config.navgraph
        self.classes = ClassTable.load(config.general.class_table)
        self.grid = NavGrid.from_bounds(
            nc.bounds_min_xy, nc.bounds_max_xy, nc.resolution_m, nc.tile_size
        )
        self.grid.add_risk_layers()  # the patches' label distributions (planner risk modes)
        self.planner = Planner(self.grid, self.classes, config.planner)
        self.graph = GraphCopy(self.grid, self.note)
        self._next_sync = 0.0
        self.patches = 0
        self.patches_skipped = 0
        self.syncs = 0
        self.graph_queries = 0  # asked of navgraph (its books count them as received)
        self.queries = 0
        self.outcomes: dict[str, int] = {}
        self.times_ms: list[float] = []
        self._resync = False
        # A fleet member plans on the fleet's shared graph, around the other members.
        self.fleet = config.fleet
        self.graph_ns = self.fleet.shared_namespace(self.robot)
        self.members: dict[str, tuple[float, float, float]] = {}  # name -> (x, y, when heard)

    def prepare(self) -> None:
        # Before the liveliness token: whoever waits for the planner gets a compiled one.
        self.startup_step = "loading (or compiling) the numba kernels"
        self.log.info("kernels ready in %.1f s", warm_up(self.classes))

    def setup(self) -> None:
        r = self.robot
        self.subscribe(keys.graph_patch(self.graph_ns), self.on_patch, GraphPatch)
        self.queryable(keys.path_query(r), self.on_path)
        if r in self.fleet.robots:
            for m in self.fleet.robots:
                if m != r:
                    self.subscribe(keys.pose(m), lambda p, m=m: self.on_member_pose(m, p), Pose)
        self.queryable(keys.query(r, "planner", "stats"), lambda req: self.stats())
        self.sync()
        # A navgraph that (re)starts starts a new graph and a new patch sequence: fetch it then.
        # The callback only raises a flag; tick() does the work on the main loop.
        self._declared.append(
            self.session.liveliness().declare_subscriber(
                keys.alive(self.graph_ns, "navgraph"), self._on_navgraph_token
            )
        )

    def _on_navgraph_token(self, sample) -> None:
        import zenoh

        if sample.kind == zenoh.SampleKind.PUT:
            self._resync = True

    def tick(self) -> None:
        if (self._resync or self.graph.want_resync) and time.monotonic() >= self._next_sync:
            self._next_sync = time.monotonic() + 1.0  # a stream in doubt: one sync a second
            self._resync = False
            self.sync()

    # -- keeping the graph -------------------------------------------------------------------

    def sync(self) -> bool:
        """Replace the grid by navgraph's whole graph. False when navgraph does not answer."""
        timeout = self.config.planner.graph_sync_timeout_s
        self.graph_queries += 1
        try:
            reply = request(
                self.session, keys.query(self.graph_ns, "navgraph", "graph"), None, timeout
            )
        except QueryError as exc:
            self.log.info("no graph from navgraph (%s): waiting for patches", exc.kind)
            self._resync |= exc.kind == "warming_up"  # live before its kernels: ask again
            return False
        if not self.graph.usable_snapshot(reply):
            return False
        self._reset_grid()
        self.graph.adopt(reply)
        self.syncs += 1
        self.log.info(
            "graph synced from navgraph: %d nodes (patch %d)", len(reply.cells), reply.seq
        )
        return True

    def _reset_grid(self) -> None:
        g = self.grid
        self.grid = self.graph.grid = NavGrid(g.origin_xy, g.shape, g.resolution_m, g.tile_size)
        self.grid.add_risk_layers()
        self.planner = Planner(self.grid, self.classes, self.planner.config)

    def on_patch(self, patch: GraphPatch):
        why = self.graph.receive(patch)
        if why is None:
            self.patches_skipped += 1  # already in the graph we synced
            return ("dropped", "covered")
        self.patches += 1
        if why:  # applied across a gap; the sync on the next tick fills it
            self.note("patch_gap", f"graph patches: {why}")

    # -- path queries ------------------------------------------------------------------------

    def on_path(self, req: Request) -> PathReply:
        self.queries += 1
        try:
            if req.payload:
                msg = req.decode(PathRequest)
            else:
                msg = request_from_params(req.params)
        except MessageError as exc:
            # Still answered as a PathReply (ok false, `malformed`), and counted as rejected.
            result = PlanResult(False, MALFORMED, f"malformed request: {exc}")
            raise Reject(exc.kind, f"bad path request: {exc}", self._reply("", result)) from None
        now = time.monotonic()
        avoid = [
            (x, y) for x, y, t in self.members.values() if now - t <= self.fleet.pose_timeout_s
        ]
        result = self.planner.plan_request(msg, avoid, self.fleet.robot_clearance_m)
        return self._reply(msg.request_id, result)

    def on_member_pose(self, member: str, pose: Pose) -> None:
        """Another fleet member's pose: a moving obstacle for the next queries."""
        x, y, _ = self.fleet.to_fleet_frame(member, float(pose.position[0]), pose.position[1])
        self.members[member] = (x, y, time.monotonic())

    def _reply(self, request_id: str, result: PlanResult) -> PathReply:
        key = "ok" if result.ok else result.error
        self.outcomes[key] = self.outcomes.get(key, 0) + 1
        self.times_ms.append(result.time_ms)
        del self.times_ms[:-100]
        return reply_of(request_id, result)

    def stats(self) -> dict:
        t = np.array(self.times_ms) if self.times_ms else np.zeros(1)
        return {
            "tiles": self.grid.n_tiles,
            "nodes_known": self.grid.n_known(),
            "bytes": self.grid.nbytes,
            "patches": self.patches,
            "patches_skipped": self.patches_skipped,
            "last_patch_seq": self.graph.last_seq or 0,
            "syncs": self.syncs,
            "graph_queries": self.graph_queries,
            "queries": self.queries,
            "outcomes": dict(self.outcomes),
            "params": dataclasses.asdict(self.planner.config),
            "plan_ms_median": float(np.median(t)),
            "plan_ms_last": float(t[-1]),
        }

    def status_details(self) -> dict:
        s = self.stats()
        keep = ("nodes_known", "patches", "last_patch_seq", "queries", "plan_ms_median")
        return {k: s[k] for k in keep} | {"outcomes": s["outcomes"]}


def main(config: SmanaConfig) -> int:
    """Run the planner until SIGINT/SIGTERM."""
    return run_service(PlannerService, config)
