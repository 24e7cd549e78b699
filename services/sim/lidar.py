"""A spinning LiDAR shaped like an Ouster OS1-64, from PyBullet ray casts.

Parameters: `[sim.lidar]` (`LidarConfig`). Rays go out on `channels` elevations spread evenly
over `vfov_deg` (centred on the horizon) and `columns` azimuths over a full turn; each hit takes
its body's class (the ground's from the raster at the hit). Rays start at the config's `starts()`
(`min_range_m`: a real sensor's blind zone; the safety scanner's low beams start clear of the
robot's body) and end at `max_range_m`; rays that hit nothing give no point.

The rays are defined once in the robot's base frame and cast with `parentObjectUniqueId`, so
each scan hands PyBullet the same prebuilt Python lists: converting 131,072 rays from numpy to
lists costs more than Bullet's own casting on 2 threads.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pybullet as p

from smana.common.config.sim import LidarConfig
from smana.common.messages import SemanticCloud

from .scene import BulletScene, transform_points

BATCH = getattr(p, "MAX_RAY_INTERSECTION_BATCH_SIZE", 16384)


@dataclass
class LidarHits:
    """One scan: points in the sensor frame, their labels and ray indices (hits only)."""

    points_sensor: np.ndarray  # f4[N, 3]
    labels: np.ndarray  # i8[N]
    ray_index: np.ndarray  # i8[N] index into LidarConfig.directions()
    world_from_sensor: np.ndarray  # 4x4 true sensor pose at the scan
    member_hits: int = 0  # hits on the bodies `scan` was asked to count (other robots)

    @property
    def points_world(self) -> np.ndarray:
        return transform_points(self.points_sensor, self.world_from_sensor)


class Lidar:
    def __init__(
        self, scene: BulletScene, config: LidarConfig | None = None, parent_body: int = -1
    ):
        """`parent_body`: the robot's body id; rays then follow its base frame. With -1 the rays
        are in the world frame and `scan` needs the sensor pose."""
        self.scene = scene
        self.config = config or LidarConfig()
        self.parent = parent_body
        self.dirs = self.config.directions()
        mount = np.array(self.config.mount_xyz)
        self.starts = self.config.starts()  # m along each ray
        self._from = mount + self.dirs * self.starts[:, None]  # parent frame
        self._to = mount + self.dirs * self.config.max_range_m
        self._chunks = None
        if parent_body >= 0:
            self._chunks = [
                (self._from[s : s + BATCH].tolist(), self._to[s : s + BATCH].tolist())
                for s in range(0, len(self.dirs), BATCH)
            ]

    def scan(
        self,
        world_from_base: np.ndarray,
        timings: dict | None = None,
        count_bodies: np.ndarray | None = None,
    ) -> LidarHits:
        """Cast every ray. `world_from_base` is the parent body's true pose (or, without a
        parent, the pose of the frame the mount is given in). With `count_bodies`, the hits on
        those bodies are counted (`member_hits`)."""
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
        cfg = self.config
        start = self.starts[hit]
        dist = start + frac[hit] * (cfg.max_range_m - start)
        pts_sensor = self.dirs[hit] * dist[:, None]
        world_from_sensor = world_from_base @ cfg.mount_matrix()
        world = transform_points(pts_sensor, world_from_sensor)
        labels = self.scene.labels_of(bodies[hit], world[:, :2])
        keep = labels >= 0  # drop hits on the robot itself (and on other robots)
        member_hits = 0
        if count_bodies is not None and len(count_bodies):
            member_hits = int(np.isin(bodies[hit], count_bodies).sum())
        if timings is not None:
            timings["cast_ms"] = 1e3 * (t1 - t0)
            timings["hits_ms"] = 1e3 * (time.perf_counter() - t1)
        return LidarHits(
            pts_sensor[keep].astype(np.float32),
            labels[keep],
            hit[keep],
            world_from_sensor,
            member_hits,
        )


def safety_cloud(
    scanner: Lidar, world_from_base: np.ndarray, stamp_s: float, seq: int
) -> SemanticCloud:
    """A safety scanner's scan as robot/safety_scan carries it: its hits in the robot's base
    frame (`frame_id` "base_link"), where no pose noise reaches them; unlabelled (class 0,
    confidence 0). Hits on the robot itself and on other members are dropped."""
    hits = scanner.scan(world_from_base)
    base = transform_points(hits.points_sensor, scanner.config.mount_matrix()).astype(np.float32)
    n = len(base)
    return SemanticCloud(
        stamp_s=stamp_s,
        seq=seq,
        points=base,
        labels=np.zeros(n, np.uint16),
        confidences=np.zeros(n, np.float32),
        sensor_position=np.asarray(scanner.config.mount_xyz, np.float64),
        frame_id="base_link",
        source="safety_scan",
    )
