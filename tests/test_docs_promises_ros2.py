"""docs/ros2.md: "The mapper reads the clouds only when the input is in `mapper.inputs` ... the
ros2 service warns at start when it is missing." Two ros2 services with a robot's input (smana's
simulator off, so `ros2.robot_input = "auto"` is on) as processes on an isolated zenoh, their
logs read once they are live. (The fake zenoh has no zenoh-ext publishers, which they use.)"""

from __future__ import annotations

import pytest

pytest.importorskip("rosbags")
pytestmark = pytest.mark.multiprocess

WARNING = "nothing will be mapped; set --set 'mapper.inputs=[\"scan\"]'"


def ros2(stack, log_name: str, robot: str, inputs: str):
    return stack.start(
        log_name,
        *("-m", "smana.services.ros2", *stack.zenoh_args(), "--robot", robot),
        *("--set", "deploy.sim.enabled=false", "--set", f"mapper.inputs={inputs}"),
    )


def test_the_ros2_service_warns_when_the_mapper_does_not_read_its_clouds(zenoh_stack):
    warned = ros2(zenoh_stack, "ros2-clouds", "rc", '["cloud"]')
    quiet = ros2(zenoh_stack, "ros2-scans", "rs", '["scan"]')
    zenoh_stack.wait_alive("ros2", robot="rc")
    zenoh_stack.wait_alive("ros2", robot="rs")
    assert WARNING in zenoh_stack.log(warned), zenoh_stack.log(warned)
    assert "mapper.inputs" not in zenoh_stack.log(quiet), zenoh_stack.log(quiet)
