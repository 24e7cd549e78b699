"""[ros2] config section: how the `ros2` service joins a ROS 2 graph that runs rmw_zenoh."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param

# A tf frame prefix: what robot_state_publisher's `frame_prefix` prepends (tf2 refuses a frame id
# that starts with '/'; a robot name of smana's is letters, digits, '_' and '-').
_FRAME_PREFIX = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_./-]{0,63}")


@dataclass(frozen=True)
class Ros2Frames:
    """The frame names the ros2 service of one robot publishes and accepts
    (`Ros2Config.frames`): each is the configured name with the prefix in front."""

    prefix: str
    map: str  # smana's world frame as published (REP-105's map; map -> odom is the identity)
    odom: str
    base: str  # `ros2.base_frame`: the robot's body
    # `ros2.world_frames`: a cloud or a goal in one of them is in smana's world
    world: tuple[str, ...]


@dataclass
class Ros2Config(Section, section="ros2"):
    """`smana ros2`: smana's map, costmap, path, goal and odometry as ROS 2 topics, and (for a
    real robot) a ROS 2 robot's clouds and odometry in, velocity commands out."""

    domain_id: int = param(0, ge=0, le=232)  # ROS_DOMAIN_ID
    node_name: str = "smana"  # the ROS 2 node (its namespace is /smana/<robot>)
    cloud_topic: str = "/points"  # sensor_msgs/msg/PointCloud2 in
    odom_topic: str = "/odom"  # nav_msgs/msg/Odometry in
    # sensor_msgs/msg/LaserScan in: the robot's safety scanner, for the explorer's guard
    # (robot/safety_scan); "" = none (the guard then lets every command out, and counts them)
    safety_scan_topic: str = ""
    cmd_vel_topic: str = "/cmd_vel"  # geometry_msgs/msg/Twist out
    # geometry_msgs/msg/PoseStamped in (RViz2's "2D Goal Pose"): a NavigateToPose goal
    goal_pose_topic: str = "/goal_pose"
    # The actions, under the node's namespace (/smana/<robot>/...)
    navigate_action: str = "navigate_to_pose"  # nav2_msgs/action/NavigateToPose
    compute_path_action: str = "compute_path_to_pose"  # nav2_msgs/action/ComputePathToPose
    # A NavigateToPose goal the planner finds no path to for this long (robot time) is aborted
    # NO_VALID_PATH, as Nav2's navigator aborts once its planner fails (the explorer's own goals
    # wait explorer.goal_timeout_s)
    navigate_no_path_s: float = param(3.0, ge=0, le=3600)
    # ComputePathToPose plans through unknown ground at planner.unknown_cost (Nav2's planners'
    # allow_unknown, on by default); off: known free ground only
    plan_through_unknown: bool = True
    # The integer label field of the clouds. "none": every cloud is labelled by the geometric
    # labeller (class table `geometric`); a cloud without the field is refused otherwise.
    label_field: str = "label"
    # "auto": read the robot's topics when smana's simulator is not running ([deploy.sim]
    # enabled = false), "on" / "off" to force.
    robot_input: Literal["auto", "on", "off"] = "auto"
    # The mapper input the robot's clouds go to: robot/scan (LiDAR) or robot/cloud (a depth
    # camera); the mapper listens to it when it is in mapper.inputs.
    cloud_input: Literal["scan", "cloud"] = "scan"
    # Frames a cloud or a goal may already be in: used as it is (REP-105: smana's world is the
    # odom frame). With a frame prefix these are prefixed too.
    world_frames: list[str] = param(["map", "odom"])
    # Clouds in a sensor frame: the sensor's pose on the robot (x, y, z, roll, pitch, yaw) when
    # the robot's static transforms do not give it; [] = from them only.
    sensor_extrinsic: list[float] = param([])
    base_frame: str = "base_link"  # the robot's own frame (REP-105)
    # Put in front of every frame name smana publishes or expects (`frames`), so that robots on
    # one /tf keep disjoint trees (r1/map -> r1/odom -> r1/base_link). "auto": "<robot>/" when
    # smana simulates the robot (robot_input off) and the config names two robots or more
    # (fleet.robots, deploy.robots), "" otherwise; any other value is used as it is ("" = none).
    frame_prefix: str = "auto"
    # Where the simulated robot's frames go (tf2_msgs/TFMessage). "auto": /smana/<robot>/tf when
    # the service logs in with a user (zenoh.credentials_file: the secured profiles, whose policy
    # lets no robot write the shared /tf), /tf otherwise.
    tf_topic: str = "auto"
    # The robot's static transforms in (transient-local), for a cloud in a sensor frame.
    tf_static_topic: str = "/tf_static"
    max_pose_gap_s: float = param(0.2, gt=0)  # odometry interpolated at most this far
    map_period_s: float = param(1.0, gt=0)  # /smana/<robot>/map at most this often
    # The map message's voxel budget (20 bytes each): past it, voxels are merged into cells of
    # 2, 4, 8 ... times the map's resolution until they fit, so one message stays under 4 MB.
    map_max_points: int = param(200_000, ge=1000)
    costmap_period_s: float = param(1.0, gt=0)  # /smana/<robot>/costmap at most this often
    min_range_m: float = param(0.3, ge=0)  # cloud points nearer the sensor are dropped
    max_range_m: float = param(20.0, gt=0)  # and farther ones

    def validate(self) -> None:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,63}", self.node_name):
            raise ConfigError(
                f"ros2.node_name: a ROS 2 node name (letters, digits, '_'), got {self.node_name!r}"
            )
        for name in ("navigate_action", "compute_path_action"):
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,63}", getattr(self, name)):
                raise ConfigError(f"ros2.{name}: one ROS 2 name token, got {getattr(self, name)!r}")
        topics = ("cloud_topic", "odom_topic", "cmd_vel_topic", "goal_pose_topic", "tf_topic")
        for name in (*topics, "tf_static_topic", "safety_scan_topic"):
            topic = getattr(self, name)
            if (name == "tf_topic" and topic == "auto") or (
                name == "safety_scan_topic" and not topic
            ):
                continue
            if not topic.startswith("/") or "//" in topic or topic.endswith("/"):
                raise ConfigError(f"ros2.{name}: a ROS 2 topic like /points, got {topic!r}")
        p = self.frame_prefix
        if p != "auto" and p and (not _FRAME_PREFIX.fullmatch(p) or "//" in p):
            raise ConfigError(
                'ros2.frame_prefix: auto, "" or a tf frame prefix like "r1/" (letters, digits, '
                f"'_', '-', '.', '/'; not starting with '/', no '//'), got {p!r}"
            )
        if self.sensor_extrinsic and len(self.sensor_extrinsic) != 6:
            raise ConfigError("ros2.sensor_extrinsic: [x, y, z, roll, pitch, yaw] or []")
        if not self.label_field:
            raise ConfigError("ros2.label_field: a field name, or none")

    def frames(
        self, robot: str, robots: Sequence[str] = (), robot_input: bool = False
    ) -> Ros2Frames:
        """The frame names robot `robot`'s ros2 service publishes and accepts, as a `Ros2Frames`:
        each configured name with the frame prefix in front (`frame_prefix`). `robots`: the
        robots the config names (fleet.robots and deploy.robots); `robot_input`: the service
        reads a real robot's topics, whose frames are the robot's, so "auto" adds nothing."""
        p = self.frame_prefix
        if p == "auto":
            p = f"{robot}/" if len(set(robots)) >= 2 and not robot_input else ""
        return Ros2Frames(
            prefix=p,
            map=p + "map",
            odom=p + "odom",
            base=p + self.base_frame,
            world=tuple(p + f for f in self.world_frames),
        )

    def tf_topic_for(self, robot: str, secured: bool = False) -> str:
        """The topic the simulated robot's frames go on (see `tf_topic`); `secured`: the service
        logs in with a user (zenoh.credentials_file)."""
        if self.tf_topic != "auto":
            return self.tf_topic
        return f"/smana/{robot}/tf" if secured else "/tf"
