"""[replay] config section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import Section, param


@dataclass
class ReplayConfig(Section, section="replay"):
    """`smana replay DATASET`: publish a recorded dataset on the robot's keys instead of the sim."""

    dataset: str = ""  # path; `smana replay DATASET` sets it
    format: str = ""  # semantickitti, rellis3d, rosbag or folder; "" = detect from the layout
    sequence: str = ""  # SemanticKITTI / RELLIS-3D root holding several sequences: which one
    class_table: str = ""  # "" = the dataset's own table (rellis3d, semantickitti, ...)
    mode: Literal["lockstep", "realtime"] = "lockstep"  # lockstep: wait for each scan's MapDelta
    rate_factor: float = param(1.0, gt=0)  # realtime: x N the recorded rate
    topic: Literal["auto", "scan", "cloud"] = "auto"  # auto: LiDAR -> robot/scan, camera -> cloud
    max_range_m: float = param(10.0, gt=0)  # points farther from the sensor are not published
    min_range_m: float = param(0.5, ge=0)  # nor closer ones (the robot itself, no-returns)
    start: int = param(0, ge=0)  # first scan replayed
    count: int = param(0, ge=0)  # scans replayed; 0 = to the end
    wait_for: list[str] = param(["mapper"])  # alive before the 1st scan
    wait_timeout_s: float = param(60.0, gt=0)  # for the services of wait_for
    ack_timeout_s: float = param(30.0, gt=0)  # lockstep: resend a scan after this long
    label_field: str = "label"  # bags / PLY: the integer label field
    cloud_topic: str = ""  # bags: the PointCloud2 topic ("" = the only one)
    odom_topic: str = ""  # bags: the nav_msgs/Odometry topic ("" = the only one)
    fixed_pose: list[float] = param([])  # bags without odometry: x, y, z, yaw
