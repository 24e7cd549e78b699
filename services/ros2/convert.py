"""smana's messages to and from ROS 2 messages (no zenoh here: testable on its own).

Frames follow REP-105: smana's world frame is the robot's `odom` frame, published as `map`
(smana does no loop closure, so map -> odom is the identity); the robot body is `base_link`.
Those are the defaults; the service passes the names of `Ros2Config.frames` (prefixed, `r1/map`,
when robots share one /tf).
"""

from __future__ import annotations

import math

import numpy as np

from smana.common.messages import Pose, quat_to_matrix
from smana.common.navgrid import (
    FLAG_DOUBTFUL,
    FLAG_KNOWN,
    FLAG_OBSTACLE,
    FLAG_SAFETY_ZONE,
    RISK_LAYER_NAMES,
)

from . import costmap_types as nav2

POINT_FIELD_FLOAT32, POINT_FIELD_UINT16 = 7, 4
LETHAL, UNKNOWN = 100, -1
_AXIS = 1 << 20  # cell indices of within_budget's packing are offset by this
MAX_TRAVERSABLE = 98  # the dearest class; 99 is "inscribed" to nav2, 100 lethal


def ros_time(types, t_s: float):
    sec = math.floor(t_s)
    return types.msg("builtin_interfaces/msg/Time")(
        sec=int(sec), nanosec=min(int(round((t_s - sec) * 1e9)), 999_999_999)
    )


def duration(types, seconds: float):
    """A builtin_interfaces Duration of `seconds` (0 for a negative or non-finite one)."""
    s = max(0.0, float(seconds)) if math.isfinite(seconds) else 0.0
    sec = math.floor(s)
    return types.msg("builtin_interfaces/msg/Duration")(
        sec=int(sec), nanosec=min(int(round((s - sec) * 1e9)), 999_999_999)
    )


def uuid_msg(types, uuid: bytes):
    return types.msg("unique_identifier_msgs/msg/UUID")(uuid=np.frombuffer(uuid, np.uint8).copy())


def goal_info(types, uuid: bytes, stamp_ns: int):
    return types.msg("action_msgs/msg/GoalInfo")(
        goal_id=uuid_msg(types, uuid), stamp=ros_time(types, stamp_ns * 1e-9)
    )


def stamp_s(header) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def header(types, t_s: float, frame: str):
    return types.msg("std_msgs/msg/Header")(stamp=ros_time(types, t_s), frame_id=frame)


def _pose(types, position, quat_xyzw):
    Point = types.msg("geometry_msgs/msg/Point")
    Quaternion = types.msg("geometry_msgs/msg/Quaternion")
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in quat_xyzw)
    return types.msg("geometry_msgs/msg/Pose")(
        position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)
    )


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


# -- out: smana -> ROS ---------------------------------------------------------------------------


