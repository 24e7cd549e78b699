"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and bare MCAP files, without a ROS install.

Scans come from a sensor_msgs/PointCloud2 topic with float fields x, y, z and an integer label
field of any width (name configurable, `label` by default); an optional float `confidence` field
is used when present. Poses come from a nav_msgs/Odometry topic, interpolated at each cloud's
header stamp (linear in position, slerp in orientation), or from one fixed pose for a static
sensor. Clouds stamped outside the odometry's time span by more than `max_pose_gap_s` are skipped.
With `label_field="none"` clouds need x, y, z only and are read without labels: the replay labels
their points by geometry.

The `rosbags` package is imported lazily: it is an optional dependency
(`pip install 'smana[replay]'`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smana.common.ros import PoseTrack, check_cloud, decode_cloud

from .base import NO_LABELS, NO_LABELS_HINT, DatasetError, DatasetReader, Scan

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOM_TYPE = "nav_msgs/msg/Odometry"


def _import_rosbags():
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise ImportError(
            "reading ROS bags needs the 'rosbags' package: pip install 'smana[replay]'"
        ) from None


class _BareMcap:
    """A single .mcap file (no rosbag2 metadata.yaml) behind AnyReader's small interface."""

    def __init__(self, path: Path):
        from rosbags.rosbag2.storage_mcap import McapReader
        from rosbags.typesys import Stores, get_typestore

        self._reader = McapReader(path)
        self._reader.open()
        self.connections = self._reader.connections
        # PointCloud2 and Odometry are identical in every ROS 2 distro: the bundled store suffices.
        self._typestore = get_typestore(Stores.ROS2_HUMBLE)

    def messages(self, connections):
        return self._reader.messages(connections)

    def deserialize(self, raw, msgtype):
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self):
        self._reader.close()


def _open_bag(path: Path):
    _import_rosbags()
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.typesys import Stores, get_typestore

    try:
        if path.is_file() and path.suffix == ".mcap":
            return _BareMcap(path)
        if not (path.suffix == ".bag" or (path / "metadata.yaml").is_file()):
            raise DatasetError(path, "not a ROS 1 .bag, a ROS 2 bag folder or an .mcap file")
        store = Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE
        reader = AnyReader([path], default_typestore=get_typestore(store))
        reader.open()
        return reader
    except (AnyReaderError, ReaderError, OSError) as exc:
        raise DatasetError(path, f"cannot open bag: {exc}") from None


def _stamp_s(header) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def fixed_pose_matrix(pose) -> np.ndarray:
    """A 4x4 matrix, or (x, y, z, yaw) -> 4x4."""
    arr = np.asarray(pose, np.float64)
    if arr.shape == (4, 4):
        return arr.copy()
    if arr.shape == (4,):
        x, y, z, yaw = arr
        m = np.eye(4)
        c, s = np.cos(yaw), np.sin(yaw)
        m[:2, :2] = [[c, -s], [s, c]]
        m[:3, 3] = x, y, z
        return m
    raise ValueError("fixed pose must be a 4x4 matrix or (x, y, z, yaw)")


