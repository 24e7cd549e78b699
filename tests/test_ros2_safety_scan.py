"""A ROS 2 robot's safety scanner (`ros2.safety_scan_topic`, a LaserScan) -> robot/safety_scan:
its ranges placed on the robot through its static transforms, in "base_link", as the simulator
sends them; a scan that cannot be read or placed is refused with its reason."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.common.config import SmanaConfig  # noqa: E402
from smana.common.config.section import ConfigError  # noqa: E402
from smana.common.messages import SemanticCloud, decode, encode  # noqa: E402
from smana.common.service import Reject  # noqa: E402
from smana.services.ros2 import convert, rmw  # noqa: E402
from smana.services.ros2.bridge import CloudInput  # noqa: E402
from smana.services.ros2.safety_input import LASER, SafetyScanInput, scan_points  # noqa: E402

TYPES = rmw.RosTypes()
T = TYPES.msg


def laser(t_s: float, ranges, frame="laser", angle_min=-math.pi / 2, increment=math.pi / 2):
    return T(LASER)(
        header=convert.header(TYPES, t_s, frame),
        angle_min=angle_min,
        angle_max=angle_min + increment * (len(ranges) - 1),
        angle_increment=increment,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.05,
        range_max=10.0,
        ranges=np.asarray(ranges, np.float32),
        intensities=np.zeros(0, np.float32),
    )


def laser_on_the_robot(x=0.2, z=0.1):
    """/tf_static: base_link -> laser, `x` ahead of the base and `z` up, turned a quarter left."""
    tf = T("geometry_msgs/msg/Transform")(
        translation=T("geometry_msgs/msg/Vector3")(x=x, y=0.0, z=z),
        rotation=T("geometry_msgs/msg/Quaternion")(
            x=0.0, y=0.0, z=math.sin(math.pi / 4), w=math.cos(math.pi / 4)
        ),
    )
    stamped = T("geometry_msgs/msg/TransformStamped")(
        header=convert.header(TYPES, 0.0, "base_link"), child_frame_id="laser", transform=tf
    )
    return T("tf2_msgs/msg/TFMessage")(transforms=[stamped])


def inputs(**ros2):
    config = SmanaConfig.load(overrides=[f"ros2.{k}={v!r}" for k, v in ros2.items()])
    service = types.SimpleNamespace(config=config, log=types.SimpleNamespace(warnings=[]))
    service.log.warning = lambda fmt, *a: service.log.warnings.append(fmt % a)
    ci = CloudInput(config, labeller=None)
    return SafetyScanInput(service, ci), ci, service


def test_ranges_become_points_of_the_scanners_frame():
    pts = scan_points(laser(1.0, [1.0, math.nan, 2.0, 0.01, 99.0], angle_min=0.0))
    # 0 deg at 1 m and 180 deg at 2 m; NaN, under range_min and over range_max are no return
    assert np.allclose(pts, [[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]], atol=1e-6)


def test_a_scan_is_placed_on_the_robot_through_its_static_transforms():
    scans, ci, service = inputs()
    assert ci.add_static(laser_on_the_robot()) == 1
    for k in range(3):  # the stream's clock locks on agreeing stamps
        cloud = scans.convert(laser(10.0 + 0.1 * k, [1.0, 1.0, 1.0]))
    # the laser looks left: its -90, 0 and +90 degree beams point ahead, left and behind
    want = [[1.2, 0.0, 0.1], [0.2, 1.0, 0.1], [-0.8, 0.0, 0.1]]
    assert np.allclose(cloud.points, want, atol=1e-6)
    assert cloud.frame_id == "base_link" and cloud.source == "safety_scan"
    assert decode(encode(cloud), SemanticCloud).points.shape == (3, 3)  # the codec takes it
    # z = 0.1 m is inside what the guard counts: no warning
    assert service.log.warnings == []


def test_a_scan_that_cannot_be_placed_or_read_is_refused_and_a_high_one_is_said():
    scans, ci, service = inputs()
    with pytest.raises(Reject) as e:
        scans.convert(laser(10.0, [1.0]))
    assert e.value.kind == "no_transform"
    ci.add_static(laser_on_the_robot(z=0.5))  # mounted above what the guard counts
    bad = laser(10.0, [1.0, 1.0])
    bad.angle_increment = math.inf
    with pytest.raises(Reject) as e:
        scans.convert(bad)
    assert e.value.kind == "value"
    with pytest.raises(Reject) as e:
        scans.convert(laser(10.0, np.ones(200_000)))
    assert e.value.kind == "oversize"
    for k in range(3):
        scans.convert(laser(10.0 + 0.1 * k, [1.0]))
    assert len(service.log.warnings) == 1 and "explorer.guard.z_min_m" in service.log.warnings[0]
    with pytest.raises(Reject) as e:
        scans.convert(laser(5e6, [1.0]))
    assert e.value.kind == "stamp"


def test_the_topic_is_a_ros2_topic_or_none():
    assert SmanaConfig.load().ros2.safety_scan_topic == ""
    assert SmanaConfig.load(overrides=['ros2.safety_scan_topic="/scan"']).ros2.safety_scan_topic
    with pytest.raises(ConfigError, match="ros2.safety_scan_topic"):
        SmanaConfig.load(overrides=['ros2.safety_scan_topic="scan"'])
