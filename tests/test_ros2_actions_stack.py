"""The ros2 service's NavigateToPose over a real router, against a stand-in explorer on the
test's session (the `explorer/goal`, `explorer/goal/cancel` and `explorer/goal/feedback`
contract of services/explorer/navigation.py), driven by an action client made of
zenoh-ros2-sdk's parts (tests/support/ros2_action_client.py): goal, feedback, result held until
it exists, pre-emption (the first goal ends ABORTED, as Nav2's), cancel, `/goal_pose`, and
hostile requests answered and counted while the service goes on."""

from __future__ import annotations

import math
import threading
import time

import msgpack
import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("zenoh_ros2_sdk")

from smana.common import keys  # noqa: E402
from smana.common.query import request  # noqa: E402
from smana.services.ros2 import nav2_types as n2  # noqa: E402
from smana.services.ros2 import rmw  # noqa: E402
from tests.conftest import ZenohStack, wait_for  # noqa: E402
from tests.support.ros2_action_client import (  # noqa: E402
    COMPUTE_PATH_TO_POSE,
    NAVIGATE_TO_POSE,
    ActionClient,
    Err,
    pose_stamped,
)
from tests.support.ros2_sdk import sdk_session  # noqa: E402

NAV = "nav2_msgs/action/NavigateToPose"
POSE = "geometry_msgs/msg/PoseStamped"
PLAN = "nav2_msgs/action/ComputePathToPose"


@pytest.fixture
def ros_stack(tmp_path, monkeypatch):
    stack = ZenohStack(tmp_path, router_args=("--set", "zenoh.gossip=true"))
    try:
        with sdk_session(tmp_path, monkeypatch):
            yield stack
    finally:
        stack.close()


class FakeExplorer:
    """The explorer's goal contract on the test's session: accepts every goal but one at x = 99,
    cancels on request, and publishes the feedback the test tells it to."""

    def __init__(self, stack):
        self.goals: list[dict] = []
        self.cancels: list[dict] = []
        r = stack.robot
        s = stack.session
        self._decl = [
            s.declare_queryable(keys.explorer_goal(r), self._goal),
            s.declare_queryable(keys.explorer_goal_cancel(r), self._cancel),
        ]
        self.feedback_key = keys.explorer_goal_feedback(r)
        self.session = s

    def _goal(self, query):
        body = msgpack.unpackb(query.payload.to_bytes())
        if body["x"] == 99.0:  # the explorer's refusal (a goal on an obstacle, say)
            reply = {"accepted": False, "id": body["id"], "reason": "goal on an obstacle"}
            query.reply(query.key_expr, msgpack.packb(reply))
            return
        self.goals.append(body)
        reply = {"accepted": True, "id": body["id"], "reason": ""}
        query.reply(query.key_expr, msgpack.packb(reply))

    def _cancel(self, query):
        body = msgpack.unpackb(query.payload.to_bytes())
        self.cancels.append(body)
        reply = {"canceled": True, "id": body["id"], "reason": ""}
        query.reply(query.key_expr, msgpack.packb(reply))

    def feedback(self, gid: str, state: str, remaining: float, pose=(1.0, 0.5, 0.2), error=""):
        fb = {
            "id": gid,
            "state": state,
            "goal": [4.0, 0.0, 0.0],
            "pose": list(pose),
            "distance_remaining_m": remaining,
            "navigation_time_s": 2.5,
            "recoveries": 1,
            "reason": "" if state == "active" else f"the test says {state}",
            "error": error,
        }
        self.session.put(self.feedback_key, msgpack.packb(fb))


