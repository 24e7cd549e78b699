"""The ros2 service: smana as a ROS 2 node over rmw_zenoh (the mapping is in `rmw.py`, the
conversions in `convert.py`, the state in `bridge.py`; this file is the wiring).

Out, for robot R (node `/smana/R/<ros2.node_name>`, frame `map`; every frame name with the
prefix of `Ros2Config.frames`, `R/map` in a simulated fleet):
- `/smana/R/map` sensor_msgs/PointCloud2 (x, y, z, rgb, label), transient-local, at most every
  `ros2.map_period_s` when the map changed; kept from `mapper/delta` (resynchronised from
  `mapper/snapshot` at start, on a gap and when the mapper restarts);
- `/smana/R/costmap` nav_msgs/OccupancyGrid of the navigation graph, transient-local; kept from
  `navgraph/patch` (`common/graph_copy.py`, synced from `navgraph/graph`); the same graph as a
  nav2_msgs/Costmap on Nav2's scale on `/smana/R/costmap_raw` (Nav2's name for it);
- `/smana/R/path` nav_msgs/Path and `/smana/R/goal` geometry_msgs/PoseStamped from
  `explorer/state`, when they change;
- `/smana/R/odom` nav_msgs/Odometry from `robot/pose`, and in simulation the robot's frames
  (map -> odom -> base_link) on `ros2.tf_topic` (/tf, or /smana/R/tf when logged in as a user);
- a ROS 2 service `/smana/R/plan` (nav_msgs/srv/GetPlan), answered by smana's planner;
- ROS 2 actions `/smana/R/navigate_to_pose` (nav2_msgs NavigateToPose, driven by the explorer's
  navigator mode) and `/smana/R/compute_path_to_pose` (ComputePathToPose, smana's planner), and
  `/goal_pose` (RViz2's "2D Goal Pose") as a NavigateToPose goal (`actions.py`).

In, for a real robot (`ros2.robot_input`; by default when smana's simulator is off):
`ros2.cloud_topic` PointCloud2 (latest wins) -> `robot/scan`, `ros2.odom_topic` Odometry ->
`robot/pose`, `ros2.tf_static_topic` for the sensor's pose on the robot, and `robot/cmd_vel` ->
`ros2.cmd_vel_topic` geometry_msgs/Twist.

Every message in is counted once (`common/service.py`); a ROS message that does not decode as
its type, a cloud that cannot be placed or read, a plan request without a valid attachment is
rejected with its reason and the service goes on. The robot's Odometry and PointCloud2 pass the
checks smana's own poses and clouds pass (the codec's bounds, the stream's clock, how far the
robot can travel: `bridge.py`) before anything is republished; /tf_static holds at most
`bridge.MAX_STATIC_FRAMES` frames.

Nothing on the main loop waits for a query: GetPlan is answered by plan workers (`jobs.py`, each
request with a deadline of PLAN_TIMEOUT_S from its arrival; past `PLAN_WAITING` waiting requests
one is refused `queue_full`), and the map and graph snapshots are fetched by a sync worker and
adopted on the loop when they come (the deltas and patches that arrive meanwhile wait for them).
So odometry and velocity commands are forwarded while a planner or mapper does not answer.
"""

from __future__ import annotations

import queue
import threading
import time

import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.config.ros2 import Ros2Frames
from smana.common.graph_copy import GraphCopy
from smana.common.messages import (
    GraphPatch,
    MapDelta,
    MessageError,
    PathReply,
    PathRequest,
    Pose,
    VelocityCommand,
)
from smana.common.navgrid import NavGrid
from smana.common.plausibility import APPLY, COVERED, SequenceFollower
from smana.common.query import QueryError, request
from smana.common.service import Reject, Reply, Request, Service, run_service

