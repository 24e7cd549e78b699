"""A ROS 2 robot's safety scanner -> `robot/safety_scan`, for the explorer's guard.

`ros2.safety_scan_topic` (a sensor_msgs/msg/LaserScan, "" = none) is read when the service takes
a real robot's topics (`ros2.robot_input`). Each scan's valid ranges become points in the
scanner's frame, then in the robot's base frame through the robot's static transforms (or
`ros2.sensor_extrinsic`, as for its clouds: `bridge.CloudInput.sensor_on_robot`), and go out as a
`SemanticCloud` in "base_link", unlabelled, as the simulator's safety scanner sends them
(services/explorer/guard.py reads them). A scan that cannot be placed or read is a `Reject`
whose kind says why; the service goes on.
"""

from __future__ import annotations

import math

import numpy as np

from smana.common import keys
from smana.common.messages import SemanticCloud, matrix_to_quat
from smana.common.plausibility import StampGate
from smana.common.service import Reject

from . import convert
from .bridge import plausible_stamp

LASER = "sensor_msgs/msg/LaserScan"
MAX_BEAMS = 100_000  # more beams in one scan than any scanner sends: refused


def scan_points(msg) -> np.ndarray:
    """The scan's valid returns (N, 3) in its own frame (z = 0): finite ranges within
    [range_min, range_max]. Reject for a scan that cannot be read."""
    r = np.asarray(msg.ranges, np.float64)
    if len(r) > MAX_BEAMS:
        raise Reject("oversize", f"LaserScan of {len(r)} beams (at most {MAX_BEAMS})")
    a0, da = float(msg.angle_min), float(msg.angle_increment)
    lo, hi = float(msg.range_min), float(msg.range_max)
    if not all(math.isfinite(v) for v in (a0, da, lo, hi)) or (len(r) > 1 and da == 0.0):
        raise Reject("value", "LaserScan with a non-finite angle or range limit, or no increment")
    a = a0 + da * np.arange(len(r))
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= lo) & (r <= hi)
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok]), np.zeros(ok.sum())])


class SafetyScanInput:
    """LaserScans of one robot, placed on it (`CloudInput`'s static transforms) and sent on."""

    def __init__(self, service, cloud_input):
        self.service = service
        self.cloud_input = cloud_input
        general = service.config.general
        self.stamps = StampGate(general.stamp_window_s, general.max_time_rate)
        self.seq = 0
        self.warned = False

    def convert(self, msg) -> SemanticCloud:
        t = convert.stamp_s(msg.header)
        plausible_stamp(self.stamps, t, f"LaserScan at {t:.3f} s")
        frame = msg.header.frame_id.lstrip("/")
        on_robot = self.cloud_input.sensor_on_robot(frame)
        if on_robot is None:
            raise Reject(
                "no_transform",
                f"LaserScan in frame {frame!r}: no static transform from the robot's base and "
                "no ros2.sensor_extrinsic",
            )
        pts = scan_points(msg)
        base = (pts @ on_robot[:3, :3].T + on_robot[:3, 3]).astype(np.float32)
        self._check_heights(base)
        self.seq += 1
        n = len(base)
        return SemanticCloud(
            stamp_s=t,
            seq=self.seq,
            points=base,
            labels=np.zeros(n, np.uint16),
            confidences=np.zeros(n, np.float32),
            sensor_position=on_robot[:3, 3].astype(np.float64),
            sensor_orientation_xyzw=matrix_to_quat(on_robot[:3, :3]),
            frame_id="base_link",
            source="safety_scan",
        )

    def _check_heights(self, base: np.ndarray) -> None:
        """Say once when the scan's points lie outside the heights the guard counts."""
        guard = self.service.config.explorer.guard
        if self.warned or not len(base):
            return
        z = float(np.median(base[:, 2]))
        if not guard.z_min_m <= z <= guard.z_max_m:
            self.warned = True
            self.service.log.warning(
                "the safety scan's points lie %.2f m above the base frame, outside what the "
                "explorer's guard counts (explorer.guard.z_min_m %.2f .. z_max_m %.2f): set them "
                "to take this scanner in",
                z,
                guard.z_min_m,
                guard.z_max_m,
            )


def wire(service, node, robot: str, qos, read) -> None:
    """Subscribe the service to `ros2.safety_scan_topic` and publish on `robot/safety_scan`;
    `read(payload, typename)` deserialises a ROS 2 message (a Reject when it is not one)."""
    from .rmw import SUBSCRIPTION

    scans = SafetyScanInput(service, service.cloud_input)
    pub = service.publisher(keys.safety_scan(robot))
    key, _ = node.endpoint(SUBSCRIPTION, service.config.ros2.safety_scan_topic, LASER, qos)

    def on_scan(payload: bytes) -> None:
        pub.put(scans.convert(read(payload, LASER)))

    service.subscribe(key, on_scan)
