"""docs/ros2.md's sentences no other test held:

- "The mapper reads the clouds only when the input is in `mapper.inputs` ... the ros2 service
  warns at start when it is missing": two ros2 services with a robot's input as processes on an
  isolated zenoh, their logs read once they are live (the fake zenoh has no zenoh-ext
  publishers, which they use);
- with a robot's input, its status details and that it leaves `/tf` to the robot (no `/tf`
  publisher among its liveliness tokens);
- `ros2.robot_input` "auto" is on exactly when smana's simulator is off;
- the map and the costmap go out "at most every `ros2.map_period_s` (1 s) when the map changed":
  the service's publishing rule, in process, with a recording `_send`;
- odometry "with a twist from consecutive poses", in process the same way;
- its liveliness tokens announce "its services (GetPlan, and the services of its two actions)",
  and the actions' status topic is "reliable and transient-local, depth 1": a ros2 process's
  tokens;
- NavigateToPose's `behavior_tree` "is ignored", its `estimated_time_remaining` is "the distance
  left at `explorer.follower.max_linear_mps`", "A finished goal's result is kept 10 s ... after
  that ... the answer is STATUS_UNKNOWN", and the status details' counts under `actions`: the
  service's action server in process, on a stand-in node and explorer;
- a map over `ros2.map_max_points` is merged into cells "each cell at its centre" and "The
  mapper's map is not changed by it": `convert.within_budget` on arrays it must not touch.
"""

from __future__ import annotations

import math

import pytest

pytest.importorskip("rosbags")

from smana.common import keys  # noqa: E402
from smana.common.config import SmanaConfig  # noqa: E402
from smana.common.query import request  # noqa: E402
from smana.services.ros2.service import Ros2Service, robot_input_on  # noqa: E402

WARNING = "nothing will be mapped; set --set 'mapper.inputs=[\"scan\"]'"


def ros2(stack, log_name: str, robot: str, inputs: str):
    return stack.start(
        log_name,
        *("-m", "smana.services.ros2", *stack.zenoh_args(), "--robot", robot),
        *("--set", "deploy.sim.enabled=false", "--set", f"mapper.inputs={inputs}"),
    )


@pytest.mark.multiprocess
def test_with_a_robots_input_ros2_warns_keeps_its_books_and_leaves_tf(zenoh_stack):
    warned = ros2(zenoh_stack, "ros2-clouds", "rc", '["cloud"]')
    quiet = ros2(zenoh_stack, "ros2-scans", "rs", '["scan"]')
    zenoh_stack.wait_alive("ros2", robot="rc")
    zenoh_stack.wait_alive("ros2", robot="rs")
    assert WARNING in zenoh_stack.log(warned), zenoh_stack.log(warned)
    assert "mapper.inputs" not in zenoh_stack.log(quiet), zenoh_stack.log(quiet)
    # "Its status details give the numbers sent and received per topic, the map's voxels and
    # the graph's known nodes."
    st = request(zenoh_stack.session, keys.status("rc", "ros2"), timeout_s=5)
    d = st.details
    assert d["robot_input"] is True and d["map_voxels"] == 0 and d["graph_nodes_known"] == 0, d
    assert {"map", "costmap", "path", "goal", "odom", "cmd_vel"} <= set(d["sent"]), d
    assert {"clouds", "odometry", "tf_static", "plans"} <= set(d["received"]), d
    # "With a real robot it leaves `/tf` to the robot": its node announces a map publisher and
    # a /tf_static subscription (rmw_zenoh's liveliness tokens), and no /tf publisher.
    tokens = [
        str(r.ok.key_expr)
        for r in zenoh_stack.session.liveliness().get("@ros2_lv/**", timeout=5)
        if r.ok is not None and "/%smana%rc/" in str(r.ok.key_expr)
    ]
    assert any("/MP/" in k and "/%smana%rc%map/" in k for k in tokens), tokens
    assert any("/MS/" in k and "/%tf_static/" in k for k in tokens), tokens
    assert not any("/MP/" in k and "/%tf/" in k for k in tokens), tokens


def test_robot_input_auto_is_on_when_smanas_simulator_is_off():
    assert not robot_input_on(SmanaConfig.load())
    assert robot_input_on(SmanaConfig.load(None, ["deploy.sim.enabled=false"]))
    assert robot_input_on(SmanaConfig.load(None, ["ros2.robot_input=on"]))
    assert not robot_input_on(
        SmanaConfig.load(None, ["deploy.sim.enabled=false", "ros2.robot_input=off"])
    )


