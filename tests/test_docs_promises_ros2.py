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
- odometry "with a twist from consecutive poses", in process the same way.
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
