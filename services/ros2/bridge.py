"""What the ros2 service keeps between messages, without zenoh: a copy of the map from the
mapper's deltas, the resync of the map and graph streams from their snapshots (`StreamSync`),
the explorer's path and goal as last shown (`ExplorerView`), the robot's last pose (its twist),
recent odometry, the static transforms, and the conversion of a ROS 2 robot's Odometry into a
smana `Pose` and its PointCloud2 into a `SemanticCloud` in the world frame.

A ROS 2 robot's input passes the checks smana's own messages pass (`common/messages.py`'s codec:
coordinates within 1000 km, stamps up to the year 2286, a unit quaternion; and
`common/plausibility.py`: a stamp must fit its stream's clock, a pose may not jump further than
the robot can travel) before it is taken: a refusal is a `Reject` whose kind says why, and
nothing refused is republished. Every table keyed by something the robot chooses (the static
transforms, keyed by frame name) has a cap; what would go past it is refused and counted."""

from __future__ import annotations

import collections
import math
from collections.abc import Callable

import msgpack
import numpy as np

from smana.common.messages import (
    STAMP_LIMIT_S,
    MapDelta,
    MessageError,
    Pose,
    SemanticCloud,
    decode,
    encode,
    matrix_to_quat,
)
from smana.common.plausibility import PoseGate, StampGate
from smana.common.ros import PoseTrack, check_cloud, decode_cloud
from smana.common.service import Reject

from . import convert

_AXIS_OFFSET = 1 << 20  # voxel indices per axis fit in 21 bits: +-100 km at 0.1 m
# A robot has tens of static frames; a stream of new names (a bug, or a peer filling memory)
# stops here. Longer frame names than any ROS graph uses are refused too.
MAX_STATIC_FRAMES = 1000
MAX_FRAME_NAME = 256


def checked(msg, what: str):
    """`msg` through smana's codec, as a receiving service would decode it: (the message,
    its msgpack bytes). A value the codec refuses is a `Reject` of the codec's kind."""
    payload = encode(msg)
    try:
        return decode(payload, type(msg)), payload
    except MessageError as exc:
        raise Reject(exc.kind, f"{what}: {exc}") from None


def plausible_stamp(gate: StampGate, t_s: float, what: str) -> None:
    """The codec's stamp range, then the stream's clock (`Reject` `value` or the gate's kind)."""
    if not 0.0 <= t_s <= STAMP_LIMIT_S:
        raise Reject("value", f"{what}: stamp {t_s:.6g} s outside [0, {STAMP_LIMIT_S:g}]")
    when = gate.check(t_s)
    if not when.ok:
        raise Reject(when.kind, f"{what}: {when.reason}")


class MapCopy:
    """The occupied voxels of the mapper's map (centre -> label), kept from its delta stream."""

    def __init__(self):
        self.resolution_m = 0.0
        self.keys = np.zeros(0, np.int64)  # sorted
        self.centres = np.zeros((0, 3), np.float32)
        self.labels = np.zeros(0, np.uint16)
        self.version = 0

    def _keys(self, centres: np.ndarray) -> np.ndarray:
        idx = np.floor(centres.astype(np.float64) / self.resolution_m).astype(np.int64)
        idx += _AXIS_OFFSET
        return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]

    def reset(self, delta: MapDelta) -> None:
        """Replace the map by a snapshot (a MapDelta of occupied voxels)."""
        self.resolution_m = float(delta.resolution_m)
        self.keys = np.zeros(0, np.int64)
        self.centres = np.zeros((0, 3), np.float32)
        self.labels = np.zeros(0, np.uint16)
        self.apply(delta)

    def apply(self, delta: MapDelta) -> None:
        if self.resolution_m != float(delta.resolution_m):
            if len(self.keys):
                raise Reject("geometry", f"map delta {delta.seq}: resolution changed; resync")
            self.resolution_m = float(delta.resolution_m)
        if not len(delta.centres):
            return
        k = self._keys(delta.centres)
        pos = np.searchsorted(self.keys, k)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == k[found]
        occ = delta.occupied.astype(bool)
        self.labels[pos[found & occ]] = delta.labels[found & occ]
        gone = pos[found & ~occ]
        new = ~found & occ
        keys = np.concatenate([np.delete(self.keys, gone), k[new]])
        centres = np.concatenate([np.delete(self.centres, gone, axis=0), delta.centres[new]])
        labels = np.concatenate([np.delete(self.labels, gone), delta.labels[new]])
        order = np.argsort(keys, kind="stable")
        self.keys, self.centres, self.labels = keys[order], centres[order], labels[order]
        self.version += 1

    def __len__(self) -> int:
        return len(self.keys)


