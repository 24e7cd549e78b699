"""The explorer service: Zenoh wiring around `exploration.Explorer`.

Inputs: `navgraph/patch` (GraphPatch, applied to the explorer's own `NavGrid` copy; the stream is
followed per producer like the planner's, `common/plausibility.py::SequenceFollower`) and
`robot/pose`. A pose must fit its stream's clock and may not jump further than the robot can
travel (`StampGate`, `PoseGate`: refused as `stamp` or `pose_jump`; both take a few poses to
agree on where and when the robot is, so no single pose sets the explorer's time or place). The
explorer's robot time runs on across a restarted simulator (the stamps' clock reset), so the time
budget can neither jump nor restart. Each tick (`explorer.control_rate_hz`) it hands the grid
around the robot and the latest pose to the core, asks the planner (`planner/path`, PathRequest)
for the paths the core wants costed, and publishes a VelocityCommand on `robot/cmd_vel` and its
state on `explorer/state` (a msgpack map; also answered as a query on the same key).

It also drives to the poses it is sent: queries `explorer/goal` and `explorer/goal/cancel`, the
feedback on `explorer/goal/feedback` (services/explorer/navigation.py has the contract); a query
by a wildcard selector drives nothing (refused `selector`).

When exploration is done (no view worth it, or the time budget spent), it stops the robot, saves
its final state into `<run_dir>/explorer/` (state.json, trajectory.csv, graph.npz) and exits with
status 0, which tells `smana up` that the run is over.

The wiring only: exploration itself is `exploration.Explorer`'s, its goal queries and feedback
`goal_queries.py`'s, its robot time and time budget `clocks.py`'s, what the run keeps of it (the
plan log, the path queries' books, the checkpoint it resumes from) `run_record.py`'s.
"""

from __future__ import annotations

import dataclasses
import math
import time
import uuid

import msgpack
import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import ConfigError, SmanaConfig
from smana.common.graph_copy import GraphCopy
from smana.common.messages import (
    GraphPatch,
    MessageError,
    PathReply,
    PathRequest,
    Pose,
    SemanticCloud,
    VelocityCommand,
)
from smana.common.navgrid import NavGrid
from smana.common.plausibility import PoseGate, StampGate
from smana.common.query import QueryError, request
from smana.common.service import Reject, Request, Service, kernels_loaded
from smana.services.explorer import frontier as fr
from smana.services.explorer.clocks import Budget, RobotClock
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.goal_queries import GoalQueries
from smana.services.explorer.navigation import GoalRefused
from smana.services.explorer.pose_filter import PoseFilter
from smana.services.explorer.run_record import RunRecord, plan_entry, state_message
from smana.services.explorer.team import Team

STATE_PERIOD_S = 0.5


