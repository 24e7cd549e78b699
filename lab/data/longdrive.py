"""A long synthetic drive through a large procedural outdoor world, for `smana bench scale`.

The world is analytic and unbounded, so 10 km of scans need no stored raster and no renderer:

- the ground is `synthetic.terrain_height` (smooth rolling terrain, |h| <= 1 m, slope <= 0.2),
  labelled dirt on the trail and grass elsewhere;
- obstacles are trees and bushes (vertical capped cylinders), at most one per square cell of
  `cell_m`, placed by a hash of the cell's indices and the seed, and kept wholly inside their
  cell so a ray finds the nearest one by walking the cells it crosses (a 2D DDA);
- the robot drives a lawnmower over a square of `side_m` (lanes along x, `lane_spacing_m`
  apart, joined at the ends); no obstacle stands within `clearance_m` of a lane or of a joining
  line, so the drive and a planner's start and goal are always free.

Scans are OS1-64-like: 64 beams x 2048 columns (131,072 rays) over 33.2 deg, the sensor
`synthetic.SENSOR_HEIGHT_M` above the ground and level, heading along the drive, 10 Hz at
`speed_mps`. Points come out in the world frame (what the mapper's core takes), rays without a
return are left out.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np

from smana.lab.data.synthetic import (
    BUSH,
    DIRT,
    GRASS,
    SENSOR_HEIGHT_M,
    TREE,
    beam_directions,
    ray_cylinder,
    ray_ground,
    terrain_height,
)


@dataclass(frozen=True)
class DriveWorld:
    """The procedural world and the lawnmower the robot drives in it."""

    seed: int = 0
    side_m: float = 1000.0  # the square the lawnmower covers (1 km^2 by default)
    lane_spacing_m: float = 40.0
    cell_m: float = 6.0  # one obstacle at most per cell of this side
    density: float = 0.35  # probability that a cell holds an obstacle
    clearance_m: float = 3.0  # no obstacle within this of the trail
    trail_half_width_m: float = 1.5  # ground labelled dirt within this of the trail

    def __post_init__(self):
        if not (self.side_m > 0 and self.lane_spacing_m > 0 and self.cell_m > 0):
            raise ValueError("side_m, lane_spacing_m and cell_m must be > 0")
        if not 0 <= self.density <= 1:
            raise ValueError(f"density must be in [0, 1], got {self.density}")
        if self.clearance_m < 0 or self.trail_half_width_m < 0:
            raise ValueError("clearance_m and trail_half_width_m must be >= 0")

    @property
    def params(self) -> np.ndarray:
        """The world as the kernels read it (f8[8])."""
        return np.array(
            [
                self.seed,
                self.side_m,
                self.lane_spacing_m,
                self.cell_m,
                self.density,
                self.clearance_m,
                self.trail_half_width_m,
                self.n_lanes,
            ],
            np.float64,
        )

    @property
    def n_lanes(self) -> int:
        return int(self.side_m // self.lane_spacing_m) + 1

    @property
    def lap_m(self) -> float:
        """Length of one full lawnmower (lanes and the joins between them)."""
        return self.n_lanes * self.side_m + (self.n_lanes - 1) * self.lane_spacing_m

    def position(self, d_m: float) -> tuple[float, float, float]:
        """(x, y, heading) after driving `d_m` metres; past the end it drives back."""
        lap = self.lap_m
        d = d_m % (2 * lap)
        back = d > lap
        if back:
            d = 2 * lap - d
        half = 0.5 * self.side_m
        leg = self.side_m + self.lane_spacing_m
        k = min(int(d // leg), self.n_lanes - 1)
        s = d - k * leg
        y0 = -half + k * self.lane_spacing_m
        east = k % 2 == 0
        if s <= self.side_m:
            x, y = (-half + s, y0) if east else (half - s, y0)
            heading = 0.0 if east else math.pi
        else:  # the join up to the next lane
            x, y = (half if east else -half), y0 + (s - self.side_m)
            heading = 0.5 * math.pi
        if back:
            heading += math.pi
        return x, y, heading


@numba.njit(cache=True)
def _hash01(i, j, seed, k):
    """A deterministic pseudo-random number in [0, 1) from integers (splitmix64's finaliser)."""
    z = np.uint64(i * 73856093 + 0x9E3779B9) ^ np.uint64(j * 19349663 + 0x85EBCA6B)
    z = z ^ np.uint64(seed * 83492791 + k * 2654435761)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) / 9007199254740992.0