def map_cloud(types, centres, labels, colour_lut, t_s: float, frame: str = "map"):
    """Occupied voxels as a PointCloud2: x, y, z, rgb (packed as RViz reads it), label (uint16)."""
    n = len(centres)
    rec = np.zeros(
        n,
        np.dtype(
            {
                "names": ["x", "y", "z", "rgb", "label"],
                "formats": ["<f4", "<f4", "<f4", "<u4", "<u2"],
                "offsets": [0, 4, 8, 12, 16],
                "itemsize": 20,
            }
        ),
    )
    c = np.asarray(centres, np.float32).reshape(-1, 3)
    rec["x"], rec["y"], rec["z"] = c[:, 0], c[:, 1], c[:, 2]
    lab = np.asarray(labels, np.uint16)
    rgb = colour_lut[np.minimum(lab, len(colour_lut) - 1)].astype(np.uint32)
    rec["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    rec["label"] = lab
    PointField = types.msg("sensor_msgs/msg/PointField")
    fields = [
        PointField(name=name, offset=off, datatype=dt, count=1)
        for name, off, dt in (
            ("x", 0, POINT_FIELD_FLOAT32),
            ("y", 4, POINT_FIELD_FLOAT32),
            ("z", 8, POINT_FIELD_FLOAT32),
            ("rgb", 12, POINT_FIELD_FLOAT32),
            ("label", 16, POINT_FIELD_UINT16),
        )
    ]
    return types.msg("sensor_msgs/msg/PointCloud2")(
        header=header(types, t_s, frame),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=20,
        row_step=20 * n,
        data=rec.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def within_budget(centres, labels, resolution_m: float, max_points: int):
    """At most `max_points` voxels: (centres, labels, cell size). A map over the budget is merged
    into cells of 2, 4, 8 ... times `resolution_m` (each cell at its centre, with the label of
    one voxel in it, the first in the input's order) until it fits."""
    centres = np.asarray(centres, np.float32).reshape(-1, 3)
    labels = np.asarray(labels)
    if len(centres) <= max_points:
        return centres, labels, float(resolution_m)
    c = centres.astype(np.float64)
    factor = 2
    while True:
        cell = float(resolution_m) * factor
        idx = np.floor(c / cell).astype(np.int64)
        # One int64 per cell (21 bits an axis: +-100 km at 0.1 m) for a fast 1-D unique.
        packed = ((idx[:, 0] + _AXIS) << 42) | ((idx[:, 1] + _AXIS) << 21) | (idx[:, 2] + _AXIS)
        _, first = np.unique(packed, return_index=True)
        if len(first) <= max_points:
            first.sort()
            return ((idx[first] + 0.5) * cell).astype(np.float32), labels[first], cell
        factor *= 2


def _scaled(labels, cost_lut, costs, planner, top: int) -> tuple[np.ndarray, np.ndarray]:
    """(T of each node scaled from 0, the cheapest class of the table, to `top`, the dearest;
    where T is finite). `costs`: each node's T when the caller has them (under the planner's
    risk, `node_costs`), else T(label). Under a risk mode the scale reaches up to what a
    forbidden class's mass costs (`planner.risk_forbidden_cost`), so a node as dear as that
    shows at the top."""
    finite = cost_lut[np.isfinite(cost_lut)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    if costs is None:
        cost = cost_lut[np.minimum(labels, len(cost_lut) - 1)]
    else:
        cost = np.asarray(costs, np.float64)
        if planner is not None and planner.risk != "label":
            hi = max(hi, planner.risk_forbidden_cost, planner.unknown_cost)
    scaled = np.zeros(labels.shape, np.float64)
    ok = np.isfinite(cost)
    if hi > lo:
        scaled[ok] = (np.clip(cost[ok], lo, hi) - lo) / (hi - lo) * top
    return np.rint(scaled), ok


def costmap_values(labels, flags, cost_lut, costs=None, planner=None) -> np.ndarray:
    """OccupancyGrid values of graph nodes: obstacles and safety zone 100, unknown -1, known
    traversable nodes their class's traversability cost scaled to 0 (cheapest class of the table)
    .. 98 (dearest); a known node of a class that is not traversable is 100, a doubtful one (an
    obstacle class the graph has not confirmed: passable for the planner) 98. `costs` and
    `planner`: each node's T under the planner's risk mode (`node_costs`); a node that mode
    closes is 100."""
    scaled, ok = _scaled(labels, cost_lut, costs, planner, MAX_TRAVERSABLE)
    out = np.where(ok, scaled, LETHAL).astype(np.int8)
    out[(flags & FLAG_KNOWN) == 0] = UNKNOWN
    out[(flags & FLAG_DOUBTFUL) != 0] = MAX_TRAVERSABLE  # dear but passable, as the planner has it
    out[(flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0] = LETHAL
    return out


def node_costs(grid, box, cost_lut, planner=None):
    """(labels, flags, T) of the nodes of `box` ([x, y] arrays). T is what the planner charges
    for each node's class: under `planner.risk` (a PlannerConfig) from the node's label
    distribution when the mode is not "label" (common/risk.py; a grid without distributions
    reads as certain: T(label)), else None (the callers' T(label))."""
    ix0, iy0, ix1, iy1 = box
    if planner is None or planner.risk == "label":
        labels, flags = grid.box(ix0, iy0, ix1, iy1, layers=("labels", "flags"))
        return labels, flags, None
    from smana.common.risk import risk_class_costs  # numba: only under a risk mode

    layers = ("labels", "flags", *RISK_LAYER_NAMES)
    labels, flags, *risk = grid.box(ix0, iy0, ix1, iy1, layers=layers)
    return labels, flags, risk_class_costs(labels, *risk, cost_lut, planner)


def occupancy_grid(types, grid, cost_lut, t_s: float, frame: str = "map", planner=None):
    """The navigation graph's known box as an OccupancyGrid (row-major, x fastest); None while
    the graph is empty. `planner` (a PlannerConfig): its risk mode prices each node
    (`node_costs`)."""
    box = grid.known_box()
    if box is None:
        return None
    ix0, iy0, ix1, iy1 = box
    labels, flags, costs = node_costs(grid, box, cost_lut, planner)
    values = costmap_values(labels, flags, cost_lut, costs, planner)  # [x, y]
    res = grid.resolution_m
    origin = grid.origin_xy + np.array([ix0, iy0]) * res
    info = types.msg("nav_msgs/msg/MapMetaData")(
        map_load_time=ros_time(types, t_s),
        resolution=float(res),
        width=int(ix1 - ix0),
        height=int(iy1 - iy0),
        origin=_pose(types, (origin[0], origin[1], 0.0), (0.0, 0.0, 0.0, 1.0)),
    )
    return types.msg("nav_msgs/msg/OccupancyGrid")(
        header=header(types, t_s, frame),
        info=info,
        data=np.ascontiguousarray(values.T).reshape(-1),
    )


def nav2_costmap_values(labels, flags, cost_lut, costs=None, planner=None) -> np.ndarray:
    """nav2_msgs/Costmap values of graph nodes, on Nav2's scale (nav2_costmap_2d's
    cost_values.hpp): obstacles 254 (LETHAL_OBSTACLE), the robot-radius safety zone 253
    (INSCRIBED_INFLATED_OBSTACLE), unknown 255 (NO_INFORMATION); known traversable nodes their
    class's traversability cost scaled from 0 (FREE_SPACE: the cheapest class of the table) to
    252 (MAX_NON_OBSTACLE: the dearest); a known node of a class that is not traversable 254, a
    doubtful one 252.
    `costs` and `planner`: each node's T under the planner's risk mode (`node_costs`); a node
    that mode closes is 254."""
    scaled, ok = _scaled(labels, cost_lut, costs, planner, nav2.MAX_NON_OBSTACLE)
    out = np.where(ok, scaled, nav2.LETHAL_OBSTACLE).astype(np.uint8)
    out[(flags & FLAG_KNOWN) == 0] = nav2.NO_INFORMATION
    out[(flags & FLAG_DOUBTFUL) != 0] = nav2.MAX_NON_OBSTACLE
    out[(flags & FLAG_SAFETY_ZONE) != 0] = nav2.INSCRIBED_INFLATED_OBSTACLE
    out[(flags & FLAG_OBSTACLE) != 0] = nav2.LETHAL_OBSTACLE
    return out


def nav2_costmap(
    types, grid, cost_lut, t_s: float, load_t_s: float, frame: str = "map", planner=None
):
    """The navigation graph's known box as a nav2_msgs/Costmap (`data` row-major from cell
    (0, 0), x fastest; `origin` the corner of that cell, as Nav2's costmap publisher writes it;
    layer "master", Nav2's name for the combined costmap); None while the graph is empty.
    `load_t_s` is when the costmap this one updates was first published. `planner` (a
    PlannerConfig): its risk mode prices each node (`node_costs`)."""
    box = grid.known_box()
    if box is None:
        return None
    ix0, iy0, ix1, iy1 = box
    labels, flags, costs = node_costs(grid, box, cost_lut, planner)
    values = nav2_costmap_values(labels, flags, cost_lut, costs, planner)  # [x, y]
    res = grid.resolution_m
    origin = grid.origin_xy + np.array([ix0, iy0]) * res
    meta = types.msg(nav2.COSTMAP_META)(
        map_load_time=ros_time(types, load_t_s),
        update_time=ros_time(types, t_s),
        layer="master",
        resolution=float(res),
        size_x=int(ix1 - ix0),
        size_y=int(iy1 - iy0),
        origin=_pose(types, (origin[0], origin[1], 0.0), (0.0, 0.0, 0.0, 1.0)),
    )
    return types.msg(nav2.COSTMAP)(
        header=header(types, t_s, frame),
        metadata=meta,
        data=np.ascontiguousarray(values.T).reshape(-1),
    )


def pose_stamped(types, xy, yaw: float, t_s: float, frame: str = "map", z: float = 0.0):
    return types.msg("geometry_msgs/msg/PoseStamped")(
        header=header(types, t_s, frame),
        pose=_pose(types, (xy[0], xy[1], z), yaw_quat(yaw)),
    )


def path(types, path_xy, t_s: float, frame: str = "map", final_yaw: float | None = None):
    """A path of (x, y[, z]) waypoints; each pose faces the next waypoint, the last one
    `final_yaw` when given (a goal's heading, as Nav2's planners end a path)."""
    pts = np.asarray(path_xy, np.float64).reshape(-1, np.shape(path_xy)[-1] if len(path_xy) else 2)
    poses = []
    for i, p in enumerate(pts):
        q = pts[min(i + 1, len(pts) - 1)] - pts[max(i - 1, 0)] if len(pts) > 1 else (1.0, 0.0)
        yaw = math.atan2(q[1], q[0])
        if final_yaw is not None and i == len(pts) - 1:
            yaw = float(final_yaw)
        poses.append(pose_stamped(types, p[:2], yaw, t_s, frame, p[2] if len(p) > 2 else 0.0))
    return types.msg("nav_msgs/msg/Path")(header=header(types, t_s, frame), poses=poses)


def odometry(types, pose: Pose, frame: str = "map", child: str = "base_link", twist=(0.0, 0.0)):
    """The pose smana uses as Odometry; `twist` = (linear m/s, angular rad/s) in the body frame."""
    Vector3 = types.msg("geometry_msgs/msg/Vector3")
    tw = types.msg("geometry_msgs/msg/Twist")(
        linear=Vector3(x=float(twist[0]), y=0.0, z=0.0),
        angular=Vector3(x=0.0, y=0.0, z=float(twist[1])),
    )
    return types.msg("nav_msgs/msg/Odometry")(
        header=header(types, pose.stamp_s, frame),
        child_frame_id=child,
        pose=types.msg("geometry_msgs/msg/PoseWithCovariance")(
            pose=_pose(types, pose.position, pose.orientation_xyzw),
            covariance=np.zeros(36, np.float64),
        ),
        twist=types.msg("geometry_msgs/msg/TwistWithCovariance")(
            twist=tw, covariance=np.zeros(36, np.float64)
        ),
    )


def robot_frames(
    types, pose: Pose, world: str = "map", odom: str = "odom", base: str = "base_link"
):
    """/tf for a simulated robot: world -> odom (the identity: no loop closure) and odom -> base
    at the pose."""

    def stamped(parent, child, position, quat):
        x, y, z = (float(v) for v in position)
        qx, qy, qz, qw = (float(v) for v in quat)
        return types.msg("geometry_msgs/msg/TransformStamped")(
            header=header(types, pose.stamp_s, parent),
            child_frame_id=child,
            transform=types.msg("geometry_msgs/msg/Transform")(
                translation=types.msg("geometry_msgs/msg/Vector3")(x=x, y=y, z=z),
                rotation=types.msg("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
            ),
        )

    return types.msg("tf2_msgs/msg/TFMessage")(
        transforms=[
            stamped(world, odom, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
            stamped(odom, base, pose.position, pose.orientation_xyzw),
        ]
    )


def twist(types, linear_mps: float, angular_radps: float):
    Vector3 = types.msg("geometry_msgs/msg/Vector3")
    return types.msg("geometry_msgs/msg/Twist")(
        linear=Vector3(x=float(linear_mps), y=0.0, z=0.0),
        angular=Vector3(x=0.0, y=0.0, z=float(angular_radps)),
    )


def plan_response(types, path_xyz, t_s: float, frame: str = "map"):
    """GetPlan's answer; an empty path when there is none (as nav2's planners answer)."""
    plan = path(types, path_xyz if len(path_xyz) else np.zeros((0, 3)), t_s, frame)
    return types.msg("nav_msgs/srv/GetPlan_Response")(plan=plan)


# -- in: ROS -> smana ----------------------------------------------------------------------------


def _checked(p, q, what: str, normalise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(position [3], unit quaternion xyzw [4]) of ROS Point/Vector3 and Quaternion fields;
    ValueError if not finite or the quaternion is degenerate (its norm zero, or overflowing).
    `normalise=False` returns the quaternion as it came, for a caller that checks its norm."""
    pos = np.array([p.x, p.y, p.z], np.float64)
    quat = np.array([q.x, q.y, q.z, q.w], np.float64)
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(quat))
    if not (np.isfinite(pos).all() and np.isfinite(quat).all()) or not 1e-6 <= norm < math.inf:
        raise ValueError(f"{what} with non-finite numbers or a zero or overflowing quaternion")
    return pos, quat / norm if normalise else quat


def pose_of(msg_pose, normalise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/Pose -> (position, unit quaternion xyzw)."""
    return _checked(msg_pose.position, msg_pose.orientation, "pose", normalise)


def matrix(position, quat_xyzw) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(quat_xyzw)
    m[:3, 3] = position
    return m


def transform_matrix(tf) -> np.ndarray:
    """geometry_msgs/Transform -> 4x4."""
    return matrix(*_checked(tf.translation, tf.rotation, "transform"))


def extrinsic_matrix(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """x, y, z, roll, pitch, yaw (REP-103, fixed axes) -> 4x4."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    m = np.eye(4)
    m[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    m[:3, 3] = x, y, z
    return m


def chain(static: dict[str, tuple[str, np.ndarray]], base: str, frame: str) -> np.ndarray | None:
    """The pose of `frame` in `base` from static transforms {child: (parent, parent_T_child)};
    None when `frame` does not hang below `base`."""
    m = np.eye(4)
    seen = set()
    while frame != base:
        if frame not in static or frame in seen:
            return None
        seen.add(frame)
        parent, t = static[frame]
        m = t @ m
        frame = parent
    return m