class ExplorerService(Service):
    name = "explorer"
    prepare_in_background = True  # prepare() only compiles kernels: live meanwhile

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        self.cfg = config.explorer
        self.tick_period_s = 1.0 / self.cfg.control_rate_hz
        self.table = ClassTable.load(config.general.class_table)
        self.class_costs = self._class_costs()
        nav = config.navgraph
        self.grid = NavGrid.from_bounds(nav.bounds_min_xy, nav.bounds_max_xy, nav.resolution_m)
        # the costs the planner will use for our requests: its t_f, the table and our overrides
        flat, bound = fr.path_cost_scale(
            config.planner.t_f, self.table.costs(self.class_costs), nav.resolution_m
        )
        # A fleet member explores on the fleet's shared graph, with the others (team.py).
        self.fleet = config.fleet
        self.graph_ns = self.fleet.shared_namespace(self.robot)
        self.team = Team(self.fleet, self.robot) if self.robot in self.fleet.robots else None
        self.core = Explorer(
            self.cfg, self.table.traversable_lut, self.table.size, bound, flat, team=self.team
        )
        self.core.max_step_m = float(config.planner.max_step_m)  # what the planner climbs
        # the pose it steers by: the localisation's, filtered with the twist it commands
        self.pose_filter = PoseFilter(self.cfg.pose_filter)
        self.claims_asked = 0  # asked of the coordinator (its books count them as received)
        self.claim_errors: dict[str, int] = {}
        self.goals = GoalQueries(self.core, self.cfg, nav)
        self._grid_dirty = False
        self._last_pose_wall = -math.inf
        # the budget starts at the first tick with a map and a pose, not at start-up
        self.budget = Budget(self.cfg, time.monotonic())
        self.record = RunRecord(config.general.run_dir or None, time.monotonic())
        self._planner_alive = 0  # planners whose liveliness token is up
        self._planner_kernels = True  # no planner status said its kernels are compiling
        self._seq = 0
        self._next_state = 0.0
        self._need_sync = True
        self._next_sync = 0.0
        self._sync_failures = 0
        self.graph = GraphCopy(self.grid, self.note)
        g = config.general
        self.stamps = StampGate(g.stamp_window_s, g.max_time_rate, accept_while_acquiring=False)
        self.places = PoseGate(g.max_speed_mps, g.pose_slack_m)
        self._last_pose_stamp: float | None = None
        self.clock = RobotClock(g.stamp_window_s)  # runs on across a restarted simulator
        self.n_patches = 0
        self.graph_queries = 0  # asked of navgraph (its books count them as received)
        self.plan_time_ms = 0.0

    def _class_costs(self) -> dict[int, float]:
        try:
            return self.table.cost_overrides(self.cfg.class_costs)
        except ValueError as exc:
            raise ConfigError(f"explorer.class_costs: {exc}") from None

    def warm_up(self) -> None:
        self._resume()

    def _resume(self) -> None:
        """A restart in the same run directory continues the run's exploration (and a run that
        had finished stays finished: the supervisor may restart us after we exited)."""
        try:
            saved = self.record.read()
            if saved is None:
                return
            state, traj = saved
            self.core.resume(state, traj)
        except (OSError, ValueError, TypeError, KeyError) as exc:
            self.log.warning("could not resume from %s: %s", self.record.folder, exc)
            return
        self.record.resume(state)
        self.budget.spent_before = float(state.get("wall_time_s") or 0.0)
        self.clock.floor = float(state.get("t_s") or 0.0)
        self.record.goal_saved = self.core.goal
        goal = self.core.goal
        self.log.info(
            "resumed the run's exploration: %.1f m travelled, %d goals%s",
            self.core.distance_m,
            self.core.n_goals,
            ""
            if goal is None
            else f", driving on to ({goal.choice.xy[0]:.2f}, {goal.choice.xy[1]:.2f})",
        )
        if state.get("done"):
            self.log.info("exploration had finished in this run (%s)", state.get("done_reason"))
            self.core.finish(str(state.get("done_reason") or "finished"))

    # -- wiring -----------------------------------------------------------------------------------

    def prepare(self) -> None:
        # The view-gain kernel compiles on a cold numba cache: before the token, not mid-plan.
        self.startup_step = "loading (or compiling) the numba kernels"
        t0 = time.perf_counter()
        unknown = np.ones((8, 8), bool)
        tiny = dataclasses.replace(self.cfg.view, max_range_m=1.0, min_range_m=0.1, n_yaw=4)
        fov = fr.FovModel.build(self.grid.resolution_m, tiny)
        fr.view_gains(unknown, ~unknown, np.array([[4, 4]]), fov)
        fr.travel_distance_m(unknown, np.array([[4, 4]]), np.zeros(1), self.grid.resolution_m)
        fr.step_components(unknown, np.zeros((8, 8), np.float32), 0.3)
        self.log.info("kernels ready in %.1f s", time.perf_counter() - t0)

    def setup(self) -> None:
        r = self.robot
        self.cmd_pub = self.publisher(keys.cmd_vel(r), express=True)
        self.state_pub = self.publisher(keys.explorer_state(r))
        self.subscribe(keys.graph_patch(self.graph_ns), self.on_patch, GraphPatch)
        self.subscribe(keys.pose(r), self.on_pose, Pose)
        self.subscribe(keys.safety_scan(r), self.on_safety_scan, SemanticCloud)
        if self.team is not None:
            for m in self.fleet.robots:
                if m != r:
                    self.subscribe(keys.pose(m), lambda p, m=m: self.on_member_pose(m, p), Pose)
            self.subscribe(keys.claims(self.fleet.name), self.on_claims)
        self.queryable(keys.explorer_state(r), lambda req: self.core.state_dict())
        # goals it is sent (services/explorer/navigation.py); the ACL lets only the robot's
        # drive role and the base's operator ask these
        self.feedback_pub = self.publisher(keys.explorer_goal_feedback(r))
        self.queryable(keys.explorer_goal(r), self.on_goal)
        self.queryable(keys.explorer_goal_cancel(r), self.on_goal_cancel)
        self._declared.append(
            self.session.liveliness().declare_subscriber(
                keys.alive(r, "planner"), self._on_planner_token, history=True
            )
        )
        # A planner is live before its kernels are loaded (it answers `warming_up`, its status
        # says so): the budget waits for them.
        self._declared.append(
            self.session.declare_subscriber(keys.status(r, "planner"), self._on_planner_status)
        )
        self._sync_graph()

    def _sync_graph(self) -> None:
        """Ask navgraph for its whole graph: we may have started after it published patches,
        missed some, or the patch stream is in doubt (another producer, a jump). Retried from
        `tick` until it answers."""
        self._next_sync = time.monotonic() + 2.0
        self.graph_queries += 1
        try:
            reply = request(self.session, keys.query(self.graph_ns, "navgraph", "graph"), None, 2.0)
        except QueryError as exc:
            if self._sync_failures == 0:
                self.log.info("no graph from navgraph yet (%s): will ask again", exc.kind)
            self._sync_failures += 1
            return
        if not self.graph.usable_snapshot(reply):
            return
        self.graph.adopt(reply)
        self._patched()
        self._need_sync = False
        self.log.info("graph synced from navgraph: %d nodes", len(reply.cells))

    def on_member_pose(self, member: str, pose: Pose) -> None:
        x, y, _ = self.fleet.to_fleet_frame(member, pose.position[0], pose.position[1])
        self.team.update_position(member, x, y, pose.stamp_s)

    def on_claims(self, payload: bytes) -> None:
        try:
            claims = msgpack.unpackb(payload)["claims"]
            if not isinstance(claims, dict):
                raise TypeError("claims is not a map")
        except Exception as exc:
            raise Reject("malformed", f"coordinator claims: {exc}") from None
        self.team.update_goals(claims)

    def _claim(self, goal_xy):
        """Ask the coordinator for `goal_xy`. Without an answer the member plans alone (the
        views near the others' last known goals are still left out)."""
        self.claims_asked += 1
        body = {"robot": self.robot, "goal": [float(goal_xy[0]), float(goal_xy[1])]}
        key = keys.claim(self.fleet.name, self.robot)
        try:
            reply = request(self.session, key, body, self.fleet.claim_timeout_s)
            granted, holder = bool(reply["granted"]), reply.get("holder")
            claims = reply.get("claims") or {}
        except (QueryError, KeyError, TypeError) as exc:
            kind = getattr(exc, "kind", "malformed")
            self.claim_errors[kind] = self.claim_errors.get(kind, 0) + 1
            if self.claim_errors[kind] in (1, 10, 100):
                self.log.warning("no answer from the coordinator (%s): planning alone", kind)
            return True, None, None
        self.team.update_goals(claims)
        return granted, holder, claims.get(holder) if holder else None

    def _on_planner_token(self, sample) -> None:
        # a zenoh callback: count planners up (one per robot, or one on the base and the robot)
        import zenoh

        self._planner_alive += 1 if sample.kind == zenoh.SampleKind.PUT else -1

    def _on_planner_status(self, sample) -> None:
        # a zenoh callback: one flag
        if (got := kernels_loaded(sample)) is not None:
            self._planner_kernels = got[1]

    def on_patch(self, patch: GraphPatch):
        if self.graph.receive(patch) is None:
            return ("dropped", "covered")
        self._patched()
        if self.graph.want_resync:
            self._need_sync = True  # a gap, or joined mid-stream: fetch the whole graph

    def _patched(self) -> None:
        self.n_patches += 1
        self._grid_dirty = True

    def on_goal(self, req: Request) -> dict:
        """A goal: accepted (it pre-empts the running one) or refused, counted, nothing changed."""
        try:
            body = req.body()
        except MessageError as exc:
            body = exc
        try:
            s, reply = self.goals.goal(body, req.key, keys.explorer_goal(self.robot))
        except GoalRefused as exc:
            raise Reject(exc.kind, f"goal refused: {exc}", reply=exc.reply) from None
        self.log.info(
            "goal %s accepted: (%.2f, %.2f)%s within %.2f m%s",
            s.id,
            s.x,
            s.y,
            "" if s.yaw is None else f" yaw {math.degrees(s.yaw):.0f} deg",
            s.tolerance_m,
            "" if self.core.nav.active else f", and aborted: {self.core.nav.reason}",
        )
        self._send(*self.core.control())
        self._send_feedback()
        return reply

    def on_goal_cancel(self, req: Request) -> dict:
        """A cancel of the running goal: the robot stops at once."""
        try:
            body = req.body()
        except MessageError as exc:
            body = exc
        try:
            nav, reply = self.goals.cancel(body, req.key, keys.explorer_goal_cancel(self.robot))
        except GoalRefused as exc:
            raise Reject(exc.kind, f"cancel refused: {exc}", reply=exc.reply) from None
        self._send(0.0, 0.0)
        self.log.info("goal %s canceled", nav.id)
        self._send_feedback()
        return reply

    def _send_feedback(self, now: float | None = None) -> None:
        for fb in self.goals.feedback(time.monotonic() if now is None else now):
            self.feedback_pub.put(fb)
            if fb["state"] != "active":
                self.log.info("goal %s %s %s", fb["id"], fb["state"], fb["reason"])

    def on_pose(self, pose: Pose) -> None:
        stamp = float(pose.stamp_s)
        when = self.stamps.check(stamp)
        if not when.ok:
            raise Reject(when.kind, f"pose {pose.seq}: {when.reason}")
        where = self.places.check(stamp, pose.position)
        if not where.ok:
            raise Reject(where.kind, f"pose {pose.seq}: {where.reason}")
        last = self.core.t_now if self.core.pose is not None else None
        t, restarted = self.clock.robot_time(stamp, last, when.reset)
        if restarted:  # a new simulator: robot time runs on from here
            self.note(
                "clock_reset",
                f"pose stamps restarted at {stamp:.3f} s; robot time runs on from {last:.3f} s",
            )
        if where.reset:
            self.note("pose_reset", f"the robot reappeared at {pose.position[:2].tolist()}")
        # a fleet member plans on the fleet's graph: its pose in the fleet's frame
        x, y, yaw = self.fleet.to_fleet_frame(
            self.robot, float(pose.position[0]), float(pose.position[1]), pose.yaw
        )
        if where.reset:
            self.pose_filter.forget()  # the robot reappeared elsewhere
        self.core.update_pose(*self.pose_filter.update(x, y, yaw, t), t)
        self._last_pose_wall = time.monotonic()
        self._last_pose_stamp = stamp

    def on_safety_scan(self, scan: SemanticCloud) -> None:
        """The safety scanner's points (base frame) for the guard, placed by the pose the robot
        steers by now: a scan taken further from that pose's stamp than the guard trusts is
        refused."""
        if scan.frame_id != "base_link":
            raise Reject("frame", f"safety scan {scan.seq} is in {scan.frame_id!r}, not base_link")
        if self.core.pose is None or self._last_pose_stamp is None:
            raise Reject("settling", f"safety scan {scan.seq} before the first pose")
        lag = abs(float(scan.stamp_s) - self._last_pose_stamp)
        if lag > self.cfg.guard.stale_s:
            raise Reject(
                "stamp", f"safety scan {scan.seq}: {lag:.2f} s from the latest pose's stamp"
            )
        self.core.guard.add(scan.points, self.core.pose, self.core.t_now)

    # -- the control loop -------------------------------------------------------------------------

    def tick(self) -> None:
        now = time.monotonic()
        if self.core.done:
            self._finish()
            return
        if now - self._last_pose_wall > self.cfg.pose_timeout_s:
            self._send(0.0, 0.0)  # no pose, no driving
            self._send_feedback(now)  # a goal's sender still hears from it (its pose is stale)
            return
        if self.core.grid is not None:
            self.budget.start(now)
        # the budget and the start-up's patience are exploration's: a navigator waits for goals
        exploring = self.core.exploring and not self.core.nav_active
        if exploring and self.budget.exhausted(now):
            self.core.finish("time_budget")
            return
        if self.budget.out_of_patience(now) and self.core.exploring:
            missing = "planner" if self._planner_alive == 0 else "navigation graph"
            self.log.error("no %s after %.0f s: giving up", missing, self.budget.waited(now))
            self.core.finish("no_planner" if self._planner_alive == 0 else "no_graph")
            return
        if self._need_sync and now >= self._next_sync:
            self._sync_graph()
        # The core gets a grid, and its budget starts, only once a planner is there to cost
        # paths: on a cold numba cache the planner may be ready long after the map.
        if self._grid_dirty and self._planner_alive > 0 and self._planner_kernels:
            self._refresh_grid()
        reason = self.core.wants_plan()
        if reason is not None and self.core.grid is not None:
            self._send(*self.core.control())  # keep the last command fresh while we think
            t0 = time.perf_counter()
            claim = self._claim if self.team is not None else None
            outcome = self.core.plan(self._path_cost, reason, claim)
            self.plan_time_ms = (time.perf_counter() - t0) * 1e3
            entry = plan_entry(self.core, outcome, reason)  # a goal this plan set, or None
            self.record.log_plan(entry)
            if entry is not None:
                c = outcome.chosen
                self.log.info(
                    "goal (%.2f, %.2f) yaw %.0f deg: gain %.2f m2, cost %.2f (%s, %d queries, "
                    "%.0f ms)",
                    c.xy[0],
                    c.xy[1],
                    math.degrees(c.yaw),
                    c.gain_m2,
                    c.path_cost,
                    reason,
                    c.n_queries,
                    self.plan_time_ms,
                )
        v, w = self.core.control()
        self._send(v, w)
        self._send_feedback(now)
        if now >= self._next_state:
            self._next_state = now + STATE_PERIOD_S
            self.state_pub.put(self._state())
        if self.record.checkpoint_due(now, self.core.goal):
            self.save(final=False)
        if self.core.done:
            self._finish()

    def _refresh_grid(self) -> None:
        """Hand the core the grid's dense box around what is known (`GridBox.around_known`)."""
        box = GridBox.around_known(self.grid, self.cfg.view.max_range_m)
        if box is None:
            return
        self.core.update_grid(box)
        self._grid_dirty = False

    def _path_cost(self, start_xy: np.ndarray, goal_xy: np.ndarray, allow_unknown: bool = False):
        self.record.paths.queries += 1
        req = PathRequest(
            request_id=uuid.uuid4().hex[:12],
            start=np.asarray(start_xy, np.float64)[:2],
            goal=np.asarray(goal_xy, np.float64)[:2],
            class_costs=dict(self.class_costs),
            allow_unknown=allow_unknown,
        )
        try:
            # a goal's feedback goes on at its rate while the planner thinks
            wait = self._send_feedback if self.core.nav_active else None
            reply = request(
                self.session,
                keys.path_query(self.robot),
                req,
                self.cfg.planner_timeout_s,
                while_waiting=wait,
            )
        except QueryError as exc:
            self._path_error(exc.kind)
            return None
        if not isinstance(reply, PathReply):
            self._path_error("malformed")
            return None
        if not reply.ok or len(reply.path) == 0:
            self._path_error(reply.error or "empty")
            return None
        self.record.paths.ok += 1
        return float(reply.cost_total), np.asarray(reply.path, np.float64)

    def _path_error(self, kind: str) -> None:
        if self.record.paths.failed(kind):
            self.log.warning(
                "the planner does not answer (%d times)", self.record.paths.errors[kind]
            )

    def _send(self, v: float, w: float) -> None:
        self.pose_filter.set_speed(v)
        self._seq += 1
        self.cmd_pub.put(VelocityCommand(time.time(), self._seq, float(v), float(w), "explorer"))

    def _state(self) -> dict:
        names = {str(i): c.name for i, c in self.table.classes.items()}
        return state_message(self.core, names, self.pose_filter.noise_sd_m)

    def _finish(self) -> None:
        if self.record.final:
            return
        self._send(0.0, 0.0)
        self.log.info(
            "exploration done (%s): %.1f m2 explored, %.1f m travelled, %d goals, %.0f s",
            self.core.done_reason,
            self.core.explored_m2,
            self.core.distance_m,
            self.core.n_goals,
            self.core.elapsed_s(),
        )
        self.state_pub.put(self._state())
        self.save()
        self.stop()

    def on_stop(self) -> None:
        if self.ready_s is None:
            return  # stopped before it was ready: the run's checkpoint stays as it was
        try:
            self._send(0.0, 0.0)
            # a goal's sender hears that it ends here (a restarted explorer does not resume it)
            self.core.abort_goal("the explorer stopped")
            self._send_feedback()
        except Exception:  # the session may already be closing
            pass
        self.save()

    def save(self, final: bool = True) -> None:
        """State, trajectory and (when final) the grid into <run_dir>/explorer/ (run_record.py)."""
        if self.record.writes(final):
            wall_s = self.budget.spent(time.monotonic())
            c = self.core
            self.record.write(self._state(), c.history, c.trajectory, wall_s, self.grid, final)

    def status_details(self) -> dict:
        c = self.core
        paths = self.record.paths
        return {
            "nav_goal": c.nav_state(),
            "progress": c.progress(),
            "mode": c.mode,
            "explored_m2": c.explored_m2,
            "distance_m": c.distance_m,
            "frontier_size": c.frontier_size,
            "n_goals": c.n_goals,
            "n_patches": self.n_patches,
            "path_queries": paths.queries,
            "graph_queries": self.graph_queries,
            "path_ok": paths.ok,
            "path_errors": dict(paths.errors),
            "plan_time_ms": self.plan_time_ms,
        } | (
            {}
            if self.team is None
            else {
                "claims_asked": self.claims_asked,
                "claim_errors": dict(self.claim_errors),
                "team_stops": self.team.n_stops,
            }
        )


def main(config: SmanaConfig) -> int:
    return ExplorerService(config).run()