from . import bridge, convert, costmap_types, safety_input
from .actions import Ros2Actions
from .bridge import (
    CloudInput,
    ExplorerView,
    MapCopy,
    OdometryInput,
    StreamSync,
    checked,
    twist_between,
)
from .jobs import Jobs
from .rmw import LATCHED_QOS, SENSOR_QOS, SERVICE, SUBSCRIPTION, QoS, RosNode, RosTypes

RESYNC_PERIOD_S = 1.0
SYNC_TIMEOUT_S = 5.0  # a snapshot query waits this long (on the sync worker)
PLAN_TIMEOUT_S = 5.0  # a GetPlan is answered within this long of its arrival
PLAN_THREADS, PLAN_WAITING = 2, 8  # plan workers, and requests that may wait for one
MAX_HELD = 1000  # deltas (patches) kept while their snapshot is being fetched
CLOUD = "sensor_msgs/msg/PointCloud2"
ODOM = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
COSTMAP = costmap_types.COSTMAP


def robot_input_on(config: SmanaConfig) -> bool:
    mode = config.ros2.robot_input
    return mode == "on" or (mode == "auto" and not config.deploy.sim.enabled)


def frames_of(config: SmanaConfig) -> Ros2Frames:
    """The frame names `config`'s robot's ros2 service publishes and accepts
    (`Ros2Config.frames`, with the robots the config names and whether it reads a real robot)."""
    robots = [*config.fleet.robots, *config.deploy.robots]
    return config.ros2.frames(config.general.robot, robots, robot_input_on(config))


def tf_topic_dropped(config: SmanaConfig) -> str | None:
    """Why the router of a secured profile would drop the simulated robot's frames (a tf topic
    set outside /smana/<robot> while the service logs in as a user: the policy grants its ros2
    identity /smana/<robot>/** only, and the robot's cmd_vel); None when it would not."""
    rc, robot = config.ros2, config.general.robot
    topic = rc.tf_topic_for(robot, secured=True)
    if not config.zenoh.credentials_file or topic.startswith(f"/smana/{robot}/"):
        return None
    return (
        f"ros2.tf_topic {topic} is outside /smana/{robot}: the secured profile's policy lets "
        f"{robot}'s ros2 service publish only there, so its router drops these frames"
    )