@pytest.mark.parametrize("what", ["map", "costmap"])
def test_the_map_and_costmap_go_out_when_changed_at_most_once_a_period(what):
    svc = Ros2Service(SmanaConfig.load())
    assert getattr(svc.config.ros2, f"{what}_period_s") == 1.0
    sent = []
    svc._send = lambda topic, msg: sent.append(msg)

    def publish(version, now):
        svc._publish_latched(what, version, lambda: f"v{version}@{now}", now)

    publish(1, 100.0)  # the first version goes out at once
    publish(2, 100.5)  # changed, but within the period: held back
    publish(2, 100.99)
    publish(2, 101.0)  # the period is over: the newest version
    publish(2, 103.0)  # unchanged: nothing
    publish(3, 103.2)
    assert sent == ["v1@100.0", "v2@101.0", "v3@103.2"]


def test_odometry_carries_a_twist_from_consecutive_poses():
    """docs/ros2.md: `/smana/R/odom` is "the pose smana uses (`robot/pose`), with a twist from
    consecutive poses" (forward speed in the body frame, yaw rate)."""
    from smana.common.messages import Pose
    from smana.services.ros2.rmw import RosTypes

    svc = Ros2Service(SmanaConfig.load())
    svc.types, svc.pubs = RosTypes(), {}  # what setup() makes; no /tf here
    sent = []
    svc._send = lambda topic, msg: sent.append((topic, msg))
    svc.on_pose(Pose.from_xyz_yaw(1.0, 2.0, 0.0, 1.0, stamp_s=10.0))
    # 0.1 s later: 0.1 m ahead along the heading of 1.05 rad, turned by 0.05 rad
    svc.on_pose(
        Pose.from_xyz_yaw(1.0 + 0.1 * math.cos(1.05), 2.0 + 0.1 * math.sin(1.05), 0.0, 1.05, 10.1)
    )
    odom = [m for topic, m in sent if topic == "odom"]
    assert len(odom) == 2
    assert odom[0].twist.twist.linear.x == 0.0 and odom[0].twist.twist.angular.z == 0.0
    assert odom[1].twist.twist.linear.x == pytest.approx(1.0)
    assert odom[1].twist.twist.angular.z == pytest.approx(0.5)
    assert odom[1].pose.pose.position.x == pytest.approx(1.0 + 0.1 * math.cos(1.05))


@pytest.mark.multiprocess
def test_its_tokens_announce_getplan_and_the_actions_services_and_a_latched_status(zenoh_stack):
    """docs/ros2.md: the liveliness tokens announce "its services (GetPlan, and the services of
    its two actions)"; an action's status topic is "reliable and transient-local, depth 1"."""
    from smana.services.ros2 import rmw

    zenoh_stack.service("ros2", "--set", "ros2.robot_input=off")
    zenoh_stack.wait_alive("ros2")
    ns = f"%smana%{zenoh_stack.robot}"
    tokens = [
        str(r.ok.key_expr)
        for r in zenoh_stack.session.liveliness().get("@ros2_lv/**", timeout=5)
        if r.ok is not None and f"/{ns}/" in str(r.ok.key_expr)
    ]

    def kind_of(topic: str) -> set[str]:
        """The entity kinds (NN, MP, MS, SS) announced for `topic` under the node's namespace."""
        return {k.split("/")[5] for k in tokens if f"/{ns}{topic}/" in k}

    assert kind_of("%plan") == {"SS"}, tokens
    for action in ("navigate_to_pose", "compute_path_to_pose"):
        for service in ("send_goal", "get_result", "cancel_goal"):
            assert kind_of(f"%{action}%_action%{service}") == {"SS"}, (action, service, tokens)
        assert kind_of(f"%{action}%_action%feedback") == {"MP"}, tokens
        status = [k for k in tokens if f"/{ns}%{action}%_action%status/" in k]
        assert len(status) == 1 and status[0].endswith("/" + rmw.LATCHED_QOS.token()), status
    # the token's QoS: reliable (empty), transient-local (1), keep-last (empty), depth 1
    assert rmw.LATCHED_QOS.token().startswith(":1:,1:")