class PoseHistory:
    """Recent odometry, interpolated at a cloud's stamp (linear position, slerp orientation)."""

    def __init__(self, size: int = 400):
        self._poses: collections.deque = collections.deque(maxlen=size)

    def add(self, t_s: float, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        if self._poses and t_s < self._poses[-1][0]:
            self._poses.clear()  # the clock went back (a replayed bag restarted)
        self._poses.append((t_s, position, quat_xyzw))

    def at(self, t_s: float, max_gap_s: float) -> np.ndarray | None:
        if not self._poses:
            return None
        t, p, q = (np.array(v) for v in zip(*self._poses, strict=True))
        return PoseTrack(t, p, q).at(t_s, max_gap_s)

    def __len__(self) -> int:
        return len(self._poses)


class OdometryInput:
    """A ROS 2 robot's nav_msgs/Odometry -> the smana `Pose` it publishes on `robot/pose`, through
    the codec's bounds and the gates `general` configures (as the explorer gates smana's own
    poses): `checked` gives the pose and its bytes, or raises `Reject`."""

    def __init__(self, general):
        g = general
        self.stamps = StampGate(g.stamp_window_s, g.max_time_rate)
        self.places = PoseGate(g.max_speed_mps, g.pose_slack_m)
        self.seq = 0

    def checked(self, msg) -> tuple[Pose, bytes]:
        try:
            pos, quat = convert.pose_of(msg.pose.pose, normalise=False)
        except ValueError as exc:
            raise Reject("value", f"odometry: {exc}") from None
        t = convert.stamp_s(msg.header)
        # The codec first (1e308 m, a quaternion of norm 1e200), then the stream's history.
        pose, _ = checked(Pose(t, self.seq + 1, pos, quat, "world"), "odometry")
        plausible_stamp(self.stamps, t, "odometry")
        where = self.places.check(t, pos)
        if not where.ok:
            raise Reject(where.kind, f"odometry: {where.reason}")
        self.seq += 1
        pose.orientation_xyzw = quat / np.linalg.norm(quat)
        return checked(pose, "odometry")


class CloudInput:
    """A ROS 2 robot's PointCloud2 -> SemanticCloud in the world frame.

    A cloud in a world frame (`ros2.world_frames`) is used as it is; one in a sensor frame is
    placed with the odometry at its stamp and the sensor's pose on the robot (from the robot's
    static transforms or `ros2.sensor_extrinsic`). Frame names are `frames`' (`Ros2Config.frames`:
    prefixed when the config sets `ros2.frame_prefix`). Labels come from the cloud's label field,
    or from the geometric labeller (`label_field = none`). Each refusal is a `Reject` whose kind
    says why."""

    def __init__(self, config, labeller: Callable | None, frames=None):
        self.rc = config.ros2
        # a robot's input: "auto" adds no prefix (the frames are the robot's), a set one does
        self.frames = frames or self.rc.frames("", robot_input=True)
        self.labeller = labeller  # (points_world, sensor_origin) -> labels, or None
        self.field = None if self.rc.label_field == "none" else self.rc.label_field
        self.poses = PoseHistory()
        self.static: dict[str, tuple[str, np.ndarray]] = {}
        self.static_refused = 0  # transforms refused: new frames past MAX_STATIC_FRAMES, ...
        general = getattr(config, "general", None)
        self.stamps = (
            StampGate(general.stamp_window_s, general.max_time_rate)
            if general is not None
            else StampGate()
        )
        self.extrinsic = (
            convert.extrinsic_matrix(*self.rc.sensor_extrinsic)
            if self.rc.sensor_extrinsic
            else None
        )
        self.seq = 0

    def add_static(self, tf_message) -> int:
        """Static transforms of a tf2_msgs/TFMessage; returns how many were taken. A transform
        that is not finite, names a frame longer than MAX_FRAME_NAME, or would add a frame past
        MAX_STATIC_FRAMES is refused (counted in `static_refused`); a known frame is updated."""
        n = 0
        for t in tf_message.transforms:
            child, parent = t.child_frame_id.lstrip("/"), t.header.frame_id.lstrip("/")
            full = child not in self.static and len(self.static) >= MAX_STATIC_FRAMES
            if full or max(len(child), len(parent)) > MAX_FRAME_NAME:
                self.static_refused += 1
                continue
            try:
                m = convert.transform_matrix(t.transform)
            except ValueError:
                self.static_refused += 1
                continue
            self.static[child] = (parent, m)
            n += 1
        return n

    def sensor_on_robot(self, frame: str) -> np.ndarray | None:
        m = convert.chain(self.static, self.frames.base, frame)
        return m if m is not None else self.extrinsic

    def convert(self, msg) -> SemanticCloud:
        if why := check_cloud(msg, self.field):
            if self.field is not None and "missing" in why:
                why += "; to map clouds without labels set ros2.label_field=none"
            raise Reject("value", why)
        t = convert.stamp_s(msg.header)
        plausible_stamp(self.stamps, t, "cloud")
        frame = msg.header.frame_id.lstrip("/")
        base = self.poses.at(t, self.rc.max_pose_gap_s)
        if base is None:
            what = "no odometry yet" if not len(self.poses) else f"odometry does not cover {t:.3f}"
            raise Reject("no_pose", f"cloud at {t:.3f} s: {what} on {self.rc.odom_topic}")
        points, labels, conf = decode_cloud(msg, self.field)
        ok = np.isfinite(points).all(axis=1)
        if frame in self.frames.world:
            # Already placed: the sensor is taken at the robot's odometry pose (plus the
            # extrinsic when known) so the mapper can carve free space along the rays.
            world_sensor = base @ (self.extrinsic if self.extrinsic is not None else np.eye(4))
            world = points
        else:
            on_robot = self.sensor_on_robot(frame)
            if on_robot is None:
                raise Reject(
                    "no_transform",
                    f"cloud in frame {frame!r}: no static transforms from {self.frames.base!r} "
                    f"on {self.rc.tf_static_topic} and no ros2.sensor_extrinsic",
                )
            world_sensor = base @ on_robot
            world = (points @ world_sensor[:3, :3].T + world_sensor[:3, 3]).astype(np.float32)
        origin = world_sensor[:3, 3]
        rng = np.linalg.norm(world - origin.astype(np.float32), axis=1)
        ok &= (rng >= self.rc.min_range_m) & (rng <= self.rc.max_range_m)
        world = np.ascontiguousarray(world[ok], np.float32)
        if self.field is None:
            labels = self.labeller(world, origin)
        else:
            labels = labels[ok]
            if len(labels) and (labels.min() < 0 or labels.max() > 65535):
                raise Reject("value", "labels outside 0..65535")
        conf = np.ones(len(world), np.float32) if conf is None else conf[ok]
        self.seq += 1
        return SemanticCloud(
            stamp_s=t,
            seq=self.seq,
            points=world,
            labels=np.asarray(labels, np.uint16),
            confidences=np.clip(np.nan_to_num(conf, nan=0.0), 0.0, 1.0).astype(np.float32),
            sensor_position=origin.astype(np.float64),
            sensor_orientation_xyzw=matrix_to_quat(world_sensor[:3, :3]),
            frame_id="world",
            source="lidar",
        )


def twist_between(last: Pose | None, pose: Pose) -> tuple[float, float]:
    """(forward speed m/s, turn rate rad/s) from the robot's last pose to `pose`, for the
    Odometry's twist; (0, 0) without a last pose less than a second older."""
    if last is None or not 0.0 < pose.stamp_s - last.stamp_s < 1.0:
        return 0.0, 0.0
    dt = pose.stamp_s - last.stamp_s
    d = pose.position[:2] - last.position[:2]
    dyaw = math.remainder(pose.yaw - last.yaw, math.tau)
    return float(d @ [math.cos(pose.yaw), math.sin(pose.yaw)]) / dt, dyaw / dt


class ExplorerView:
    """The explorer's state (`explorer/state`) as the ROS 2 side shows it: its path and goal,
    read and checked, once per change."""

    def __init__(self):
        self.last: tuple | None = None

    def update(self, payload: bytes) -> tuple[np.ndarray, list | None, float, float] | None:
        """(path (K, 2|3), goal xy or None, goal yaw, stamp s) when they changed, else None.
        MessageError for a state that is not one."""
        try:
            state = msgpack.unpackb(payload)
            goal = state.get("goal")
            path = np.asarray(state.get("path") or np.zeros((0, 2)), np.float64)
            t = float(state.get("t_s") or 0.0)
            xy = None if goal is None else [float(v) for v in goal["xy"]]
            yaw = 0.0 if goal is None else float(goal.get("yaw") or 0.0)
        except (ValueError, TypeError, KeyError, AttributeError, msgpack.UnpackException) as exc:
            raise MessageError("malformed", f"explorer state: {exc}") from None
        if path.ndim != 2 or path.shape[-1] not in (2, 3) or not np.isfinite(path).all():
            raise MessageError("value", "explorer state: path must be finite (x, y) points")
        if xy is not None and (len(xy) not in (2, 3) or not np.isfinite([*xy, yaw]).all()):
            # a goal of one number reached convert.pose_stamped and failed there (the campaign)
            raise MessageError("value", "explorer state: a goal must be finite x, y and yaw")
        key = (None if xy is None else tuple(xy), yaw, path.tobytes())
        if key == self.last:
            return None
        self.last = key
        return path, xy, yaw, t


class StreamSync:
    """A stream kept from its producer's updates (the map's deltas, the graph's patches) and
    resynchronised from its snapshot: whether one is wanted, the one on its way, and the updates
    that came meanwhile (applied after it, MAX_HELD at most: past that the stream has a gap and
    another resync follows)."""

    def __init__(self, period_s: float, max_held: int):
        self.period_s, self.max_held = period_s, max_held
        self.wanted = True  # at start, and after a failed sync or a producer's restart
        self.syncing = False
        self.next_try = 0.0
        self.held: list = []

    def due(self, now: float, want_resync: bool) -> bool:
        """Whether to fetch a snapshot now (one a period at most); it is then on its way."""
        if self.syncing or not (self.wanted or want_resync) or now < self.next_try:
            return False
        self.next_try = now + self.period_s
        self.syncing = True
        return True

    def hold(self, msg):
        """Keep an update that came while the snapshot is on its way (None), or drop it."""
        if len(self.held) >= self.max_held:
            return ("dropped", "sync_backlog")
        self.held.append(msg)
        return None

    def done(self, ok: bool) -> list:
        """The snapshot came (and was adopted when `ok`) or did not: the updates held."""
        self.wanted = not ok
        self.syncing = False
        held, self.held = self.held, []
        return held
