"""Every key expression smana uses, in one place: `smana/<robot>/<service>/<topic>`.

`robot` is the robot's own interface: whatever drives the robot (the simulator, a dataset replay or
a real driver) publishes its sensors and pose there and listens to its velocity commands.
Every other segment names the service that owns the topic.
A multi-robot deployment differs only in `<robot>`.
"""

from __future__ import annotations

import re

from smana.common import service_table

PREFIX = "smana"
NAME_PATTERN = "[A-Za-z0-9_-]{1,32}"
_NAME = re.compile(NAME_PATTERN)


def check_name(name, what: str = "robot name") -> str:
    """The one check of a name smana puts in a key and in a file name: a robot (`--robot`,
    `general.robot`), a fleet and its members (`fleet.name`, `fleet.robots`), a host of
    `smana deploy init-certs`. It is a whole zenoh key chunk (`smana/<robot>/...`) and part of a
    file name (`logs/mapper@<robot>.log`, `<host>.pem`), so: 1 to 32 letters, digits, '_' or
    '-'; no '/', '*', '$', '?', '#', '@', '.', space. ValueError (one line) otherwise."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"{what} {name!r} must match {NAME_PATTERN} (letters, digits, '_' and '-': it is "
            "a zenoh key chunk and a file name)"
        )
    return name


def check_robot(robot: str) -> str:
    """A robot name, checked by `check_name`."""
    return check_name(robot)


def key(robot: str, service: str, topic: str) -> str:
    return f"{PREFIX}/{check_robot(robot)}/{service}/{topic}"


# -- the robot interface (sim, replay or a real driver) --------------------------------------------
def cloud(robot: str) -> str:
    """SemanticCloud from the camera, world frame."""
    return key(robot, "robot", "cloud")


def scan(robot: str) -> str:
    """SemanticCloud from the LiDAR, world frame."""
    return key(robot, "robot", "scan")


def safety_scan(robot: str) -> str:
    """SemanticCloud from the safety scanner, the robot's base frame ("base_link")."""
    return key(robot, "robot", "safety_scan")


def pose(robot: str) -> str:
    """Pose as localisation gives it (noisy in simulation when pose noise is set)."""
    return key(robot, "robot", "pose")


def pose_truth(robot: str) -> str:
    """Ground-truth Pose (simulation only, for evaluation)."""
    return key(robot, "robot", "pose_truth")


def cmd_vel(robot: str) -> str:
    """VelocityCommand to the base."""
    return key(robot, "robot", "cmd_vel")


def clock(robot: str) -> str:
    """Simulation time (msgpack map {"sim_time_s", "real_time_factor"})."""
    return key(robot, "robot", "clock")


def image(robot: str, kind: str) -> str:
    """Camera images: kind is "rgb", "depth" or "semantic"."""
    return key(robot, "robot", f"image/{kind}")


# -- services --------------------------------------------------------------------------------------
def map_delta(robot: str) -> str:
    return key(robot, "mapper", "delta")


def graph_patch(robot: str) -> str:
    return key(robot, "navgraph", "patch")


def path_query(robot: str) -> str:
    return key(robot, "planner", "path")


def explorer_state(robot: str) -> str:
    return key(robot, "explorer", "state")


def explorer_goal(robot: str) -> str:
    """Queryable: drive to a pose. Query {"x", "y", "yaw"|None, "tolerance_m"|None, "id"|None}
    (msgpack or JSON) -> {"accepted", "id", "reason"}; a new accepted goal pre-empts the running
    one (services/explorer/navigation.py)."""
    return key(robot, "explorer", "goal")


def explorer_goal_cancel(robot: str) -> str:
    """Queryable: cancel a goal. Query {"id"|None} (None: the current goal) ->
    {"canceled", "id", "reason"}; a cancel stops the robot at once."""
    return key(robot, "explorer", "goal/cancel")


def explorer_goal_feedback(robot: str) -> str:
    """The running goal's feedback (msgpack map: id, state, goal, pose, distance_remaining_m,
    navigation_time_s, recoveries, reason), at least once a second while it runs and once at
    every change of state."""
    return key(robot, "explorer", "goal/feedback")


def claim(fleet: str, member: str) -> str:
    """The coordinator's query for one member's claims: the goal it wants in, granted or not out.
    One key per member, so that an access-control policy lets each member's identity ask its own
    only (`deploy/acl.py`)."""
    return key(fleet, "coordinator", f"claim/{check_robot(member)}")


def claims(fleet: str) -> str:
    """Every member's current goal, as the coordinator holds them (published on each change)."""
    return key(fleet, "coordinator", "claims")


def status(robot: str, service: str) -> str:
    """ServiceStatus: published periodically and answered as a query."""
    return key(robot, service, "status")


def query(robot: str, service: str, name: str) -> str:
    """A service's queryable, e.g. query(r, "mapper", "stats")."""
    return key(robot, service, name)


def alive(robot: str, service: str) -> str:
    """Liveliness token of a running service (ready: warmed up, inputs declared)."""
    return f"{PREFIX}/{check_robot(robot)}/alive/{service}"


def alive_any(robot: str = "*") -> str:
    return f"{PREFIX}/{robot}/alive/*"


def starting(robot: str, service: str) -> str:
    """Liveliness token of a service that is up but not yet ready (loading, compiling)."""
    return f"{PREFIX}/{check_robot(robot)}/starting/{service}"


def starting_any(robot: str = "*") -> str:
    return f"{PREFIX}/{robot}/starting/*"


def status_any(robot: str = "*") -> str:
    return f"{PREFIX}/{robot}/*/status"


def __getattr__(name: str):
    # SERVICES: every service's name, from the table of services (common/service_table.py): smana's
    # own, then plug-ins' (entry-point group `smana.services`), read when first asked for.
    if name == "SERVICES":
        return service_table.names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