class _Recorder:
    """A stand-in publisher: keeps what is put."""

    def __init__(self):
        self.sent: list = []

    def put(self, msg) -> None:
        self.sent.append(msg)


class _Node:
    """What Ros2Actions uses of the service's RosNode, without zenoh."""

    def __init__(self):
        from smana.services.ros2.rmw import RosTypes

        self.types = RosTypes()
        self.publishers: dict[str, _Recorder] = {}

    def endpoint(self, kind, name, typename, qos=None):
        return f"key{name}", 0

    def publisher(self, topic, typename, qos=None):
        return self.publishers.setdefault(topic, _Recorder())


class _Session:
    def declare_queryable(self, *args, **kwargs):
        return self


class _Svc:
    """What Ros2Actions uses of the ros2 service: its config, node, session and books."""

    def __init__(self, robots=()):
        self.config = SmanaConfig.load()
        self.node, self.session, self.robot = _Node(), _Session(), "r1"
        self.frames = self.config.ros2.frames("r1", robots)
        self._declared: list = []
        self.notes: list = []
        self._last_pose = None  # no robot pose: feedback carries the explorer's

    def subscribe(self, key, callback) -> None:
        pass

    def note(self, kind, text) -> None:
        self.notes.append((kind, text))

    def _stamp(self) -> float:
        return 100.0


def test_navigate_to_pose_ignores_the_behavior_tree_gives_an_eta_and_keeps_a_result_10_s(
    monkeypatch,
):
    import msgpack

    from smana.services.ros2 import actions as act
    from smana.services.ros2 import convert
    from smana.services.ros2.nav2_types import STATUS_SUCCEEDED, STATUS_UNKNOWN

    asked: list[tuple[str, dict]] = []

    def explorer(session, key, body, timeout_s):  # the explorer accepts every goal
        asked.append((key, dict(body)))
        return {"accepted": True, "id": body["id"], "reason": ""}

    monkeypatch.setattr(act, "request", explorer)
    svc = _Svc()
    actions = act.Ros2Actions(svc, "/smana/r1")
    try:
        now = [1000.0]
        actions.nav.book.clock = lambda: now[0]
        types = svc.node.types

        def goal(tree: str):
            pose = convert.pose_stamped(types, (4.0, -1.0), 0.5, 12.0)
            return actions.nav.msg("Goal")(pose=pose, behavior_tree=tree)

        # `behavior_tree` is ignored: the explorer is asked the same with a tree as without
        replies: list[bytes] = []
        tree = "<root><BehaviorTree><Wait/></BehaviorTree></root>"
        a, b = bytes([1]) * 16, bytes([2]) * 16
        assert actions.navigate(a, goal(tree), replies.append) == (True, "")
        assert actions.navigate(b, goal(""), replies.append) == (True, "")
        (key_a, with_tree), (key_b, without) = asked
        assert key_a == key_b == "smana/r1/explorer/goal"
        assert with_tree.pop("id") == a.hex() and without.pop("id") == b.hex()
        assert with_tree == without
        assert (without["x"], without["y"], without["tolerance_m"]) == (4.0, -1.0, None)
        assert without["yaw"] == pytest.approx(0.5)

        # feedback: the ETA is the distance left at explorer.follower.max_linear_mps
        fb = {"id": b.hex(), "state": "active", "pose": [1.0, 0.5, 0.2]}
        fb |= {"distance_remaining_m": 3.0, "navigation_time_s": 2.5, "recoveries": 1}
        actions.on_explorer_feedback(msgpack.packb(fb))
        sent = svc.node.publishers["/smana/r1/navigate_to_pose/_action/feedback"].sent
        eta = sent[-1].feedback.estimated_time_remaining
        speed = svc.config.explorer.follower.max_linear_mps
        assert eta.sec + eta.nanosec * 1e-9 == pytest.approx(3.0 / speed, abs=1e-6)
        assert sent[-1].feedback.distance_remaining == pytest.approx(3.0)

        # before the explorer has a pose: no feedback (no made-up pose, no NaN distance), counted
        n_sent = len(sent)
        no_pose = fb | {"pose": None, "distance_remaining_m": float("nan")}
        actions.on_explorer_feedback(msgpack.packb(no_pose))
        assert len(sent) == n_sent
        assert actions.status_details()["feedback_without_pose"] == 1
        # a pose without a finite distance is a bad message, not a missing pose
        from smana.common.messages import MessageError

        with pytest.raises(MessageError, match="finite distance"):
            actions.on_explorer_feedback(msgpack.packb(fb | {"distance_remaining_m": None}))
        assert len(sent) == n_sent

        # the result: kept 10 s after the goal ends, then STATUS_UNKNOWN
        actions.on_explorer_feedback(msgpack.packb(fb | {"state": "succeeded"}))

        def result() -> int:
            got = []
            actions.nav.book.result(b, lambda status, r: got.append(status))
            return got[0]

        assert result() == STATUS_SUCCEEDED
        now[0] += 9.9
        actions.tick()
        assert result() == STATUS_SUCCEEDED
        now[0] += 0.2
        actions.tick()
        assert result() == STATUS_UNKNOWN
        # "The status details count goals, acceptances, refusals, feedback and cancels"
        details = actions.status_details()
        assert {"goals", "accepted", "refused", "feedback", "canceled"} <= set(details)
        assert (details["accepted"], details["feedback"]) == (2, 2)
    finally:
        actions.close()