def test_navigate_to_pose_goal_feedback_preemption_cancel_and_goal_pose(ros_stack):
    from zenoh_ros2_sdk import ROS2Publisher

    s = ros_stack
    explorer = FakeExplorer(s)
    ros2 = s.service("ros2", "--set", "ros2.robot_input=off")
    s.wait_alive("ros2", timeout_s=120)
    types = rmw.RosTypes()
    hashes = {w: types.hash(n2.part(NAV, p)) for w, p in (("send_goal", "SendGoal"),
                                                          ("get_result", "GetResult"))}  # fmt: skip
    client = ActionClient(s.port, "/smana/test/navigate_to_pose", NAV, NAVIGATE_TO_POSE, hashes)

    def goal(x, y, yaw=0.0, frame="map"):
        return {"pose": pose_stamped(client, x, y, yaw, frame), "behavior_tree": ""}

    # A goal: handed to the explorer as its contract says, EXECUTING on the status topic.
    g1, resp = client.send_goal(**goal(4.0, 0.0, 0.5))
    assert resp.accepted and resp.stamp.sec > 0
    assert explorer.goals[-1]["id"] == g1.hex()
    assert explorer.goals[-1]["x"] == 4.0 and explorer.goals[-1]["yaw"] == pytest.approx(0.5)
    assert wait_for(lambda: client.status_of(g1) == n2.STATUS_EXECUTING, 10)

    results: dict[bytes, object] = {}

    def wait_result(uuid):
        results[uuid] = client.get_result(uuid, timeout_s=60.0)

    t1 = threading.Thread(target=wait_result, args=(g1,))
    t1.start()
    # Feedback from the explorer's feedback; the result is held meanwhile.
    assert wait_for(
        lambda: explorer.feedback(g1.hex(), "active", 3.0) or client.feedback_of(g1), 10, 0.2
    )
    fb = client.feedback_of(g1)[-1]
    assert fb.distance_remaining == pytest.approx(3.0)
    assert fb.current_pose.pose.position.x == pytest.approx(1.0)
    assert fb.navigation_time.sec >= 2 and fb.number_of_recoveries == 1
    # Feedback at 10 Hz (FEEDBACK_HZ), though the explorer said it once: counted over 2 s
    n0, t0 = len(client.feedback_of(g1)), time.monotonic()
    assert wait_for(lambda: time.monotonic() - t0 >= 2.0, 5, 0.05)
    rate = (len(client.feedback_of(g1)) - n0) / (time.monotonic() - t0)
    assert 5.0 <= rate <= 11.0, rate
    assert fb.estimated_time_remaining.sec + fb.estimated_time_remaining.nanosec * 1e-9 > 0
    assert g1 not in results

    # A second goal pre-empts the first: ABORTED, as Nav2's SimpleActionServer ends it.
    g2, resp = client.send_goal(**goal(-2.0, 1.0))
    assert resp.accepted
    t1.join(10)
    assert results[g1].status == n2.STATUS_ABORTED
    assert "preempted" in results[g1].result.error_msg
    assert wait_for(lambda: client.status_of(g2) == n2.STATUS_EXECUTING, 10)
    assert client.status_of(g1) == n2.STATUS_ABORTED
    # Late feedback for the pre-empted goal changes nothing.
    explorer.feedback(g1.hex(), "preempted", 3.0)

    # Cancel: the explorer is asked, the goal ends CANCELED.
    t2 = threading.Thread(target=wait_result, args=(g2,))
    t2.start()
    c = client.cancel(g2)
    assert c.return_code == n2.CANCEL_NONE
    assert [bytes(g.goal_id.uuid) for g in c.goals_canceling] == [g2]
    t2.join(10)
    assert results[g2].status == n2.STATUS_CANCELED
    assert explorer.cancels[-1]["id"] == g2.hex()
    assert client.cancel(g2).return_code == n2.CANCEL_GOAL_TERMINATED

    # A goal the explorer reports reached ends SUCCEEDED.
    g3, resp = client.send_goal(**goal(1.0, 1.0))
    assert resp.accepted
    t3 = threading.Thread(target=wait_result, args=(g3,))
    t3.start()
    assert wait_for(lambda: explorer.feedback(g3.hex(), "succeeded", 0.1) or g3 in results, 10)
    t3.join(10)
    assert results[g3].status == n2.STATUS_SUCCEEDED and results[g3].result.error_code == 0

    # A goal the explorer gives up on: ABORTED with Kilted's UNKNOWN (9000) and its reason,
    # or with the planner's code when the explorer says why (NO_VALID_PATH here); one it
    # refuses: `accepted = false`.
    g4, resp = client.send_goal(**goal(1.5, 1.5))
    assert resp.accepted
    t4 = threading.Thread(target=wait_result, args=(g4,))
    t4.start()
    assert wait_for(lambda: explorer.feedback(g4.hex(), "aborted", 1.0) or g4 in results, 10)
    t4.join(10)
    assert results[g4].status == n2.STATUS_ABORTED and results[g4].result.error_code == 9000
    assert results[g4].result.error_msg == "the test says aborted"
    g6, resp = client.send_goal(**goal(1.5, 1.5))
    assert resp.accepted
    assert wait_for(lambda: explorer.feedback(g6.hex(), "aborted", 1.0, error="no_path") or
                    client.status_of(g6) == n2.STATUS_ABORTED, 10)  # fmt: skip
    assert client.get_result(g6, 10.0).result.error_code == 208
    _, refused = client.send_goal(**goal(99.0, 0.0))
    assert not refused.accepted

    # Unknown ids: STATUS_UNKNOWN and ERROR_UNKNOWN_GOAL_ID, as rclcpp_action answers.
    ghost = bytes(range(16))
    assert client.get_result(ghost, 5.0).status == n2.STATUS_UNKNOWN
    assert client.cancel(ghost).return_code == n2.CANCEL_UNKNOWN_GOAL_ID

    # Hostile requests: an error reply or `accepted = false`, counted; the service goes on.
    def status():
        return request(s.session, keys.status("test", "ros2"), None, 3.0)

    before = status()
    n_goals = len(explorer.goals)
    assert isinstance(client.call("send_goal", None, raw=b"\x00\x01\x00\x00\xff\xff"), Err)
    _, nan = client.send_goal(**goal(math.nan, 0.0))
    assert not nan.accepted
    _, elsewhere = client.send_goal(**goal(1.0, 0.0, frame="odd_frame"))
    assert not elsewhere.accepted
    # base_link is a frame smana publishes; before the robot's first pose there is no transform
    # to it: accepted and aborted, Kilted's TF_ERROR, as Nav2's navigator fails a goal it
    # cannot transform
    in_base, resp = client.send_goal(**goal(1.0, 0.0, frame="base_link"))
    assert resp.accepted
    r = client.get_result(in_base, 10.0)
    assert r.status == n2.STATUS_ABORTED and r.result.error_code == 9002, r
    assert "no transform" in r.result.error_msg
    assert len(explorer.goals) == n_goals  # none of them reached the explorer
    no_att = list(s.session.get(client.keys["get_result"], payload=b"\x00\x01\x00\x00",
                                timeout=5.0))  # fmt: skip
    assert len(no_att) == 1 and no_att[0].err is not None
    after = status()
    assert after.rejected.get("malformed", 0) - before.rejected.get("malformed", 0) == 2
    assert after.rejected.get("value", 0) - before.rejected.get("value", 0) == 2
    assert after.state == "running" and after.books_add_up()
    # On /goal_pose: CDR that is no PoseStamped, and a pose with NaN: counted, never a goal.
    from smana.services.ros2 import convert

    goal_pose_key = rmw.data_key(0, "/goal_pose", POSE, types.hash(POSE))
    bad = convert.pose_stamped(types, (math.nan, 1.0), 0.0, 1.0)
    s.session.put(goal_pose_key, b"\x00\x01\x00\x00\x07")
    s.session.put(goal_pose_key, types.serialize(bad, POSE))

    def rejected(kind):
        return status().rejected.get(kind, 0) - after.rejected.get(kind, 0)

    assert wait_for(lambda: rejected("malformed") == 1 and rejected("value") == 1, 10)
    assert len(explorer.goals) == n_goals

    # /goal_pose (RViz2's "2D Goal Pose", from the SDK's publisher): a NavigateToPose goal.
    pub = ROS2Publisher("/goal_pose", "geometry_msgs/msg/PoseStamped", router_port=s.port)
    ps = pose_stamped(client, 2.5, -1.5, math.pi / 2)
    assert wait_for(
        lambda: pub.publish(header=ps.header, pose=ps.pose) or len(explorer.goals) > n_goals,
        10,
        0.3,
    )
    g = explorer.goals[-1]
    assert (g["x"], g["y"]) == (2.5, -1.5) and g["yaw"] == pytest.approx(math.pi / 2)
    uuid = bytes.fromhex(g["id"])
    assert wait_for(lambda: client.status_of(uuid) == n2.STATUS_EXECUTING, 10)
    # (one goal runs: a second /goal_pose still on its way pre-empts the first)
    assert wait_for(lambda: status().details["actions"]["navigate_running"] == 1, 10)
    assert status().details["actions"]["feedback"] >= 1
    pub.close()

    # The status topic is transient-local: a client that comes late gets the goals at once.
    from zenoh import ext

    late: list = []
    sub = ext.declare_advanced_subscriber(
        s.session,
        client.keys["status"],
        lambda sample: late.append(
            client.decode(sample.payload.to_bytes(), client.types["status"])
        ),
        history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
    )
    assert wait_for(lambda: late, 10), "no status from the transient-local cache"
    assert uuid in {bytes(st.goal_info.goal_id.uuid) for st in late[-1].status_list}
    sub.undeclare()

    # ComputePathToPose with no planner answering: ABORTED with Nav2's TIMEOUT; with
    # `use_start = false` and no robot pose yet: UNKNOWN; an unknown planner_id: INVALID_PLANNER.
    plan_hashes = {
        "send_goal": types.hash(n2.part(PLAN, "SendGoal")),
        "get_result": types.hash(n2.part(PLAN, "GetResult")),
    }
    plan = ActionClient(
        s.port, "/smana/test/compute_path_to_pose", PLAN, COMPUTE_PATH_TO_POSE, plan_hashes
    )

    def ask(use_start=True, planner_id=""):
        t0 = time.monotonic()
        uuid, resp = plan.send_goal(
            goal=pose_stamped(plan, 3.0, 0.0),
            start=pose_stamped(plan, 0.0, 0.0),
            planner_id=planner_id,
            use_start=use_start,
        )
        assert resp.accepted
        # the acceptance comes at once, not when the planner's 5 s are over
        assert time.monotonic() - t0 < 2.0
        r = plan.get_result(uuid, 30.0)
        assert r.status == n2.STATUS_ABORTED and len(r.result.path.poses) == 0, r
        return r.result.error_code

    # A planner that never answers (its queries held): TIMEOUT once the 5 s are over, and the
    # goal's acceptance all the same at once.
    held: list = []
    silent = s.session.declare_queryable(keys.path_query("test"), held.append)
    t0 = time.monotonic()
    assert ask() == 207
    assert held and time.monotonic() - t0 >= 4.5
    silent.undeclare()
    held.clear()
    # No planner at all: TIMEOUT too (nothing answered).
    assert ask() == 207
    assert ask(use_start=False) == 200
    assert ask(planner_id="GridBased") == 201
    plan.close()

    # An explorer that goes silent on a goal: ABORTED once 5 s pass without its feedback.
    g5, resp = client.send_goal(**goal(0.5, 0.5))
    assert resp.accepted
    r = client.get_result(g5, 30.0)
    assert r.status == n2.STATUS_ABORTED and "no feedback" in r.result.error_msg, r
    client.close()
    assert np.isfinite(after.msgs_in)
    assert s.stop(ros2) == 0, s.log("ros2")