class RosbagReader(DatasetReader):
    format = "rosbag"
    default_class_table = "rellis3d"
    sequential = True

    def __init__(
        self,
        path,
        *,
        cloud_topic: str | None = None,
        odom_topic: str | None = None,
        label_field: str = "label",
        fixed_pose=None,
        sensor_to_base=None,
        max_pose_gap_s: float = 0.2,
        strict: bool = False,
    ):
        super().__init__(path, strict=strict)
        self.labelled = label_field != NO_LABELS
        self.label_field = label_field if self.labelled else None  # as common/ros.py takes it
        self._bag = _open_bag(self.path)
        try:
            self._index(cloud_topic, odom_topic, fixed_pose, sensor_to_base, max_pose_gap_s)
        except BaseException:
            self.close()
            raise

    def _pick_topic(self, topic: str | None, msgtype: str, what: str):
        conns = [c for c in self._bag.connections if c.msgtype == msgtype]
        if topic is not None:
            chosen = [c for c in self._bag.connections if c.topic == topic]
            if not chosen:
                known = ", ".join(sorted({c.topic for c in self._bag.connections})) or "none"
                raise DatasetError(self.path, f"no topic {topic!r} (topics: {known})")
            if chosen[0].msgtype != msgtype:
                raise DatasetError(
                    self.path, f"topic {topic!r} is {chosen[0].msgtype}, expected {msgtype}"
                )
            return chosen
        topics = sorted({c.topic for c in conns})
        if len(topics) > 1:
            raise DatasetError(self.path, f"several {what} topics, name one: {', '.join(topics)}")
        return conns

    def _index(self, cloud_topic, odom_topic, fixed_pose, sensor_to_base, max_gap_s) -> None:
        clouds = self._pick_topic(cloud_topic, CLOUD_TYPE, "PointCloud2")
        if not clouds:
            raise DatasetError(self.path, "no sensor_msgs/PointCloud2 topic")
        self._clouds = clouds
        self.cloud_topic = clouds[0].topic
        self._sensor_to_base = (
            np.eye(4) if sensor_to_base is None else fixed_pose_matrix(sensor_to_base)
        )
        self._fixed = None if fixed_pose is None else fixed_pose_matrix(fixed_pose)
        self._track: PoseTrack | None = None
        self._odom_frame = None
        if self._fixed is None:
            odoms = self._pick_topic(odom_topic, ODOM_TYPE, "Odometry")
            if not odoms:
                raise DatasetError(
                    self.path, "no nav_msgs/Odometry topic: give a fixed pose for a static sensor"
                )
            self._track = self._read_odometry(odoms)

        # One pass over the clouds decides which scans can be replayed; only stamps are kept.
        self._entries: list[tuple[int, float, np.ndarray]] = []  # (message number, stamp, pose)
        self._n_messages = 0
        for k, (_, msg) in enumerate(self._cloud_messages()):
            self._n_messages += 1
            name = f"{self.cloud_topic}#{k}"
            why = check_cloud(msg, self.label_field)
            if why is not None:
                if why.startswith("label field") and "missing" in why:
                    why = f"{why}; {NO_LABELS_HINT}"
                self.skip(name, why)
                continue
            stamp = _stamp_s(msg.header)
            pose = self._pose_at(stamp, max_gap_s)
            if pose is None:
                self.skip(name, f"no odometry within {max_gap_s} s of stamp {stamp:.3f}")
                continue
            self._entries.append((k, stamp, pose))
        if not self._entries:
            first = self.skipped[0].reason if self.skipped else "the topic has no messages"
            raise DatasetError(
                self.path, f"no scan can be replayed from {self.cloud_topic}: {first}"
            )
        self._cursor = None  # (iterator over cloud messages, next message number)

    def _read_odometry(self, conns) -> PoseTrack:
        stamps, pos, quat = [], [], []
        for conn, _, raw in self._bag.messages(connections=conns):
            msg = self._bag.deserialize(raw, conn.msgtype)
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            stamps.append(_stamp_s(msg.header))
            pos.append((p.x, p.y, p.z))
            quat.append((q.x, q.y, q.z, q.w))
            self._odom_frame = msg.header.frame_id
        if not stamps:
            raise DatasetError(self.path, f"odometry topic {conns[0].topic} has no messages")
        quat = np.asarray(quat, np.float64)
        norms = np.linalg.norm(quat, axis=1)
        if not np.all(np.isfinite(pos)) or np.any(~np.isfinite(norms) | (norms < 1e-6)):
            raise DatasetError(self.path, f"{conns[0].topic}: non-finite or zero-norm pose")
        return PoseTrack(np.asarray(stamps), np.asarray(pos, np.float64), quat / norms[:, None])

    def _pose_at(self, stamp: float, max_gap_s: float) -> np.ndarray | None:
        if self._fixed is not None:
            return self._fixed @ self._sensor_to_base
        base = self._track.at(stamp, max_gap_s)
        return None if base is None else base @ self._sensor_to_base

    def _cloud_messages(self):
        for conn, _, raw in self._bag.messages(connections=self._clouds):
            yield conn, self._bag.deserialize(raw, conn.msgtype)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def rate_hz(self) -> float:
        stamps = np.array([e[1] for e in self._entries])
        if stamps.size < 2:
            return 10.0
        dt = float(np.median(np.diff(stamps)))
        return 1.0 / dt if dt > 0 else 10.0

    def _make_scan(self, i: int, msg) -> Scan:
        k, stamp, pose = self._entries[i]
        points, labels, conf = decode_cloud(msg, self.label_field)
        if self._odom_frame is not None and msg.header.frame_id == self._odom_frame:
            # The cloud was recorded in the world frame already: bring it back to the sensor's.
            inv = np.linalg.inv(pose)
            points = (points.astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
        return Scan(i, f"{self.cloud_topic}#{k}", stamp, points, labels, pose.copy(), conf)

    def __iter__(self):
        wanted = {e[0]: i for i, e in enumerate(self._entries)}
        for k, (_, msg) in enumerate(self._cloud_messages()):
            if k in wanted:
                yield self._make_scan(wanted[k], msg)

    def scan(self, i: int) -> Scan:
        # Bags are streams: random access walks forward, restarting only when asked to go back.
        target = self._entries[i][0]
        if self._cursor is None or self._cursor[1] > target:
            self._cursor = [iter(self._cloud_messages()), 0]
        it = self._cursor[0]
        try:
            while True:
                _, msg = next(it)
                k = self._cursor[1]
                self._cursor[1] += 1
                if k == target:
                    return self._make_scan(i, msg)
        except StopIteration:
            self._cursor = None
            raise DatasetError(
                self.path, f"message {target} of {self.cloud_topic} is gone"
            ) from None
        except Exception:
            self._cursor = None  # a broken stream: the next call starts over
            raise

    def close(self) -> None:
        bag, self._bag = getattr(self, "_bag", None), None
        if bag is not None:
            bag.close()