def test_a_coarsened_map_puts_each_cell_at_its_centre_and_leaves_the_map_alone():
    import numpy as np

    from smana.services.ros2 import convert

    rng = np.random.default_rng(7)
    idx = np.unique(rng.integers(-60, 60, size=(5000, 3)), axis=0)
    centres = ((idx + 0.5) * 0.1).astype(np.float32)
    labels = rng.integers(0, 9, len(idx)).astype(np.uint16)
    before = (centres.copy(), labels.copy())
    out, lab, cell = convert.within_budget(centres, labels, 0.1, 1000)
    assert len(out) <= 1000 and cell > 0.1
    # each kept point is the centre of its cell
    np.testing.assert_allclose(out, (np.floor(out / cell) + 0.5) * cell, atol=1e-5)
    # the map it was given is as it was
    np.testing.assert_array_equal(centres, before[0])
    np.testing.assert_array_equal(labels, before[1])


def test_the_actions_read_and_stamp_the_fleet_s_prefixed_frames(monkeypatch):
    """docs/ros2.md: "The Nav2 actions (below) take it too: a goal is read in `r1/map`,
    `r1/odom` or `r1/base_link`, and feedback and paths are stamped in `r1/map`." """
    import msgpack

    from smana.common.messages import Pose
    from smana.services.ros2 import actions as act
    from smana.services.ros2 import convert

    asked: list[dict] = []

    def explorer(session, key, body, timeout_s):
        asked.append(dict(body))
        return {"accepted": True, "id": body["id"], "reason": ""}

    monkeypatch.setattr(act, "request", explorer)
    svc = _Svc(robots=("r1", "r2"))
    actions = act.Ros2Actions(svc, "/smana/r1")
    try:
        types = svc.node.types

        def goal(frame, x=1.0):
            pose = convert.pose_stamped(types, (x, 0.0), 0.0, 12.0, frame)
            return actions.nav.msg("Goal")(pose=pose, behavior_tree="")

        for frame in ("map", "odom", "base_link", "r2/map"):  # the plain names are r2's too
            ok, why = actions.navigate(bytes([1]) * 16, goal(frame), lambda body: None)
            assert not ok and "frame" in why, (frame, why)
        assert actions.navigate(bytes([2]) * 16, goal("r1/map"), lambda b: None) == (True, "")
        svc._last_pose = Pose.from_xyz_yaw(2.0, 3.0, 0.0, math.pi / 2)
        assert actions.navigate(bytes([3]) * 16, goal("r1/base_link"), lambda b: None)[0]
        assert (asked[-1]["x"], asked[-1]["y"]) == pytest.approx((2.0, 4.0))
        fb = {"id": bytes([3] * 16).hex(), "state": "active", "pose": [2.0, 3.0, 0.0]}
        fb |= {"distance_remaining_m": 1.0, "navigation_time_s": 0.5, "recoveries": 0}
        actions.on_explorer_feedback(msgpack.packb(fb))
        sent = svc.node.publishers["/smana/r1/navigate_to_pose/_action/feedback"].sent
        assert sent[-1].feedback.current_pose.header.frame_id == "r1/map"
    finally:
        actions.close()
