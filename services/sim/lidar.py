"""A spinning LiDAR shaped like an Ouster OS1-64, from PyBullet ray casts.

Rays go out on `channels` elevations spread evenly over `vfov_deg` (centred on the horizon) and
`columns` azimuths over a full turn; each hit takes its body's class (the ground's from the
raster at the hit). Rays start at `min_range_m` (a real sensor's blind zone) and end at
`max_range_m`; rays that hit nothing give no point.

The rays are defined once in the robot's base frame and cast with `parentObjectUniqueId`, so
each scan hands PyBullet the same prebuilt Python lists: converting 131,072 rays from numpy to
lists costs more than Bullet's own casting on 2 threads.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pybullet as p

from .scene import BulletScene, transform_points

BATCH = getattr(p, "MAX_RAY_INTERSECTION_BATCH_SIZE", 16384)


@dataclass(frozen=True)
class LidarSpec:
    channels: int = 64
    columns: int = 2048
    vfov_deg: float = 33.2
    max_range_m: float = 20.0
    min_range_m: float = 0.3
    mount_xyz: tuple[float, float, float] = (0.0, 0.0, 0.30)  # on the base frame, level

    def validate(self) -> None:
        if self.channels < 1 or self.columns < 1 or self.channels * self.columns > 4_000_000:
            raise ValueError("lidar needs 1..4M rays")
        if not 0 <= self.vfov_deg < 180:
            raise ValueError(f"lidar vfov_deg must be within 0..180, got {self.vfov_deg}")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError("lidar needs 0 <= min_range_m < max_range_m")

    @property
    def n_rays(self) -> int:
        return self.channels * self.columns

    def directions(self) -> np.ndarray:
        """Unit ray directions (channels * columns, 3) in the sensor frame, channel-major: top
        channel first, azimuth from -pi (behind) counter-clockwise."""
        half = math.radians(self.vfov_deg) / 2
        el = np.linspace(half, -half, self.channels) if self.channels > 1 else np.zeros(1)
        az = -math.pi + np.arange(self.columns) * (2 * math.pi / self.columns)
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(
            -1, 3
        )

    def mount_matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, 3] = self.mount_xyz
        return m


@dataclass
class LidarHits:
    """One scan: points in the sensor frame, their labels and ray indices (hits only)."""

    points_sensor: np.ndarray  # f4[N, 3]
    labels: np.ndarray  # i8[N]
    ray_index: np.ndarray  # i8[N] index into LidarSpec.directions()
    world_from_sensor: np.ndarray  # 4x4 true sensor pose at the scan

    @property
    def points_world(self) -> np.ndarray:
        return transform_points(self.points_sensor, self.world_from_sensor)


class Lidar:
    def __init__(self, scene: BulletScene, spec: LidarSpec | None = None, parent_body: int = -1):
        """`parent_body`: the robot's body id; rays then follow its base frame. With -1 the rays
        are in the world frame and `scan` needs the sensor pose."""
        self.scene = scene
        self.spec = spec or LidarSpec()
        self.spec.validate()
        self.parent = parent_body
        self.dirs = self.spec.directions()
        mount = np.array(self.spec.mount_xyz)
        self._from = mount + self.dirs * self.spec.min_range_m  # parent frame
        self._to = mount + self.dirs * self.spec.max_range_m
        self._chunks = None
        if parent_body >= 0:
            self._chunks = [
                (self._from[s : s + BATCH].tolist(), self._to[s : s + BATCH].tolist())
                for s in range(0, len(self.dirs), BATCH)
            ]

    def scan(self, world_from_base: np.ndarray, timings: dict | None = None) -> LidarHits:
        """Cast every ray. `world_from_base` is the parent body's true pose (or, without a
        parent, the pose of the frame the mount is given in)."""
        c = self.scene.client
        t0 = time.perf_counter()
        out = []
        if self._chunks is not None:
            for a, b in self._chunks:
                out += p.rayTestBatch(
                    a,
                    b,
                    numThreads=0,
                    parentObjectUniqueId=self.parent,
                    parentLinkIndex=-1,
                    physicsClientId=c,
                )
        else:
            wf = transform_points(self._from, world_from_base)
            wt = transform_points(self._to, world_from_base)
            for s in range(0, len(wf), BATCH):
                out += p.rayTestBatch(
                    wf[s : s + BATCH].tolist(),
                    wt[s : s + BATCH].tolist(),
                    numThreads=0,
                    physicsClientId=c,
                )
        t1 = time.perf_counter()
        n = len(out)
        bodies = np.fromiter((h[0] for h in out), np.int64, n)
        frac = np.fromiter((h[2] for h in out), np.float64, n)
        hit = np.flatnonzero(bodies >= 0)
        spec = self.spec
        dist = spec.min_range_m + frac[hit] * (spec.max_range_m - spec.min_range_m)
        pts_sensor = self.dirs[hit] * dist[:, None]
        world_from_sensor = world_from_base @ spec.mount_matrix()
        world = transform_points(pts_sensor, world_from_sensor)
        labels = self.scene.labels_of(bodies[hit], world[:, :2])
        keep = labels >= 0  # drop hits on the robot itself
        if timings is not None:
            timings["cast_ms"] = 1e3 * (t1 - t0)
            timings["hits_ms"] = 1e3 * (time.perf_counter() - t1)
        return LidarHits(
            pts_sensor[keep].astype(np.float32), labels[keep], hit[keep], world_from_sensor
        )
