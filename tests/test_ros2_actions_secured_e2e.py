"""The end-to-end test of the Nav2 actions (tests/test_ros2_actions_e2e.py) on the secured profile:
one router over TLS with users and the policy of `smana deploy init-certs` (robots r1 and r2; the
base's policy, so every identity of both robots may log in to it), gossip and multicast off; robot
r1's stack (sim, mapper, navgraph, planner, the explorer in navigate mode, ros2), each service
logged in as itself (`r1.sim`, ..., `r1.ros2`) with r1's host certificate and its own credentials
file; ROS 2 clients of zenoh-ros2-sdk's parts logged in as `r1.ros2peer` and `r2.ros2peer` the way
docs/ros2.md tells an rmw_zenoh node to (`ZENOH_SESSION_CONFIG_URI`: rmw_zenoh's session config
with the TLS files and the user's password).

r1's peer drives r1: NavigateToPose 4 m away arrives with feedback; `/r1/goal_pose` starts a goal
that a NavigateToPose pre-empts; a cancel stops the robot; ComputePathToPose returns `smana plan`'s
path. r2's peer, while r1 drives back to the start, sends r1 a NavigateToPose, cancels r1's goal
and publishes `/r1/goal_pose`: no reply, nothing reaches r1's ros2 service, and r1's goal ends
where r1's peer sent it. First seen that r2's peer knows r1's action server and goal subscriber
(the router declared them to it), and afterwards that the same session's calls and messages to
its own robot arrive: what it was denied is the policy, not a slow router."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("zenoh_ros2_sdk")

from smana.common import keys  # noqa: E402
from smana.common.config import ZenohConfig  # noqa: E402
from smana.common.query import request  # noqa: E402
from smana.common.zenoh_config import make_zenoh_config  # noqa: E402
from smana.deploy.security import init_certs  # noqa: E402
from smana.services.ros2 import nav2_types as n2  # noqa: E402
from smana.services.ros2 import rmw  # noqa: E402
from tests.conftest import ZenohStack, free_port, wait_for, wait_port  # noqa: E402
from tests.support.ros2_action_client import (  # noqa: E402
    COMPUTE_PATH_TO_POSE,
    NAVIGATE_TO_POSE,
    ActionClient,
    pose_stamped,
)
from tests.support.ros2_sdk import rmw_zenoh_session_config, sdk_session  # noqa: E402
from tests.test_ros2_actions_e2e import NAV, PLAN, SETS, TOLERANCE_M, Track  # noqa: E402

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

ROBOT, OTHER = "r1", "r2"
NS = f"/smana/{ROBOT}"
# The robot's own topics in its namespace, as the secured profile has them (docs/ros2.md).
SECURED_SETS = [kv for kv in SETS if not kv.startswith("ros2.")] + [
    "ros2.robot_input=off",
    f"ros2.goal_pose_topic=/{ROBOT}/goal_pose",
]
NO_REPLY_S = 8.0  # how long a denied call waits for the reply that never comes


class SecuredStack(ZenohStack):
    """`ZenohStack` on the secured profile: a router over TLS (its host `base`'s certificate) with
    every identity's password and the base's policy; each service started as `<robot>.<name>`
    with its robot's certificate and its own credentials file; the test's own session as
    `<robot>.tool`, which only reads."""

    def __init__(self, tmp, monkeypatch, robots=(ROBOT, OTHER)):
        self.monkeypatch = monkeypatch
        self.peers = []  # the SDK sessions of `ros2_peer`
        self.sessions = []  # those of `open`
        self.certs = tmp / "certs"
        init_certs(self.certs, list(robots), "fleet")
        self.tmp, self.robot = tmp, ROBOT
        self.port = free_port()
        self.endpoint = f"tls/127.0.0.1:{self.port}"
        self.procs = []
        self._session = self._probe = None
        c = self.certs
        section = {
            "tls_ca": c / "ca.pem",
            "tls_cert": c / "base" / "host.pem",
            "tls_key": c / "base" / "host.key",
            "credentials_file": c / "users.txt",  # both robots' identities log in here
            "acl_file": c / "base" / "acl.json5",
        }
        config = tmp / "router.toml"
        config.write_text("[zenoh]\n" + "".join(f'{k} = "{v}"\n' for k, v in section.items()))
        self.router = self.start(
            "router",
            "-m",
            "smana.deploy.router",
            "--config",
            str(config),
            "--listen",
            self.endpoint,
        )
        wait_port(self.port, 120.0)

    def login(self, robot: str, role: str) -> ZenohConfig:
        c = self.certs / robot
        return ZenohConfig(
            mode="client",
            connect=[self.endpoint],
            user=f"{robot}.{role}",
            credentials_file=str(c / "credentials" / f"{robot}.{role}.txt"),
            tls_ca=str(c / "ca.pem"),
            tls_cert=str(c / "host.pem"),
            tls_key=str(c / "host.key"),
        )

    def login_args(self, robot: str, role: str) -> list[str]:
        zc = self.login(robot, role)
        sets = {k: getattr(zc, k) for k in ("user", "credentials_file", "tls_ca", "tls_cert")}
        sets["tls_key"] = zc.tls_key
        return [a for k, v in sets.items() for a in ("--set", f'zenoh.{k}="{v}"')]

    def open(self, robot: str, role: str):
        """A session of `<robot>.<role>`, closed with the stack."""
        import zenoh

        self.sessions.append(zenoh.open(make_zenoh_config(self.login(robot, role))))
        return self.sessions[-1]

    def service(self, name: str, *args: str, module: str | None = None):
        module = module or f"smana.services.{name}"
        return self.start(
            name,
            "-m",
            module,
            *self.zenoh_args(),
            "--robot",
            self.robot,
            *self.login_args(self.robot, name),
            *args,
        )

    @property
    def session(self):
        if self._session is None:
            import zenoh

            self._session = zenoh.open(make_zenoh_config(self.login(self.robot, "tool")))
        return self._session

    def ros2_peer(self, robot: str):
        """An SDK session logged in as `<robot>.ros2peer`, configured as docs/ros2.md configures
        an rmw_zenoh node: `ZENOH_SESSION_CONFIG_URI` names rmw_zenoh's session config with the
        robot's TLS files and the peer's password. The SDK replaces the config's endpoint by
        `tcp/<ip>:<port>`, so `ZENOH_CONFIG_OVERRIDE` (which rmw_zenoh reads too) sets it back
        to the router's TLS endpoint."""
        from zenoh_ros2_sdk import session as sdk

        c = self.certs / robot
        path = rmw_zenoh_session_config(
            self.tmp / f"{robot}.ros2peer.json5",
            c,
            c / "credentials" / f"{robot}.ros2peer.txt",
            self.endpoint,
        )
        self.monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", str(path))
        override = f'connect/endpoints=["{self.endpoint}"];scouting/multicast/enabled=false'
        self.monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", override)
        sdk.ZenohSession._instance = None  # one session per identity, not the SDK's one
        peer = sdk.ZenohSession.get_instance()
        if self.peers:
            # The SDK's registry loads a message type once per process, into the store of the
            # session current then: every session here shares the first one's store.
            peer.store, peer._registered_types = (
                self.peers[0].store,
                self.peers[0]._registered_types,
            )
        self.peers.append(peer)
        return peer

    def close(self, timeout_s: float = 5.0) -> None:
        for session in [*self.sessions, *(p.session for p in self.peers)]:
            try:
                session.close()
            except Exception:  # noqa: BLE001 - closed already (`sdk_session` closes its last)
                pass
        super().close(timeout_s)


@pytest.fixture
def secured(tmp_path, monkeypatch):
    stack = SecuredStack(tmp_path, monkeypatch)
    try:
        with sdk_session(tmp_path, monkeypatch):
            yield stack
    finally:
        stack.close()


def test_r1s_peer_drives_r1_and_r2s_peer_cannot(secured):
    from zenoh_ros2_sdk import ROS2Publisher
    from zenoh_ros2_sdk import session as sdk

    s = secured
    sets = [a for kv in SECURED_SETS for a in ("--set", kv)]
    names = ("sim", "mapper", "navgraph", "planner", "explorer", "ros2")
    for name in names:
        s.service(name, *sets)
    for name in names:
        s.wait_alive(name, timeout_s=240)
    track = Track(s)
    assert wait_for(lambda: track.poses, 30)
    types = rmw.RosTypes()
    hashes = {
        action: {
            "send_goal": types.hash(n2.part(action, "SendGoal")),
            "get_result": types.hash(n2.part(action, "GetResult")),
        }
        for action in (NAV, PLAN)
    }
    texts = {NAV: NAVIGATE_TO_POSE, PLAN: COMPUTE_PATH_TO_POSE}

    def client(peer, ns, action, name):
        return ActionClient(s.port, f"{ns}/{name}", action, texts[action], hashes[action], peer)

    peer1 = s.ros2_peer(ROBOT)
    nav = client(peer1, NS, NAV, "navigate_to_pose")
    results: dict[bytes, object] = {}

    def result_of(uuid):
        results[uuid] = nav.get_result(uuid, timeout_s=300.0)

    def goal(x, y, yaw=0.0):
        return {"pose": pose_stamped(nav, x, y, yaw), "behavior_tree": ""}

    def ros2_status():
        return request(s.session, keys.status(ROBOT, "ros2"), None, 5.0)

    # 1. r1's peer: a free place 4 m away, reached within the tolerance, with feedback.
    g1, resp = nav.send_goal(**goal(4.0, 0.0))
    assert resp.accepted, s.log("ros2")[-3000:]
    waiter = threading.Thread(target=result_of, args=(g1,))
    waiter.start()
    waiter.join(240)
    assert g1 in results, (s.log("explorer")[-3000:], s.log("ros2")[-2000:])
    assert results[g1].status == n2.STATUS_SUCCEEDED, results[g1]
    x, y = track.last()
    assert math.hypot(x - 4.0, y) <= TOLERANCE_M + 0.05, (x, y)
    fb = nav.feedback_of(g1)
    assert len(fb) >= 3 and fb[0].distance_remaining > 2.5, [f.distance_remaining for f in fb]
    assert max(nav.feedback_gaps(g1)) <= 1.0, nav.feedback_gaps(g1)
    print(f"secured NavigateToPose 4 m: {fb[-1].navigation_time.sec} s, {len(fb)} feedback")

    # 2. r2's peer, on r1, while r1's peer sends the robot back to the start.
    peer2 = s.ros2_peer(OTHER)
    intruder = client(peer2, NS, NAV, "navigate_to_pose")
    own = client(peer2, f"/smana/{OTHER}", NAV, "navigate_to_pose")  # its own robot's action
    sdk.ZenohSession._instance = peer2  # an SDK publisher takes the SDK's current session
    pub2 = ROS2Publisher("/r1/goal_pose", "geometry_msgs/msg/PoseStamped", namespace=f"/{OTHER}")
    pub2_own = ROS2Publisher(
        f"/{OTHER}/goal_pose", "geometry_msgs/msg/PoseStamped", namespace=f"/{OTHER}"
    )
    # Robot r2's smana stands in as a session of `r2.ros2`: what reaches its action and topic.
    r2_smana = s.open(OTHER, "ros2")
    reached: list[str] = []
    held = [
        r2_smana.declare_queryable(
            own.keys["send_goal"], lambda q: reached.append("send_goal"), complete=True
        ),
        r2_smana.declare_subscriber(pub2_own.keyexpr, lambda _: reached.append("goal_pose")),
    ]
    # Before: the router has declared r1's action server and goal subscriber to r2's peer (so a
    # call or message would be routed there, were it allowed), and r2's own stand-ins.
    probes = [
        *(peer2.session.declare_querier(intruder.keys[w]) for w in ("send_goal", "cancel_goal")),
        peer2.session.declare_querier(own.keys["send_goal"]),
        peer2.session.declare_publisher(pub2.keyexpr),
        peer2.session.declare_publisher(pub2_own.keyexpr),
    ]
    assert wait_for(lambda: all(p.matching_status.matching for p in probes), 30), [
        p.matching_status.matching for p in probes
    ]
    for p in probes:
        p.undeclare()
    before = ros2_status().details["actions"]

    g2, resp = nav.send_goal(**goal(0.0, 0.0, math.pi))
    assert resp.accepted
    threading.Thread(target=result_of, args=(g2,), daemon=True).start()
    assert wait_for(lambda: len(nav.feedback_of(g2)) >= 1, 60)
    denied: dict[str, object] = {}

    def attempt(what, call):
        try:
            denied[what] = call()
        except TimeoutError as exc:
            denied[what] = exc

    attempts = [
        threading.Thread(target=attempt, args=(what, call))
        for what, call in (
            ("cancel", lambda: intruder.cancel(g2, timeout_s=NO_REPLY_S)),
            ("send_goal", lambda: intruder.send_goal(timeout_s=NO_REPLY_S, **goal(2.0, 3.0))),
        )
    ]
    for t in attempts:
        t.start()
    ps = pose_stamped(intruder, 1.0, -2.0, -math.pi / 2)
    for _ in range(5):
        pub2.publish(header=ps.header, pose=ps.pose)
    for t in attempts:
        t.join(NO_REPLY_S + 5)
    # After: the same session's call and message to its own robot arrive (a session's traffic
    # reaches the router in order).
    peer2.session.get(own.keys["send_goal"], payload=b"own", timeout=NO_REPLY_S)
    pub2_own.publish(header=ps.header, pose=ps.pose)
    assert wait_for(lambda: {"send_goal", "goal_pose"} <= set(reached), 20), reached
    assert all(isinstance(v, TimeoutError) for v in denied.values()), denied
    # r1's goal went on to where r1's peer sent it: not canceled, not pre-empted.
    assert wait_for(lambda: g2 in results, 240), s.log("ros2")[-2000:]
    assert results[g2].status == n2.STATUS_SUCCEEDED, results[g2]
    x, y = track.last()
    assert math.hypot(x, y) <= TOLERANCE_M + 0.05, (x, y)
    with nav._lock:
        goals = {bytes(st.goal_info.goal_id.uuid) for m in nav.statuses for st in m.status_list}
    assert goals == {g1, g2}, len(goals)  # no goal of r2's, from its call or /r1/goal_pose
    after = ros2_status().details["actions"]
    assert after["goals"] == before["goals"] + 1, (before, after)  # g2 alone reached it
    assert after["canceled"] == before["canceled"], (before, after)
    assert wait_for(lambda: track.still(2.0, 0.02), 10), "the robot moved after r1's goal"
    for h in held:
        h.undeclare()

    # 3. r1's peer: `/r1/goal_pose` starts a goal; a NavigateToPose pre-empts it (ABORTED);
    #    a cancel of that one: CANCELED, and the robot stops.
    sdk.ZenohSession._instance = peer1
    pub1 = ROS2Publisher("/r1/goal_pose", "geometry_msgs/msg/PoseStamped", namespace=f"/{ROBOT}")
    known = set(goals)

    def new_goals() -> dict[bytes, int]:
        with nav._lock:
            last = nav.statuses[-1].status_list if nav.statuses else []
        return {
            bytes(st.goal_info.goal_id.uuid): int(st.status)
            for st in last
            if bytes(st.goal_info.goal_id.uuid) not in known
        }

    # One message, once the router routes it to the ros2 service's subscriber: a message before
    # would be lost, as a volatile ROS 2 topic loses it, and a second would pre-empt the first.
    assert wait_for(lambda: pub1.pub.matching_status.matching, 20)
    ps = pose_stamped(nav, 1.0, -2.0, -math.pi / 2)
    pub1.publish(header=ps.header, pose=ps.pose)
    assert wait_for(new_goals, 20)
    (g_pose,) = new_goals()
    threading.Thread(target=result_of, args=(g_pose,), daemon=True).start()
    assert wait_for(lambda: len(nav.feedback_of(g_pose)) >= 2, 60)
    g3, resp = nav.send_goal(**goal(2.0, 3.0))
    assert resp.accepted
    assert wait_for(lambda: g_pose in results, 10)
    assert results[g_pose].status == n2.STATUS_ABORTED, results[g_pose]
    threading.Thread(target=result_of, args=(g3,), daemon=True).start()
    assert wait_for(lambda: len(nav.feedback_of(g3)) >= 2, 30)
    c = nav.cancel(g3)
    assert c.return_code == n2.CANCEL_NONE and len(c.goals_canceling) == 1
    assert wait_for(lambda: g3 in results, 10)
    assert results[g3].status == n2.STATUS_CANCELED
    assert wait_for(lambda: track.still(1.0, 0.02), 3.0), "the robot kept moving after the cancel"
    pub1.close()

    # 4. r1's peer: ComputePathToPose, the path `smana plan` prints (run as `r1.tool`).
    plan = client(peer1, NS, PLAN, "compute_path_to_pose")
    agree = []
    for _ in range(5):  # the graph may change between the two asks while the map grows
        uuid, resp = plan.send_goal(
            goal=pose_stamped(plan, 3.5, 0.5),
            start=pose_stamped(plan, 0.5, -0.5),
            planner_id="",
            use_start=True,
        )
        assert resp.accepted
        r = plan.get_result(uuid, 30.0)
        assert r.status == n2.STATUS_SUCCEEDED, (r.result.error_code, r.result.error_msg)
        ros_path = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                             for p in r.result.path.poses])  # fmt: skip
        done = subprocess.run(
            [sys.executable, "-m", "smana.deploy", "plan", "--from", "0.5,-0.5", "--to", "3.5,0.5",
             "--json", *s.zenoh_args(), "--robot", ROBOT, *s.login_args(ROBOT, "tool")],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        cli_path = np.array(json.loads(done.stdout)["path"], np.float64).reshape(-1, 3)
        same = ros_path.shape == cli_path.shape and np.allclose(ros_path, cli_path, atol=1e-6)
        agree.append(same)
        if same:
            break
    assert any(agree), (ros_path[:3], cli_path[:3])
    assert len(ros_path) >= 10
    for c in (nav, plan, intruder, own):
        c.close()
    pub2.close()
    pub2_own.close()
    print(f"secured e2e: {time.monotonic() - track.poses[0][0]:.0f} s from the first pose")


def test_r1s_frames_reach_a_ros2_subscriber_and_r1_cannot_publish_r2s(secured):
    """r1's ros2 service on the secured profile (simulation, logged in as `r1.ros2`) puts its
    robot's frames on `/smana/r1/tf` (`ros2.tf_topic` "auto": the policy grants no robot the
    shared /tf). A ROS 2 subscriber logged in as `r1.ros2peer` gets map -> odom -> base_link at
    r1's pose. A TFMessage a session of `r1.ros2` publishes on `/smana/r2/tf` never reaches a
    subscriber of that topic logged in as `r2.ros2peer`, after the router declared it to that
    session; r2's own, and the same session's later one on `/smana/r1/tf`, arrive."""
    import zenoh
    from zenoh_ros2_sdk import ROS2Subscriber

    from smana.common.messages import Pose, encode
    from smana.services.ros2 import convert

    s = secured
    s.service("ros2", "--set", "ros2.robot_input=off")
    s.wait_alive("ros2", timeout_s=240)
    details = request(s.session, keys.status(ROBOT, "ros2"), None, 5.0).details
    assert details["frames"]["tf_topic"] == f"{NS}/tf", details
    tf_type = "tf2_msgs/msg/TFMessage"
    got: dict[str, list] = {ROBOT: [], OTHER: []}
    lock = threading.Lock()

    def keep(robot):
        def cb(msg):
            with lock:
                got[robot].append(msg)

        return cb

    subs = []
    for robot in (ROBOT, OTHER):
        s.ros2_peer(robot)  # the SDK's current session: a subscriber takes it
        subs.append(
            ROS2Subscriber(f"/smana/{robot}/tf", tf_type, keep(robot), namespace=f"/{robot}")
        )

    def frames(robot) -> dict[str, tuple[str, float]]:
        with lock:
            msgs = list(got[robot])
        return {
            t.child_frame_id: (t.header.frame_id, t.transform.translation.x)
            for m in msgs
            for t in m.transforms
        }

    # r1's pose, as its simulator (`r1.sim`) publishes it, until its frames arrive.
    sim = s.open(ROBOT, "sim")
    pose_pub = sim.declare_publisher(
        keys.pose(ROBOT), congestion_control=zenoh.CongestionControl.BLOCK
    )
    assert wait_for(lambda: pose_pub.matching_status.matching, 30)
    n = [0]

    def r1_frames() -> bool:
        n[0] += 1
        pose_pub.put(encode(Pose.from_xyz_yaw(1.5, -0.5, 0.0, 0.4, 50.0 + 0.1 * n[0], n[0])))
        return "base_link" in frames(ROBOT)

    assert wait_for(r1_frames, 60, step_s=0.1), s.log("ros2")[-2000:]
    f1 = frames(ROBOT)
    assert f1["odom"][0] == "map" and f1["base_link"] == ("odom", 1.5), f1

    # A session of `r1.ros2` on r2's tf topic, once the router has declared r2's subscriber
    # to it; then r2's own and the same session's on r1's.
    types = rmw.RosTypes()

    def tf_of(child: str) -> bytes:
        pose = Pose.from_xyz_yaw(9.0, 9.0, 0.0, 0.0, stamp_s=60.0)
        msg = convert.robot_frames(types, pose, "map", "odom", child)
        return types.serialize(msg, tf_type)

    def tf_key(robot: str) -> str:
        return rmw.data_key(0, f"/smana/{robot}/tf", tf_type, types.hash(tf_type))

    smana1, smana2 = s.open(ROBOT, "ros2"), s.open(OTHER, "ros2")
    probe = smana1.declare_publisher(tf_key(OTHER))
    assert wait_for(lambda: probe.matching_status.matching, 30)
    probe.undeclare()
    att = rmw.attachment(1, time.time_ns(), bytes(16))
    block = zenoh.CongestionControl.BLOCK
    smana1.put(tf_key(OTHER), tf_of("intruder"), attachment=att, congestion_control=block)
    smana2.put(tf_key(OTHER), tf_of("r2_own"), attachment=att, congestion_control=block)
    smana1.put(tf_key(ROBOT), tf_of("r1_later"), attachment=att, congestion_control=block)
    assert wait_for(lambda: "r2_own" in frames(OTHER) and "r1_later" in frames(ROBOT), 30), (
        frames(OTHER),
        frames(ROBOT),
    )
    assert "intruder" not in frames(OTHER), frames(OTHER)
    for sub in subs:
        sub.close()