class Ros2Service(Service):
    name = "ros2"
    tick_period_s = 0.1
    # Transient-local topics are AdvancedPublishers, which order their cache by timestamps
    # (rmw_zenoh's session config turns timestamping on for the same reason).
    zenoh_settings = {"timestamping/enabled": True}

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        rc = config.ros2
        self.classes = ClassTable.load(config.general.class_table)
        if rc.label_field == "none" and self.classes.name != "geometric":
            raise ValueError(
                "ros2.label_field=none labels clouds with the geometric labeller: "
                "set general.class_table=geometric too"
            )
        nc = config.navgraph
        self.grid = NavGrid.from_bounds(
            nc.bounds_min_xy, nc.bounds_max_xy, nc.resolution_m, nc.tile_size
        )
        # under a risk mode the costmap shows what the planner pays: keep the distributions
        self.risk = config.planner.risk != "label"
        if self.risk:
            self.grid.add_risk_layers()
        self.graph = GraphCopy(self.grid, self.note)
        self.map = MapCopy()
        self.deltas_in = SequenceFollower()
        self.robot_input = robot_input_on(config)
        self.frames = frames_of(config)
        # the simulated robot's frames: none with a real robot's input (the robot owns them)
        secured = bool(config.zenoh.credentials_file)
        self.tf_topic = None if self.robot_input else rc.tf_topic_for(self.robot, secured)
        self.cloud_input: CloudInput | None = None
        self.types: RosTypes | None = None
        self.node: RosNode | None = None
        # the map and the graph, each resynchronised from its producer's snapshot
        self.syncs = {w: StreamSync(RESYNC_PERIOD_S, MAX_HELD) for w in ("map", "graph")}
        self._next_pub = {"map": 0.0, "costmap": 0.0, "costmap_raw": 0.0}
        self._published = {"map": -1, "costmap": -1, "costmap_raw": -1}
        self._costmap_load_t: float | None = None  # nav2 Costmap's map_load_time
        self.explorer_view = ExplorerView()
        self._last_pose: Pose | None = None
        self.sent = dict.fromkeys(
            ("map", "costmap", "costmap_raw", "path", "goal", "odom", "tf", "cmd_vel"), 0
        )
        self.received = {"clouds": 0, "odometry": 0, "tf_static": 0, "plans": 0}
        self.odometry_input = OdometryInput(config.general)
        self.plan_jobs: Jobs | None = None
        self.sync_jobs: Jobs | None = None
        self._plan_lock = threading.Lock()  # plan workers share `received["plans"]`
        self._fetched: queue.SimpleQueue = queue.SimpleQueue()  # (what, snapshot or QueryError)
        self.actions: Ros2Actions | None = None

    def prepare(self) -> None:
        self.startup_step = "loading ROS 2 message types"
        self.types = RosTypes()
        labeller = None
        if self.config.ros2.label_field == "none":
            from smana.common.geometric import GeometricLabeller

            self.startup_step = "loading (or compiling) the geometric labeller"
            labeller = GeometricLabeller.from_config(self.config).label
            labeller(np.zeros((1, 3), np.float32), np.zeros(3))  # compile before going live
        if self.robot_input:
            self.cloud_input = CloudInput(self.config, labeller, self.frames)

    def setup(self) -> None:
        r, rc = self.robot, self.config.ros2
        ns = f"/smana/{r}"
        # Every endpoint's token waits until the whole node can answer (the end of setup).
        self.node = RosNode(
            self.session, self.types, rc.domain_id, rc.node_name, ns, announce=False
        )
        node = self.node
        self.pubs = {
            "map": node.publisher(f"{ns}/map", CLOUD, LATCHED_QOS),
            "costmap": node.publisher(f"{ns}/costmap", "nav_msgs/msg/OccupancyGrid", LATCHED_QOS),
            "costmap_raw": node.publisher(f"{ns}/costmap_raw", COSTMAP, LATCHED_QOS),
            "path": node.publisher(f"{ns}/path", "nav_msgs/msg/Path", LATCHED_QOS),
            "goal": node.publisher(f"{ns}/goal", "geometry_msgs/msg/PoseStamped", LATCHED_QOS),
            "odom": node.publisher(f"{ns}/odom", ODOM, QoS()),
        }
        if self.tf_topic is not None:
            # In simulation nobody else owns the robot's frames: map -> odom (identity) and
            # odom -> base_link go on the tf topic, so RViz2 can show the robot in any fixed
            # frame. A real robot publishes its own odom -> base_link; smana then stays off /tf.
            self.pubs["tf"] = node.publisher(self.tf_topic, TF, QoS(depth=100))
            if why := tf_topic_dropped(self.config):
                self.log.warning("%s", why)
        self.subscribe(keys.map_delta(r), self.on_delta, MapDelta)
        self.subscribe(keys.graph_patch(r), self.on_patch, GraphPatch)
        self.subscribe(keys.explorer_state(r), self.on_explorer_state)
        self.subscribe(keys.pose(r), self.on_pose, Pose)
        self.plan_jobs = Jobs("ros2-plan", PLAN_THREADS, PLAN_WAITING)
        self.sync_jobs = Jobs("ros2-sync", 1, 2)
        self._plan_key, _ = node.endpoint(SERVICE, f"{ns}/plan", "nav_msgs/srv/GetPlan")
        # ROS 2 clients ask complete queryables. Not `self.queryable`: its queries are answered
        # on the main loop, and a plan waits for the planner.
        self._declared.append(
            self.session.declare_queryable(self._plan_key, self._on_plan_query, complete=True)
        )
        self.actions = Ros2Actions(self, ns)
        if self.robot_input:
            cloud_key, _ = node.endpoint(SUBSCRIPTION, rc.cloud_topic, CLOUD, SENSOR_QOS)
            self.subscribe_latest(cloud_key, self.on_cloud)
            odom_key, _ = node.endpoint(SUBSCRIPTION, rc.odom_topic, ODOM, QoS())
            self.subscribe(odom_key, self.on_odometry)
            tf_qos = QoS(transient_local=True, depth=100)
            tf_key, _ = node.endpoint(SUBSCRIPTION, rc.tf_static_topic, TF, tf_qos)
            self.subscribe(tf_key, self.on_tf_static)
            self._query_history(tf_key, self.on_tf_static)
            self.pubs["cmd_vel"] = node.publisher(rc.cmd_vel_topic, "geometry_msgs/msg/Twist")
            ci = rc.cloud_input
            self.scan_pub = self.publisher(keys.scan(r) if ci == "scan" else keys.cloud(r))
            if ci not in self.config.mapper.inputs:
                self.log.warning(
                    "the robot's clouds go to robot/%s but mapper.inputs is %s: nothing will be "
                    "mapped; set --set 'mapper.inputs=[\"%s\"]'",
                    ci,
                    self.config.mapper.inputs,
                    ci,
                )
            self.pose_pub = self.publisher(keys.pose(r))
            self.subscribe(keys.cmd_vel(r), self.on_cmd_vel, VelocityCommand)
            if rc.safety_scan_topic:  # the robot's safety scanner, for the explorer's guard
                safety_input.wire(self, node, r, SENSOR_QOS, self._ros)
        self._declared.append(
            self.session.liveliness().declare_subscriber(keys.alive(r, "*"), self._on_alive)
        )
        node.announce()
        self.log.info(
            "ROS 2 node %s/%s on domain %d (zenoh %s), frames %s%s",
            ns,
            rc.node_name,
            rc.domain_id,
            node.zid,
            f"{self.frames.map} -> {self.frames.odom} -> {self.frames.base}",
            ", reading the robot's topics" if self.robot_input else f" on {self.tf_topic}",
        )

    def _query_history(self, key: str, handler) -> None:
        """What transient-local publishers already sent (their AdvancedPublisher caches), as a
        late-joining rmw_zenoh subscription asks for it."""
        try:
            replies = list(self.session.get(f"{key}/@adv/pub/**?_anyke", timeout=1.0))
        except Exception as exc:  # noqa: BLE001 - history is a bonus; live samples follow
            self.note("history_failed", f"{key}: {exc}")
            return
        # Query replies are not samples the books count: each is an event, taken or refused.
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                handler(reply.ok.payload.to_bytes())
                self.events["history_taken"] += 1
            except (MessageError, Reject) as exc:
                self.note("history_refused", f"{key}: cached sample refused: {exc}")

    def _on_alive(self, sample) -> None:
        import zenoh

        if sample.kind == zenoh.SampleKind.PUT:
            service = str(sample.key_expr).rsplit("/", 1)[-1]
            if service in ("mapper", "navgraph"):  # a (re)started producer: new stream
                self.syncs["map" if service == "mapper" else "graph"].wanted = True

    def on_stop(self) -> None:
        for jobs in (self.plan_jobs, self.sync_jobs):
            if jobs is not None:
                jobs.close()
        if self.actions is not None:
            self.actions.close()
        if self.node is not None:
            self.node.close()

    # -- smana -> ROS --------------------------------------------------------------------------

    def _send(self, what: str, msg) -> None:
        self.pubs[what].put(msg)
        with self._counter_lock:
            self.sent[what] += 1
            self.msgs_out += 1

    def on_delta(self, delta: MapDelta):
        if self.syncs["map"].syncing:  # applied after the snapshot
            return self.syncs["map"].hold(delta)
        action, why = self.deltas_in.check(delta.producer, delta.seq)
        if action == COVERED:
            return ("dropped", "covered")
        if action != APPLY:
            raise Reject(action, f"map delta {delta.seq}: {why}; resync asked")
        self.map.apply(delta)
        self.deltas_in.advance(delta.producer, delta.seq)
        if why:
            self.note("delta_gap", f"map deltas: {why}")

    def on_patch(self, patch: GraphPatch):
        if self.syncs["graph"].syncing:
            return self.syncs["graph"].hold(patch)
        if self.graph.receive(patch) is None:
            return ("dropped", "covered")

    def on_explorer_state(self, payload: bytes) -> None:
        changed = self.explorer_view.update(payload)
        if changed is None:
            return
        path, xy, yaw, t = changed
        frame = self.frames.map
        self._send("path", convert.path(self.types, path, t, frame))
        if xy is not None:
            self._send("goal", convert.pose_stamped(self.types, xy, yaw, t, frame))

    def on_pose(self, pose: Pose) -> None:
        twist = twist_between(self._last_pose, pose)
        self._last_pose = pose
        if self.actions is not None:
            self.actions.on_pose(float(pose.position[0]), float(pose.position[1]))
        f = self.frames
        self._send("odom", convert.odometry(self.types, pose, f.map, f.base, twist))
        if "tf" in self.pubs:
            self._send("tf", convert.robot_frames(self.types, pose, f.map, f.odom, f.base))

    def tick(self) -> None:
        now = time.monotonic()
        self._take_snapshots()
        for what, sync in self.syncs.items():
            stream = self.deltas_in if what == "map" else self.graph
            if sync.due(now, bool(stream.want_resync)):
                if not self.sync_jobs.submit(lambda w=what: self._fetch(w)):
                    sync.syncing = False
        self._publish_latched("map", self.map.version, self._map_message, now)
        self._publish_latched("costmap", self.grid.version, self._costmap_message, now)
        self._publish_latched("costmap_raw", self.grid.version, self._costmap_raw_message, now)
        if self.actions is not None:
            self.actions.tick()

    def _publish_latched(self, what: str, version: int, make, now: float) -> None:
        period = getattr(self.config.ros2, f"{what.removesuffix('_raw')}_period_s")
        if version == self._published[what] or now < self._next_pub[what]:
            return
        msg = make()
        if msg is None:
            return
        self._send(what, msg)
        self._published[what] = version
        self._next_pub[what] = now + period

    def _stamp(self) -> float:
        return self._last_pose.stamp_s if self._last_pose is not None else time.time()

    def _map_message(self):
        centres, labels, _ = convert.within_budget(
            self.map.centres,
            self.map.labels,
            self.map.resolution_m,
            self.config.ros2.map_max_points,
        )
        return convert.map_cloud(
            self.types, centres, labels, self.classes.colour_lut, self._stamp(), self.frames.map
        )

    def _costmap_message(self):
        return convert.occupancy_grid(
            self.types,
            self.grid,
            self.classes.cost_lut,
            self._stamp(),
            self.frames.map,
            planner=self.config.planner,
        )

    def _costmap_raw_message(self):
        t = self._stamp()
        if self._costmap_load_t is None:
            self._costmap_load_t = t
        cost_lut = self.classes.cost_lut
        load_t, frame = self._costmap_load_t, self.frames.map
        return convert.nav2_costmap(
            self.types, self.grid, cost_lut, t, load_t, frame, planner=self.config.planner
        )

    def _fetch(self, what: str) -> None:
        """The sync worker: ask the map's or the graph's producer for its snapshot."""
        r = self.robot
        key = (
            keys.query(r, "mapper", "snapshot")
            if what == "map"
            else keys.query(r, "navgraph", "graph")
        )
        try:
            reply = request(self.session, key, None, SYNC_TIMEOUT_S)
        except QueryError as exc:
            reply = exc
        self._fetched.put((what, reply))

    def _take_snapshots(self) -> None:
        """The main loop: adopt the snapshots fetched since the last tick, then apply what was
        held while each was on its way."""
        while True:
            try:
                what, reply = self._fetched.get_nowait()
            except queue.Empty:
                return
            if isinstance(reply, QueryError):
                self.log.info("no %s snapshot yet (%s)", what, reply.kind)
                ok = False
            else:
                ok = self._sync(what, reply)
            held = self.syncs[what].done(ok)
            apply = self.on_delta if what == "map" else self.on_patch
            for msg in held:
                try:
                    apply(msg)
                except Reject as exc:
                    self.note("held_" + exc.kind, f"a {what} update held during the sync: {exc}")

    def _sync(self, what: str, reply) -> bool:
        """Replace the map copy or the graph copy by its producer's snapshot."""
        if what == "map":
            if not isinstance(reply, MapDelta):
                self.note("bad_snapshot", "mapper/snapshot did not answer with a MapDelta")
                return False
            self.map.reset(reply)
            self.deltas_in.synced(reply.producer, reply.seq)
        else:
            if not self.graph.usable_snapshot(reply):
                return False
            g = self.grid
            self.grid = self.graph.grid = NavGrid(g.origin_xy, g.shape, g.resolution_m, g.tile_size)
            if self.risk:
                self.grid.add_risk_layers()
            self.graph.adopt(reply)
            self._published["costmap"] = self._published["costmap_raw"] = -1
        return True

    # -- ROS -> smana (a real robot) -----------------------------------------------------------

    def _ros(self, payload: bytes, typename: str):
        try:
            return self.types.deserialize(payload, typename)
        except Exception as exc:  # noqa: BLE001 - any CDR that is not this type
            raise MessageError("malformed", f"not a {typename}: {type(exc).__name__}") from None

    def on_cloud(self, payload: bytes) -> None:
        cloud = self.cloud_input.convert(self._ros(payload, CLOUD))
        _, wire = checked(cloud, "cloud")  # what the mapper would refuse is refused here
        self.received["clouds"] += 1
        if cloud.n_dropped_nonfinite:
            self.note("points_dropped", f"{cloud.n_dropped_nonfinite} points not finite")
        self.scan_pub.put(wire)

    def on_odometry(self, payload: bytes) -> None:
        pose, wire = self.odometry_input.checked(self._ros(payload, ODOM))
        self.cloud_input.poses.add(pose.stamp_s, pose.position, pose.orientation_xyzw)
        self.received["odometry"] += 1
        self.pose_pub.put(wire)

    def on_tf_static(self, payload: bytes) -> None:
        before = self.cloud_input.static_refused
        self.received["tf_static"] += self.cloud_input.add_static(self._ros(payload, TF))
        if refused := self.cloud_input.static_refused - before:
            self.note(
                "tf_static_refused",
                f"{self.config.ros2.tf_static_topic}: {refused} transform(s) refused (not "
                f"finite, a frame name over {bridge.MAX_FRAME_NAME} characters, or past "
                f"{bridge.MAX_STATIC_FRAMES} frames)",
                refused,
            )

    def on_cmd_vel(self, cmd: VelocityCommand) -> None:
        self._send("cmd_vel", convert.twist(self.types, cmd.linear_mps, cmd.angular_radps))

    # -- the plan service ----------------------------------------------------------------------

    def _on_plan_query(self, query) -> None:
        """zenoh's thread: count the request in and hand it to a plan worker; never waits."""
        with self.books.lock:
            self.books.received += 1
            self.books.in_flight += 1
        deadline = time.monotonic() + PLAN_TIMEOUT_S
        taken = self.plan_jobs.submit(
            lambda: self._plan(query, deadline), lambda: self._plan_dropped(query, "stopping")
        )
        if not taken:
            self._plan_dropped(query, "stopping" if self.stopping else "queue_full")

    def _plan_dropped(self, query, why: str) -> None:
        self.books.settle("dropped", why)
        self._log_kind(why, f"GetPlan dropped: {why}", self.books.dropped[why])
        self._reply_err(query, why, f"GetPlan not answered: {why}", False)
        _finish(query)

    def _plan(self, query, deadline: float) -> None:
        """A plan worker: answer one GetPlan by its deadline; settle it in the books."""
        try:
            self._answer_plan(query, deadline)
        finally:
            _finish(query)  # the asker's get ends now, not when the query is collected

    def _answer_plan(self, query, deadline: float) -> None:
        try:
            size = len(query.payload) if query.payload is not None else 0
            if size > self.max_payload_bytes:
                raise MessageError("oversize", f"{size} bytes > {self.max_payload_bytes}")
            payload = query.payload.to_bytes() if query.payload is not None else None
            att = query.attachment.to_bytes() if query.attachment is not None else None
            reply = self.on_plan(Request(self._plan_key, {}, payload, False, att), deadline)
        except (Reject, MessageError) as exc:
            self._rejected(exc.kind, f"GetPlan: {exc}")
            self._reply_err(query, exc.kind, str(exc), False)
            return
        except Exception as exc:  # noqa: BLE001 - a bug: counted, logged, the worker goes on
            self._internal(exc, "GetPlan")
            self._reply_err(query, "internal", f"{type(exc).__name__}: {exc}", False)
            return
        self.books.settle("accepted")
        self._send_reply(query, self._plan_key, reply.payload, None, reply.attachment)

    def on_plan(self, req: Request, deadline: float | None = None) -> Reply:
        """A GetPlan request -> its response, asking smana's planner until `deadline`
        (monotonic; PLAN_TIMEOUT_S from now by default). Runs on a plan worker."""
        if deadline is None:
            deadline = time.monotonic() + PLAN_TIMEOUT_S
        try:
            reply_attachment = self.node.reply_attachment(req.attachment)
        except ValueError as exc:
            raise Reject("malformed", f"GetPlan request: {exc}") from None
        msg = self._ros(req.payload or b"", "nav_msgs/srv/GetPlan_Request")
        try:
            start, _ = convert.pose_of(msg.start.pose)
            goal, _ = convert.pose_of(msg.goal.pose)
        except ValueError as exc:
            raise Reject("value", f"GetPlan request: {exc}") from None
        with self._plan_lock:
            self.received["plans"] += 1
            n = self.received["plans"]
        ask = PathRequest(request_id=f"ros2-{n}", start=start[:2], goal=goal[:2])
        try:
            left = deadline - time.monotonic()
            if left <= 0.05:
                raise QueryError("timeout", "the request waited past its deadline")
            answer = request(self.session, keys.path_query(self.robot), ask, left)
            path = answer.path if isinstance(answer, PathReply) and answer.ok else np.zeros((0, 3))
            if isinstance(answer, PathReply) and not answer.ok:
                self.log.info("GetPlan: no path (%s: %s)", answer.error, answer.message)
        except QueryError as exc:
            self.log.info("GetPlan: planner did not answer (%s)", exc.kind)
            path = np.zeros((0, 3))
        body = convert.plan_response(self.types, path, self._stamp(), self.frames.map)
        return Reply(self.types.serialize(body, "nav_msgs/srv/GetPlan_Response"), reply_attachment)

    def status_details(self) -> dict:
        return {
            "robot_input": self.robot_input,
            "frames": {
                "map": self.frames.map,
                "odom": self.frames.odom,
                "base": self.frames.base,
                "tf_topic": self.tf_topic or "",
            },
            "map_voxels": len(self.map),
            "graph_nodes_known": self.grid.n_known(),
            "sent": dict(self.sent),
            "received": dict(self.received),
            "static_frames": len(self.cloud_input.static) if self.cloud_input else 0,
            "plans_waiting": self.plan_jobs.waiting() if self.plan_jobs else 0,
            "zid": self.node.zid if self.node is not None else "",
            "actions": self.actions.status_details() if self.actions is not None else {},
        }


def _finish(query) -> None:
    try:
        query.drop()
    except Exception:  # noqa: BLE001 - already finished, or the session is closing
        pass


def main(config: SmanaConfig) -> int:
    return run_service(Ros2Service, config)
