"""What the ros2 service keeps between messages, without zenoh: a copy of the map from the
mapper's deltas, recent odometry, the static transforms, and the conversion of a ROS 2 robot's
PointCloud2 into a smana `SemanticCloud` in the world frame."""

from __future__ import annotations

import collections
from collections.abc import Callable

import numpy as np

from smana.common.messages import MapDelta, SemanticCloud, matrix_to_quat
from smana.common.ros import PoseTrack, check_cloud, decode_cloud
from smana.common.service import Reject

from . import convert

_AXIS_OFFSET = 1 << 20  # voxel indices per axis fit in 21 bits: +-100 km at 0.1 m


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


class CloudInput:
    """A ROS 2 robot's PointCloud2 -> SemanticCloud in the world frame.

    A cloud in a world frame (`ros2.world_frames`) is used as it is; one in a sensor frame is
    placed with the odometry at its stamp and the sensor's pose on the robot (from /tf_static or
    `ros2.sensor_extrinsic`). Labels come from the cloud's label field, or from the geometric
    labeller (`label_field = none`). Each refusal is a `Reject` whose kind says why."""

    def __init__(self, config, labeller: Callable | None):
        self.rc = config.ros2
        self.labeller = labeller  # (points_world, sensor_origin) -> labels, or None
        self.field = None if self.rc.label_field == "none" else self.rc.label_field
        self.poses = PoseHistory()
        self.static: dict[str, tuple[str, np.ndarray]] = {}
        self.extrinsic = (
            convert.extrinsic_matrix(*self.rc.sensor_extrinsic)
            if self.rc.sensor_extrinsic
            else None
        )
        self.seq = 0

    def add_static(self, tf_message) -> int:
        """Static transforms of a tf2_msgs/TFMessage; returns how many were taken."""
        n = 0
        for t in tf_message.transforms:
            try:
                m = convert.transform_matrix(t.transform)
            except ValueError:
                continue
            self.static[t.child_frame_id.lstrip("/")] = (t.header.frame_id.lstrip("/"), m)
            n += 1
        return n

    def sensor_on_robot(self, frame: str) -> np.ndarray | None:
        m = convert.chain(self.static, self.rc.base_frame, frame)
        return m if m is not None else self.extrinsic

    def convert(self, msg) -> SemanticCloud:
        if why := check_cloud(msg, self.field):
            if self.field is not None and "missing" in why:
                why += "; to map clouds without labels set ros2.label_field=none"
            raise Reject("value", why)
        t = convert.stamp_s(msg.header)
        frame = msg.header.frame_id.lstrip("/")
        base = self.poses.at(t, self.rc.max_pose_gap_s)
        if base is None:
            what = "no odometry yet" if not len(self.poses) else f"odometry does not cover {t:.3f}"
            raise Reject("no_pose", f"cloud at {t:.3f} s: {what} on {self.rc.odom_topic}")
        points, labels, conf = decode_cloud(msg, self.field)
        ok = np.isfinite(points).all(axis=1)
        if frame in self.rc.world_frames:
            # Already placed: the sensor is taken at the robot's odometry pose (plus the
            # extrinsic when known) so the mapper can carve free space along the rays.
            world_sensor = base @ (self.extrinsic if self.extrinsic is not None else np.eye(4))
            world = points
        else:
            on_robot = self.sensor_on_robot(frame)
            if on_robot is None:
                raise Reject(
                    "no_transform",
                    f"cloud in frame {frame!r}: no /tf_static chain from {self.rc.base_frame!r} "
                    "and no ros2.sensor_extrinsic",
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