@numba.njit(cache=True)
def _trail_distance(x, y, w):
    """Distance from (x, y) to the lawnmower's lines (lanes and end joins, taken whole)."""
    side, spacing, n_lanes = w[1], w[2], w[7]
    half = 0.5 * side
    k = math.floor((y + half) / spacing + 0.5)
    k = min(max(k, 0.0), n_lanes - 1)
    d = abs(y - (-half + k * spacing))
    if x < -half or x > half:
        d = max(d, min(abs(x + half), abs(x - half)))  # off the lanes' ends
    y_top = -half + (n_lanes - 1) * spacing
    if -half <= y <= y_top:
        d = min(d, abs(x + half), abs(x - half))
    return d


@numba.njit(cache=True)
def _cell_obstacle(i, j, w, out):
    """The obstacle of cell (i, j) into out (cx, cy, r, z0, z1, label); False when none."""
    seed, cell, density, clearance = int(w[0]), w[3], w[4], w[5]
    if _hash01(i, j, seed, 0) >= density:
        return False
    bush = _hash01(i, j, seed, 1) < 0.4
    r = 0.3 + 0.5 * _hash01(i, j, seed, 2) if bush else 0.15 + 0.35 * _hash01(i, j, seed, 2)
    free = cell - 2 * r  # the whole disc stays inside the cell
    cx = i * cell + r + free * _hash01(i, j, seed, 3)
    cy = j * cell + r + free * _hash01(i, j, seed, 4)
    if _trail_distance(cx, cy, w) < clearance + r:
        return False
    ground = terrain_height(cx, cy)
    height = 0.5 + 0.8 * _hash01(i, j, seed, 5) if bush else 3.0 + 9.0 * _hash01(i, j, seed, 5)
    out[0], out[1], out[2], out[3], out[4] = cx, cy, r, ground - 1.0, ground + height
    out[5] = BUSH if bush else TREE
    return True


@numba.njit(cache=True)
def _ground_label(x, y, w):
    return DIRT if _trail_distance(x, y, w) <= w[6] else GRASS


@numba.njit(cache=True)
def _cast_one(origin, dx, dy, dz, max_range, w, obs):
    """Nearest hit of one world-frame unit ray from `origin`: (t, label), label -1 for none."""
    ox, oy, oz = origin[0], origin[1], origin[2]
    cell = w[3]
    best, lab = max_range, -1
    # Walk the obstacle cells the ray's xy crosses, nearest first: an obstacle lies wholly
    # in its cell, so the first cell with a hit holds the nearest one.
    i, j = int(math.floor(ox / cell)), int(math.floor(oy / cell))
    step_i = 1 if dx > 0 else -1
    step_j = 1 if dy > 0 else -1
    t_di = cell / abs(dx) if abs(dx) > 1e-12 else np.inf
    t_dj = cell / abs(dy) if abs(dy) > 1e-12 else np.inf
    nx = (i + (1 if dx > 0 else 0)) * cell
    ny = (j + (1 if dy > 0 else 0)) * cell
    t_i = (nx - ox) / dx if abs(dx) > 1e-12 else np.inf
    t_j = (ny - oy) / dy if abs(dy) > 1e-12 else np.inf
    t_cell = 0.0
    while t_cell < best:
        if _cell_obstacle(i, j, w, obs):
            t = ray_cylinder(ox, oy, oz, dx, dy, dz, obs)
            if t < best:
                best, lab = t, int(obs[5])
                break
        if t_i < t_j:
            t_cell, t_i, i = t_i, t_i + t_di, i + step_i
        else:
            t_cell, t_j, j = t_j, t_j + t_dj, j + step_j
    tg = ray_ground(ox, oy, oz, dx, dy, dz, best)
    if tg < best:
        best, lab = tg, _ground_label(ox + dx * tg, oy + dy * tg, w)
    return best, lab


