"""ROS message helpers shared by the replay's bag reader and the ros2 service: PointCloud2
decoding (any field layout, padding, endianness) and odometry interpolated at a stamp.

Messages are the objects rosbags' typestore deserialises (attribute access as in rclpy); nothing
here imports rosbags, so these helpers cost nothing without it.
"""

from __future__ import annotations

import numpy as np

from smana.common.messages import quat_to_matrix

# sensor_msgs/PointField datatypes -> numpy kinds
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_INT_TYPES = {1, 2, 3, 4, 5, 6}
_FLOAT_TYPES = {7, 8}


def cloud_fields(msg) -> dict[str, tuple[int, int, int]]:
    """PointCloud2 field name -> (offset, datatype, count)."""
    return {f.name: (int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields}


def check_cloud(msg, label_field: str | None) -> str | None:
    """Why this PointCloud2 cannot be read as a labelled scan, or None if it can. With
    `label_field=None` the cloud is read without labels (x, y, z only are required)."""
    fields = cloud_fields(msg)
    names = ", ".join(fields) or "none"
    for axis in "xyz":
        if axis not in fields:
            return f"field {axis!r} missing from the PointCloud2 (fields: {names})"
        if fields[axis][1] not in _FLOAT_TYPES:
            return f"field {axis!r} is not float32/float64"
    if label_field is not None:
        if label_field not in fields:
            return f"label field {label_field!r} missing from the PointCloud2 (fields: {names})"
        if fields[label_field][1] not in _INT_TYPES:
            return f"label field {label_field!r} is not an integer type"
    step = int(msg.point_step)
    for name, (off, dt, count) in fields.items():
        if dt in _FIELD_TYPES and off + np.dtype(_FIELD_TYPES[dt]).itemsize * max(count, 1) > step:
            return f"field {name!r} runs past point_step {step}"
    n = int(msg.width) * int(msg.height)
    if int(msg.row_step) < int(msg.width) * step:
        return f"row_step {msg.row_step} < width {msg.width} * point_step {step}"
    if n and len(msg.data) < (int(msg.height) - 1) * int(msg.row_step) + int(msg.width) * step:
        return f"data holds {len(msg.data)} bytes, too few for {msg.height}x{msg.width} points"
    return None


def decode_cloud(
    msg, label_field: str | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """PointCloud2 -> (points f4[N,3], labels [N] or None, confidences f4[N] or None). Call check
    first. `label_field=None` reads no labels (labels None), for clouds that carry none."""
    fields = cloud_fields(msg)
    order = ">" if msg.is_bigendian else "<"
    wanted = ["x", "y", "z"] + ([label_field] if label_field is not None else [])
    if "confidence" in fields and fields["confidence"][1] in _FLOAT_TYPES:
        wanted.append("confidence")
    dtype = np.dtype(
        {
            "names": wanted,
            "formats": [order + _FIELD_TYPES[fields[n][1]] for n in wanted],
            "offsets": [fields[n][0] for n in wanted],
            "itemsize": int(msg.point_step),
        }
    )
    h, w, step, row = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    data = np.frombuffer(memoryview(msg.data), np.uint8)
    if h * w == 0:
        labels = None if label_field is None else np.zeros(0, np.uint32)
        return np.zeros((0, 3), np.float32), labels, None
    # Rows may carry padding past width * point_step: cut each row before viewing it as points.
    rows = np.lib.stride_tricks.as_strided(data, (h, w * step), (row, 1))
    pts = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    points = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float32)
    labels = None if label_field is None else pts[label_field].astype(np.int64)
    conf = pts["confidence"].astype(np.float32) if "confidence" in wanted else None
    return points, labels, conf


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0:  # take the short way round
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        th = np.arccos(d)
        q = (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


class PoseTrack:
    """Timestamped poses (position + xyzw quaternion) interpolated at any stamp inside the span."""

    def __init__(self, stamps: np.ndarray, positions: np.ndarray, quats: np.ndarray):
        order = np.argsort(stamps, kind="stable")
        self.stamps, self.positions, self.quats = stamps[order], positions[order], quats[order]

    def at(self, t: float, max_gap_s: float) -> np.ndarray | None:
        s = self.stamps
        if t < s[0] - max_gap_s or t > s[-1] + max_gap_s:
            return None
        k = int(np.searchsorted(s, t))
        if k == 0 or k == s.size:  # just outside the span: hold the end pose
            k = min(k, s.size - 1)
            p, q = self.positions[k], self.quats[k]
        else:
            a = (t - s[k - 1]) / (s[k] - s[k - 1]) if s[k] > s[k - 1] else 0.0
            if s[k] - s[k - 1] > 2 * max_gap_s and min(t - s[k - 1], s[k] - t) > max_gap_s:
                return None  # a hole in the odometry
            p = (1 - a) * self.positions[k - 1] + a * self.positions[k]
            q = _slerp(self.quats[k - 1], self.quats[k], a)
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(q)
        m[:3, 3] = p
        return m
