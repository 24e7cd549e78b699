"""[fleet] config section: several robots sharing one map, one navigation graph and one plan.

A fleet is a list of robot names (`robots`). Each member keeps its own stack under its own
namespace (`smana/<robot>/...`: sensors, mapper, planner, explorer); the fleet's shared services
run under `name` (`smana/<name>/...`): the simulator of all members (one PyBullet world), the
fleet mapper (every member's map deltas merged by the back-end's own rule), the navigation graph
built from it (which every member's planner and explorer use) and the coordinator (which hands
out next-best views so that no two robots head for the same frontier).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param


@dataclass
class FleetConfig(Section, section="fleet"):
    name: str = "fleet"  # the shared services' namespace (smana/<name>/...)
    robots: list[str] = param([])  # the members; [] = a single robot, no fleet
    # The common frame: "world" when every member's poses are already in it (the simulator's
    # ground truth, or one shared localisation); "start_pose" when each member maps in its own
    # odometry frame, which starts at its `start_poses` entry of the fleet frame.
    frame: Literal["world", "start_pose"] = "world"
    start_poses: list[list[float]] = param([])  # [x, y, yaw] per member, in `robots` order
    spawn_spacing_m: float = param(1.2, gt=0)  # the simulator: members start this far apart
    # ...where the ground truth leaves them this much room from any obstacle, in the first
    # member's part of the garden joined by passages that wide: the navigation graph's safety
    # zone (robot_radius_m between node centres, over a map that rounds obstacles out to its
    # voxels and nodes) closes narrower spots, and a member spawned 0.47 m from a hedge in a
    # pocket so joined never moved.
    member_clearance_m: float = param(0.6, ge=0)
    # Coordination (the coordinator and each member's explorer):
    goal_separation_m: float = param(2.5, ge=0)  # no two members' goals closer than this
    # Unknown area within this of another member's goal counts for nothing in a view's gain:
    # that member will see it.
    claim_radius_m: float = param(2.5, ge=0)
    claim_timeout_s: float = param(2.0, gt=0)  # a claim query unanswered -> plan alone
    # A member that moved less than 1 m in this long (wedged, held up) holds nobody back: its
    # goal is left out of the claims until it moves again.
    claim_stall_s: float = param(20.0, gt=0)
    # Other members as moving obstacles: the planner does not enter nodes this close to another
    # member (centre to centre), except to move away from it; the follower stops while another
    # member is within `stop_distance_m` ahead.
    robot_clearance_m: float = param(0.9, ge=0)
    stop_distance_m: float = param(1.0, ge=0)
    pose_timeout_s: float = param(2.0, gt=0)  # a member's pose older than this is forgotten

    def validate(self) -> None:
        from smana.common.keys import check_name

        for key, names in (("name", [self.name]), ("robots", self.robots)):
            for name in names:
                try:
                    check_name(name, "fleet name" if key == "name" else "robot name")
                except ValueError as exc:
                    raise ConfigError(f"fleet.{key}: {exc}") from None
        if self.name in self.robots:
            raise ConfigError(f"fleet.name {self.name!r} must not also be a member's name")
        if len(set(self.robots)) != len(self.robots):
            raise ConfigError(f"fleet.robots: names must be distinct, got {self.robots!r}")
        if self.start_poses and len(self.start_poses) != len(self.robots):
            raise ConfigError(
                f"fleet.start_poses: one [x, y, yaw] per member ({len(self.robots)}), "
                f"got {len(self.start_poses)}"
            )
        for p in self.start_poses:
            if len(p) != 3:
                raise ConfigError(f"fleet.start_poses: each entry is [x, y, yaw], got {p!r}")
        if self.frame == "start_pose" and not self.start_poses:
            raise ConfigError('fleet.frame = "start_pose" needs fleet.start_poses')

    @property
    def enabled(self) -> bool:
        return bool(self.robots)

    def to_fleet_frame(self, robot: str, x: float, y: float, yaw: float = 0.0):
        """A member's pose (x, y, yaw) in the fleet's frame: as it is with frame "world", moved
        by the member's start pose with "start_pose" (its odometry starts there). Anyone else's
        pose is returned as it is."""
        if self.frame != "start_pose" or robot not in self.robots:
            return x, y, yaw
        sx, sy, syaw = self.start_poses[self.robots.index(robot)]
        c, s = math.cos(syaw), math.sin(syaw)
        return sx + c * x - s * y, sy + s * x + c * y, yaw + syaw

    def shared_namespace(self, robot: str) -> str:
        """Where `robot`'s planner and explorer find the navigation graph: the fleet's for a
        member, its own otherwise."""
        return self.name if robot in self.robots else robot
