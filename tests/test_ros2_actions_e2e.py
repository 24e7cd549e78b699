"""End to end in simulation: smana's whole stack (sim, mapper, navgraph, planner, the explorer in
navigator mode, ros2) on an isolated router with gossip on, driven through the ROS 2 actions by
an action client made of zenoh-ros2-sdk's parts (tests/support/ros2_action_client.py), as a Nav2
user's client or RViz2 would drive it.

The ros2 service joins a running stack: ComputePathToPose asked the moment its server's tokens
appear returns a path over ground not seen yet within 3 s. NavigateToPose to a free place 4 m
away arrives within the goal tolerance with feedback at 5 Hz or more; a goal in `base_link`
arrives where the robot's pose put it; a goal far outside the map is accepted and aborted
GOAL_OUTSIDE_MAP within 10 s; a goal pre-empted by a second ends ABORTED and a canceled one
CANCELED with the robot stopped; a `/goal_pose` message drives like a goal; ComputePathToPose
returns the path `smana plan --allow-unknown` prints."""

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
from smana.common.messages import Pose, decode  # noqa: E402
from smana.services.ros2 import nav2_types as n2  # noqa: E402
from smana.services.ros2 import rmw  # noqa: E402
from tests.conftest import ZenohStack, wait_for  # noqa: E402
from tests.support.ros2_action_client import (  # noqa: E402
    COMPUTE_PATH_TO_POSE,
    NAVIGATE_TO_POSE,
    ActionClient,
    pose_stamped,
)
from tests.support.ros2_sdk import sdk_session  # noqa: E402

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

NAV, PLAN = "nav2_msgs/action/NavigateToPose", "nav2_msgs/action/ComputePathToPose"
NS = "/smana/test"
TOLERANCE_M = 0.2  # explorer.follower.goal_tolerance_m, the default a NavigateToPose gets
# An open garden (walls, ground, no objects): every place 4 m from the centre is free.
SETS = [
    "sim.garden.layout=classic",
    "sim.garden.clutter=0.0",
    "sim.garden.size_m=12.0",
    "sim.seed=3",
    "sim.spawn=[0.0, 0.0, 0.0]",
    "sim.camera.width=160",
    "sim.camera.height=160",
    "mapper.resolution_m=0.1",
    "navgraph.bounds_min_xy=[-7.0, -7.0]",
    "navgraph.bounds_max_xy=[7.0, 7.0]",
    "explorer.mode=navigate",
    "ros2.robot_input=off",
]


@pytest.fixture
def ros_stack(tmp_path, monkeypatch):
    stack = ZenohStack(tmp_path, router_args=("--set", "zenoh.gossip=true"))
    try:
        with sdk_session(tmp_path, monkeypatch):
            yield stack
    finally:
        stack.close()


class Track:
    """The robot's true pose (the simulator's `robot/pose_truth`), with arrival times."""

    def __init__(self, stack):
        self.poses: list[tuple[float, float, float, float]] = []  # (monotonic, x, y, yaw)
        self._lock = threading.Lock()
        self.sub = stack.session.declare_subscriber(keys.pose_truth(stack.robot), self._on)

    def _on(self, sample) -> None:
        p = decode(sample.payload.to_bytes(), Pose)
        with self._lock:
            self.poses.append((time.monotonic(), float(p.position[0]), float(p.position[1]), p.yaw))

    def last(self) -> tuple[float, float]:
        with self._lock:
            return self.poses[-1][1:3]

    def pose(self) -> tuple[float, float, float]:
        with self._lock:
            return self.poses[-1][1:]

    def still(self, window_s: float, within_m: float) -> bool:
        """Whether the poses of the last `window_s` (covering at least 90 % of it) lie within
        `within_m` of each other."""
        now = time.monotonic()
        with self._lock:
            recent = [p for p in self.poses if p[0] >= now - window_s]
        if len(recent) < 2 or recent[-1][0] - recent[0][0] < 0.9 * window_s:
            return False
        xy = np.array([p[1:3] for p in recent])
        return float(np.hypot(*(xy.max(0) - xy.min(0)))) < within_m