CAST_TASKS = 64  # parallel tasks; each ray's result depends on that ray alone


@numba.njit(cache=True, parallel=True)
def _cast(origin, dirs, max_range, w):
    """Nearest hit per world-frame unit ray: (t or inf, label), over every core."""
    n = dirs.shape[0]
    ts = np.full(n, np.inf)
    labels = np.zeros(n, np.int32)
    # Task c takes every CAST_TASKS-th ray from c: a scan's rays come beam by beam, and a beam
    # looking up costs many times one looking down, so contiguous blocks would load one core.
    for c in numba.prange(CAST_TASKS):
        obs = np.empty(6)  # one scratch obstacle per task
        for r in range(c, n, CAST_TASKS):
            best, lab = _cast_one(origin, dirs[r, 0], dirs[r, 1], dirs[r, 2], max_range, w, obs)
            if lab >= 0:
                ts[r] = best
                labels[r] = lab
    return ts, labels


def sensor_origin(world: DriveWorld, d_m: float) -> tuple[np.ndarray, float]:
    x, y, heading = world.position(d_m)
    return np.array([x, y, float(terrain_height(x, y)) + SENSOR_HEIGHT_M]), heading


@functools.lru_cache(maxsize=4)
def _sensor_rays(beams: int, columns: int) -> np.ndarray:
    d = beam_directions(beams, columns)
    d.flags.writeable = False  # shared by every scan
    return d


def world_rays(heading: float, beams: int = 64, columns: int = 2048) -> np.ndarray:
    """The sensor's unit rays rotated to `heading` (level sensor), f8[beams * columns, 3]."""
    d = _sensor_rays(int(beams), int(columns))
    c, s = math.cos(heading), math.sin(heading)
    return np.ascontiguousarray(
        np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]])
    )


def cast_rays(world: DriveWorld, origin, dirs, max_range_m: float = 60.0):
    """Distance to the first surface along each world-frame unit ray (inf: none) and its label
    (RELLIS-3D ids)."""
    origin = np.asarray(origin, np.float64)
    dirs = np.ascontiguousarray(dirs, np.float64)
    if origin.shape != (3,) or dirs.ndim != 2 or dirs.shape[1] != 3:
        raise ValueError("origin must be (3,) and dirs (N, 3)")
    if not (np.isfinite(max_range_m) and max_range_m > 0):
        raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
    return _cast(origin, dirs, float(max_range_m), world.params)


class Drive:
    """Scans along the lawnmower at `rate_hz`, `speed_mps`: `scan(k)` is the k-th one."""

    def __init__(
        self,
        world: DriveWorld | None = None,
        speed_mps: float = 1.5,
        rate_hz: float = 10.0,
        beams: int = 64,
        columns: int = 2048,
        max_range_m: float = 30.0,
    ):
        if not (speed_mps > 0 and rate_hz > 0 and beams > 0 and columns > 0):
            raise ValueError("speed_mps, rate_hz, beams and columns must be > 0")
        self.world = DriveWorld() if world is None else world
        self.speed_mps, self.rate_hz = float(speed_mps), float(rate_hz)
        self.beams, self.columns, self.max_range_m = int(beams), int(columns), float(max_range_m)

    def n_scans(self, km: float) -> int:
        return max(1, int(round(km * 1000.0 / self.speed_mps * self.rate_hz)))

    def distance_m(self, k: int) -> float:
        return self.speed_mps * k / self.rate_hz

    def scan(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-frame points f4[N, 3], RELLIS-3D labels u2[N] and the sensor origin f8[3]."""
        origin, heading = sensor_origin(self.world, self.distance_m(k))
        dirs = world_rays(heading, self.beams, self.columns)
        t, lab = cast_rays(self.world, origin, dirs, self.max_range_m)
        hit = np.isfinite(t)
        pts = (origin + dirs[hit] * t[hit, None]).astype(np.float32)
        return pts, lab[hit].astype(np.uint16), origin