def test_actions_drive_smana_in_simulation(ros_stack):
    from zenoh_ros2_sdk import ROS2Publisher

    s = ros_stack
    sets = [a for kv in SETS for a in ("--set", kv)]
    names = ("sim", "mapper", "navgraph", "planner", "explorer")
    for name in names:
        s.service(name, *sets)
    for name in names:
        s.wait_alive(name, timeout_s=240)
    track = Track(s)
    assert wait_for(lambda: track.poses, 30)
    types = rmw.RosTypes()

    def client(action, name, texts):
        hashes = {
            "send_goal": types.hash(n2.part(action, "SendGoal")),
            "get_result": types.hash(n2.part(action, "GetResult")),
        }
        return ActionClient(s.port, f"{NS}/{name}", action, texts, hashes)

    # 0. The ros2 service joins the running stack. The moment its ComputePathToPose server's
    #    send_goal token appears (rmw_zenoh's discovery), a path over ground not seen yet is
    #    asked for: the server answers (its queryables came before its tokens) and plans
    #    through the unknown (Nav2's allow_unknown), within 3 s of the token.
    plan = client(PLAN, "compute_path_to_pose", COMPUTE_PATH_TO_POSE)
    seen: list[float] = []
    watch = s.session.liveliness().declare_subscriber(
        "@ros2_lv/**",
        lambda sample: (
            "compute_path_to_pose%_action%send_goal" in str(sample.key_expr)
            and seen.append(time.monotonic())
        ),
    )
    s.service("ros2", *sets)
    assert wait_for(lambda: seen, 240), s.log("ros2")
    uuid, resp = plan.send_goal(
        goal=pose_stamped(plan, 5.0, 5.0, math.pi / 2),
        start=pose_stamped(plan, 0.0, 0.0),
        planner_id="",
        use_start=True,
    )
    assert resp.accepted
    r = plan.get_result(uuid, 30.0)
    took = time.monotonic() - seen[0]
    watch.undeclare()
    assert r.status == n2.STATUS_SUCCEEDED, (r.result.error_code, r.result.error_msg)
    assert took <= 3.0, f"a path {took:.2f} s after the server appeared"
    end = r.result.path.poses[-1].pose
    assert (end.position.x, end.position.y) == pytest.approx((5.0, 5.0), abs=0.1)
    assert 2 * math.atan2(end.orientation.z, end.orientation.w) == pytest.approx(math.pi / 2)
    print(f"ComputePathToPose over unseen ground: {took:.2f} s after the server's tokens")
    s.wait_alive("ros2", timeout_s=240)

    nav = client(NAV, "navigate_to_pose", NAVIGATE_TO_POSE)
    results: dict[bytes, object] = {}

    def result_of(uuid):
        results[uuid] = nav.get_result(uuid, timeout_s=300.0)

    def goal(x, y, yaw=0.0):
        return {"pose": pose_stamped(nav, x, y, yaw), "behavior_tree": ""}

    # 1. A free place 4 m away: reached within the tolerance, with feedback on the way.
    g1, resp = nav.send_goal(**goal(4.0, 0.0, 0.0))
    assert resp.accepted, s.log("ros2")
    waiter = threading.Thread(target=result_of, args=(g1,))
    waiter.start()
    waiter.join(240)
    assert g1 in results, (s.log("explorer")[-3000:], s.log("ros2")[-2000:])
    assert results[g1].status == n2.STATUS_SUCCEEDED, results[g1]
    x, y = track.last()
    assert math.hypot(x - 4.0, y - 0.0) <= TOLERANCE_M + 0.05, (x, y)
    fb = nav.feedback_of(g1)
    assert len(fb) >= 3, len(fb)
    remaining = [f.distance_remaining for f in fb]
    assert remaining[0] > 2.5 and min(remaining) < 1.0, remaining
    assert fb[-1].current_pose.header.frame_id == "map"
    gaps = nav.feedback_gaps(g1)
    assert max(gaps) <= 1.0, f"feedback below 1 Hz: gaps up to {max(gaps):.2f} s"
    assert np.median(gaps) <= 0.2, f"feedback below 5 Hz: median gap {np.median(gaps):.2f} s"
    print(
        f"NavigateToPose 4 m: {fb[-1].navigation_time.sec} s of navigation, {len(fb)} feedback "
        f"messages, gaps {np.median(gaps):.2f} s median, {max(gaps):.2f} s max; arrived "
        f"{math.hypot(x - 4.0, y):.3f} m from the goal"
    )

    # 1b. A goal in base_link, 1 m behind and 1 m to the left of where the robot stands:
    #     placed by the robot's pose when it was sent, and reached there.
    rx, ry, ryaw = track.pose()
    want = (rx - 1.0 * math.cos(ryaw) - 1.0 * math.sin(ryaw),
            ry - 1.0 * math.sin(ryaw) + 1.0 * math.cos(ryaw))  # fmt: skip
    gb, resp = nav.send_goal(pose=pose_stamped(nav, -1.0, 1.0, 0.0, "base_link"), behavior_tree="")
    assert resp.accepted
    r = nav.get_result(gb, 240.0)
    assert r.status == n2.STATUS_SUCCEEDED, (r.result.error_code, r.result.error_msg)
    x, y = track.last()
    assert math.hypot(x - want[0], y - want[1]) <= TOLERANCE_M + 0.1, ((x, y), want)

    # 1c. A goal 50 m away, far outside the map: accepted, then aborted GOAL_OUTSIDE_MAP (the
    #     code Nav2's navigator takes from its planner) within 10 s.
    t0 = time.monotonic()
    gf, resp = nav.send_goal(**goal(50.0, 0.0))
    assert resp.accepted
    r = nav.get_result(gf, 30.0)
    assert r.status == n2.STATUS_ABORTED and r.result.error_code == 204, r
    assert "outside" in r.result.error_msg and time.monotonic() - t0 <= 10.0

    # 2. Pre-emption and cancel: a goal 4 m back, pre-empted on the way by one to the side
    #    (the first ends ABORTED, as Nav2's); that one canceled: CANCELED, and the robot stops.
    g2, resp = nav.send_goal(**goal(0.0, 0.0, math.pi))
    assert resp.accepted
    threading.Thread(target=result_of, args=(g2,), daemon=True).start()
    assert wait_for(lambda: any(f.distance_remaining < 3.0 for f in nav.feedback_of(g2)), 120)
    g3, resp = nav.send_goal(**goal(2.0, 3.0))
    assert resp.accepted
    assert wait_for(lambda: g2 in results, 10)
    assert results[g2].status == n2.STATUS_ABORTED
    threading.Thread(target=result_of, args=(g3,), daemon=True).start()
    assert wait_for(lambda: len(nav.feedback_of(g3)) >= 2, 30)
    c = nav.cancel(g3)
    assert c.return_code == n2.CANCEL_NONE and len(c.goals_canceling) == 1
    assert wait_for(lambda: g3 in results, 10)
    assert results[g3].status == n2.STATUS_CANCELED
    # Stopped: within 10 s of the cancel (a loaded machine), a second in which it moved < 2 cm.
    assert wait_for(lambda: track.still(1.0, 0.02), 10.0), "the robot kept moving after the cancel"

    # 3. /goal_pose (RViz2's "2D Goal Pose"): drives like a NavigateToPose goal.
    pub = ROS2Publisher("/goal_pose", "geometry_msgs/msg/PoseStamped", router_port=s.port)
    ps = pose_stamped(nav, 1.0, -2.0, -math.pi / 2)
    known = {bytes(st.goal_info.goal_id.uuid) for st in nav.statuses[-1].status_list}

    def new_goals() -> dict[bytes, int]:
        """Goals on the status topic that the client did not send: {uuid: status}."""
        with nav._lock:
            last = nav.statuses[-1].status_list if nav.statuses else []
        return {
            bytes(st.goal_info.goal_id.uuid): int(st.status)
            for st in last
            if bytes(st.goal_info.goal_id.uuid) not in known
        }

    # (published until the subscription is seen: a message before that is lost, as a volatile
    # ROS 2 topic loses it; a second message pre-empts the first, as a second click does)
    assert wait_for(lambda: pub.publish(header=ps.header, pose=ps.pose) or new_goals(), 20, 0.5)
    assert wait_for(lambda: n2.STATUS_SUCCEEDED in new_goals().values(), 240), new_goals()
    x, y = track.last()
    assert math.hypot(x - 1.0, y + 2.0) <= TOLERANCE_M + 0.05, (x, y)
    pub.close()

    # 4. ComputePathToPose: the path `smana plan --allow-unknown` prints for the same start and
    #    goal (both through unknown ground at the planner's unknown_cost).
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
        assert r.result.error_code == 0
        ros_path = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                             for p in r.result.path.poses])  # fmt: skip
        done = subprocess.run(
            [sys.executable, "-m", "smana.deploy", "plan", "--from", "0.5,-0.5", "--to", "3.5,0.5",
             "--allow-unknown", "--json", *s.zenoh_args(), "--robot", s.robot],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        cli_path = np.array(json.loads(done.stdout)["path"], np.float64).reshape(-1, 3)
        same = ros_path.shape == cli_path.shape and np.allclose(ros_path, cli_path, atol=1e-6)
        agree.append(same)
        if same:
            break
    assert any(agree), (ros_path[:3], cli_path[:3])
    assert r.result.path.header.frame_id == "map" and len(ros_path) >= 10
    # `use_start = false`: from the robot's pose.
    uuid, resp = plan.send_goal(
        goal=pose_stamped(plan, 3.5, 0.5),
        start=pose_stamped(plan, 0.0, 0.0),
        planner_id="smana",
        use_start=False,
    )
    r = plan.get_result(uuid, 30.0)
    assert r.status == n2.STATUS_SUCCEEDED, (r.result.error_code, r.result.error_msg)
    first = r.result.path.poses[0].pose.position
    x, y = track.last()
    assert math.hypot(first.x - x, first.y - y) < 0.3, ((first.x, first.y), (x, y))
    # A goal outside the graph: ABORTED with Nav2's GOAL_OUTSIDE_MAP.
    uuid, resp = plan.send_goal(
        goal=pose_stamped(plan, 50.0, 0.0),
        start=pose_stamped(plan, 0.0, 0.0),
        planner_id="",
        use_start=True,
    )
    r = plan.get_result(uuid, 30.0)
    assert r.status == n2.STATUS_ABORTED and r.result.error_code == 204, r
    nav.close()
    plan.close()
