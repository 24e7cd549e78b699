"""A synthetic off-road LiDAR sequence written in the RELLIS-3D layout.

Without a real dataset at hand, the replay benchmark and the reader tests need scans shaped like
RELLIS-3D's: an Ouster OS1-64 (64 beams x 2048 columns = 131,072 points, 33.2 deg vertical field
of view, 10 Hz) on a ground robot driving a dirt trail through grass, trees and bushes, labelled
with RELLIS-3D ids. The world is analytic (a smooth height field, vertical cylinders, spheres and
axis-aligned boxes), so each point's true surface is known and the ray caster can be checked.

Layout written: `<out>/Rellis-3D/00000/{os1_cloud_node_kitti_bin,
os1_cloud_node_semantickitti_label_id}/NNNNNN.{bin,label}`, `poses.txt` (camera frame, as KITTI)
and `calib.txt` (with the LiDAR -> camera `Tr`), plus `synthetic.json` with the parameters.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np
from scipy import ndimage

# RELLIS-3D label ids used by the synthetic world
VOID, DIRT, GRASS, TREE, POLE, WATER, VEHICLE, OBJECT, ASPHALT = 0, 1, 3, 4, 5, 6, 8, 9, 10
BUILDING, LOG, PERSON, FENCE, BUSH, CONCRETE, BARRIER, PUDDLE, MUD, RUBBLE = (
    12,
    15,
    17,
    18,
    19,
    23,
    27,
    31,
    33,
    34,
)

OS1_64_FOV_DEG = (-16.6, 16.6)
WORLD_VERSION = 2  # bump when make_world changes: sequences on disk are then rewritten
SENSOR_HEIGHT_M = 1.0
TERRAIN_MAX_M = 1.0  # bound on |terrain_height|: rays above it going up cannot hit the ground
TERRAIN_MAX_SLOPE = 0.2  # bound on |grad terrain_height| (0.173 from the coefficients below)

# LiDAR -> camera (KITTI convention: camera x right, y down, z forward) with a small offset.
LIDAR_TO_CAMERA = np.array(
    [[0.0, -1.0, 0.0, 0.02], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27], [0, 0, 0, 1.0]]
)


@numba.njit(cache=True)
def terrain_height(x, y):
    """Ground height (m); smooth rolling terrain, |h| <= TERRAIN_MAX_M. Scalars or arrays."""
    return (
        0.55 * np.sin(0.09 * x + 0.4) * np.cos(0.07 * y - 0.2)
        + 0.3 * np.sin(0.05 * x + 0.11 * y)
        + 0.08 * np.sin(0.7 * x) * np.sin(0.6 * y)
    )


def terrain_gradient(x: float, y: float, eps: float = 1e-4) -> tuple[float, float]:
    hx = (terrain_height(x + eps, y) - terrain_height(x - eps, y)) / (2 * eps)
    hy = (terrain_height(x, y + eps) - terrain_height(x, y - eps)) / (2 * eps)
    return float(hx), float(hy)


@dataclass
class SyntheticWorld:
    """Primitives with RELLIS-3D labels, and a raster of ground labels."""

    cylinders: np.ndarray  # f8[C, 5]: cx, cy, r, z0, z1 (vertical, capped at z1)
    cylinder_labels: np.ndarray  # i4[C]
    spheres: np.ndarray  # f8[S, 4]: cx, cy, cz, r
    sphere_labels: np.ndarray
    boxes: np.ndarray  # f8[B, 6]: xmin, ymin, zmin, xmax, ymax, zmax
    box_labels: np.ndarray
    ground_labels: np.ndarray  # u1[H, W], row = y, column = x
    ground_origin: np.ndarray  # f8[2], world xy of cell (0, 0)'s corner
    ground_res_m: float
    trail: np.ndarray  # f8[K, 2], closed polyline the robot drives


def trail_polyline(n: int = 4000) -> np.ndarray:
    """A wobbly closed loop, about 190 m long."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    x = 34 * np.cos(s) + 4 * np.sin(3 * s)
    y = 22 * np.sin(s) + 3 * np.cos(2 * s + 0.5)
    return np.stack([x, y], axis=1)


def make_world(seed: int = 0, extent_m: float = 70.0, res_m: float = 0.1) -> SyntheticWorld:
    """Random objects around the trail (never on it), ground classes in bands and patches."""
    rng = np.random.default_rng(seed)
    trail = trail_polyline()
    n = int(round(2 * extent_m / res_m))
    origin = np.array([-extent_m, -extent_m])
    # Distance to the trail and the trail parameter of the nearest trail cell, from a raster.
    dense = trail_polyline(40000)
    s_dense = np.linspace(0, 1, dense.shape[0], endpoint=False)
    ij = np.floor((dense - origin) / res_m).astype(int)
    mask = np.ones((n, n), bool)
    s_of = np.zeros((n, n))
    mask[ij[:, 1], ij[:, 0]] = False
    s_of[ij[:, 1], ij[:, 0]] = s_dense
    dist, (ni, nj) = ndimage.distance_transform_edt(mask, return_indices=True)
    dist *= res_m
    s_near = s_of[ni, nj]

    ground = np.full((n, n), GRASS, np.uint8)
    on_trail = dist < 1.6
    ground[on_trail] = DIRT
    ground[on_trail & (s_near > 0.05) & (s_near < 0.14)] = ASPHALT
    ground[(dist < 3.0) & (s_near > 0.55) & (s_near < 0.58)] = CONCRETE
    cy, cx = np.mgrid[0:n, 0:n]
    wx, wy = origin[0] + (cx + 0.5) * res_m, origin[1] + (cy + 0.5) * res_m

    def disc(x, y, r, label, where=None):
        m = (wx - x) ** 2 + (wy - y) ** 2 < r * r
        ground[m if where is None else m & where] = label

    for k in rng.choice(trail.shape[0], 10, replace=False):  # puddles on the trail
        disc(*trail[k], rng.uniform(0.5, 1.1), PUDDLE)
    for k in rng.choice(trail.shape[0], 12, replace=False):  # mud at the trail's edges
        off = rng.normal(size=2)
        disc(*(trail[k] + 1.5 * off / np.linalg.norm(off)), rng.uniform(1.0, 2.2), MUD)
    disc(0.0, 0.0, 6.0, WATER)  # a pond inside the loop

    def place(count, clearance, min_r=0.0):
        """Random xy positions at least `clearance` from the trail and outside the pond."""
        out = []
        while len(out) < count:
            p = rng.uniform(-extent_m + 2, extent_m - 2, size=2)
            i, j = np.floor((p - origin) / res_m).astype(int)
            if dist[j, i] > clearance and np.hypot(*p) > 7.0 + min_r:
                out.append(p)
        return np.array(out)

    cyl, cyl_l, sph, sph_l, box, box_l = [], [], [], [], [], []

    def ground_at(p):
        return float(terrain_height(p[0], p[1]))

    for _ in range(160):  # trees: trunk and crown; crowns do not overhang the trail, whose
        # nodes the navigation graph would otherwise label tree (highest voxel wins)
        crown = rng.uniform(1.5, 3.0)
        p = place(1, crown + 2.0)[0]
        h, r = rng.uniform(4, 8), rng.uniform(0.12, 0.3)
        z = ground_at(p)
        cyl.append((p[0], p[1], r, z - 0.3, z + h)), cyl_l.append(TREE)
        sph.append((p[0], p[1], z + h, crown)), sph_l.append(TREE)
    for p in place(220, 2.2):  # bushes
        r = rng.uniform(0.4, 1.1)
        sph.append((p[0], p[1], ground_at(p) + 0.4 * r, r)), sph_l.append(BUSH)
    for p in place(10, 2.5):
        z = ground_at(p)
        cyl.append((p[0], p[1], 0.1, z - 0.3, z + 4.0)), cyl_l.append(POLE)
    for p in place(4, 2.5):
        z = ground_at(p)
        cyl.append((p[0], p[1], 0.25, z - 0.2, z + 1.75)), cyl_l.append(PERSON)
    for p in place(14, 2.5):  # rubble heaps
        for _ in range(5):
            q = p + rng.normal(scale=0.4, size=2)
            sph.append((q[0], q[1], ground_at(q), rng.uniform(0.2, 0.4))), sph_l.append(RUBBLE)

    def add_box(p, size, label):
        z = ground_at(p) - 0.2
        hx, hy = size[0] / 2, size[1] / 2
        box.append((p[0] - hx, p[1] - hy, z, p[0] + hx, p[1] + hy, z + size[2]))
        box_l.append(label)

    for p in place(2, 5.0, 3):
        add_box(p, (4.5, 2.0, 1.8), VEHICLE)
    add_box(place(1, 8.0, 6)[0], (10.0, 8.0, 5.0), BUILDING)
    for p in place(5, 2.5):
        add_box(p, (2.0, 0.4, 1.0) if rng.random() < 0.5 else (0.4, 2.0, 1.0), BARRIER)
    for p in place(10, 2.5):
        add_box(p, (3.0, 0.5, 0.5) if rng.random() < 0.5 else (0.5, 3.0, 0.5), LOG)
    for p in place(8, 2.5):
        add_box(p, (0.6, 0.6, 0.6), OBJECT)
    for x in np.arange(-extent_m + 3, extent_m - 3, 2.5):  # a fence line, gapped at the trail
        i, j = np.floor((np.array([x, 48.0]) - origin) / res_m).astype(int)
        if dist[j, i] > 2.5:
            add_box(np.array([x, 48.0]), (2.4, 0.06, 1.3), FENCE)

    def arr(rows, width):
        return np.asarray(rows, np.float64).reshape(-1, width)

    return SyntheticWorld(
        arr(cyl, 5),
        np.asarray(cyl_l, np.int32),
        arr(sph, 4),
        np.asarray(sph_l, np.int32),
        arr(box, 6),
        np.asarray(box_l, np.int32),
        ground,
        origin,
        res_m,
        trail,
    )


def trajectory_poses(
    world: SyntheticWorld,
    n_scans: int,
    rate_hz: float = 10.0,
    speed_mps: float = 1.5,
    start_m: float = 0.0,
) -> np.ndarray:
    """LiDAR poses (f8[n, 4, 4]) driving the trail; the sensor tilts with the ground."""
    trail = world.trail
    seg = np.diff(np.vstack([trail, trail[:1]]), axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    length = cum[-1]
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    for k in range(n_scans):
        d = (start_m + speed_mps * k / rate_hz) % length
        i = int(np.searchsorted(cum, d, side="right") - 1)
        a = (d - cum[i]) / (cum[i + 1] - cum[i])
        x, y = trail[i] + a * seg[i]
        hx, hy = terrain_gradient(x, y)
        up = np.array([-hx, -hy, 1.0])
        up /= np.linalg.norm(up)
        fwd = np.array([seg[i][0], seg[i][1], 0.0])
        fwd -= up * (fwd @ up)
        fwd /= np.linalg.norm(fwd)
        poses[k, :3, :3] = np.stack([fwd, np.cross(up, fwd), up], axis=1)
        poses[k, :3, 3] = (x, y, terrain_height(x, y) + SENSOR_HEIGHT_M)
    return poses


def beam_directions(beams: int = 64, columns: int = 2048) -> np.ndarray:
    """Unit ray directions in the sensor frame, f8[beams * columns, 3], beam-major order."""
    elev = np.deg2rad(np.linspace(OS1_64_FOV_DEG[1], OS1_64_FOV_DEG[0], beams))
    azim = 2 * np.pi * np.arange(columns) / columns
    e, a = np.meshgrid(elev, azim, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


# -- ray casting ------------------------------------------------------------------------------


@numba.njit(cache=True)
def ray_cylinder(ox, oy, oz, dx, dy, dz, c):
    """The first t > 0 where the ray o + t d meets the upright cylinder c = (cx, cy, r, z0, z1),
    its side or its top; inf when it misses."""
    cx, cy, r, z0, z1 = c[0], c[1], c[2], c[3], c[4]
    best = np.inf
    a = dx * dx + dy * dy
    fx, fy = ox - cx, oy - cy
    if a > 1e-12:
        b = fx * dx + fy * dy
        cc = fx * fx + fy * fy - r * r
        disc = b * b - a * cc
        if disc >= 0:
            sq = math.sqrt(disc)
            for t in ((-b - sq) / a, (-b + sq) / a):
                if t > 1e-6 and z0 <= oz + t * dz <= z1:
                    best = min(best, t)
                    break
    if abs(dz) > 1e-12:  # the top cap
        t = (z1 - oz) / dz
        if 1e-6 < t < best:
            px, py = fx + t * dx, fy + t * dy
            if px * px + py * py <= r * r:
                best = t
    return best


@numba.njit(cache=True)
def _ray_sphere(ox, oy, oz, dx, dy, dz, s):
    fx, fy, fz = ox - s[0], oy - s[1], oz - s[2]
    b = fx * dx + fy * dy + fz * dz
    cc = fx * fx + fy * fy + fz * fz - s[3] * s[3]
    disc = b * b - cc
    if disc < 0:
        return np.inf
    sq = math.sqrt(disc)
    t = -b - sq
    if t > 1e-6:
        return t
    t = -b + sq
    return t if t > 1e-6 else np.inf


@numba.njit(cache=True)
def _ray_box(ox, oy, oz, dx, dy, dz, bx):
    t0, t1 = -np.inf, np.inf
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    for k in range(3):
        lo, hi = bx[k], bx[k + 3]
        if abs(d[k]) < 1e-12:
            if o[k] < lo or o[k] > hi:
                return np.inf
        else:
            ta, tb = (lo - o[k]) / d[k], (hi - o[k]) / d[k]
            if ta > tb:
                ta, tb = tb, ta
            t0, t1 = max(t0, ta), min(t1, tb)
            if t0 > t1:
                return np.inf
    if t0 > 1e-6:
        return t0
    return t1 if t1 > 1e-6 else np.inf


@numba.njit(cache=True)
def ray_ground(ox, oy, oz, dx, dy, dz, t_end):
    """First t where the ray goes below the terrain, or inf.

    Marches with steps that cannot skip the surface (the terrain's slope is at most
    TERRAIN_MAX_SLOPE, so a ray `diff` above it needs diff / (slope * |d_xy| - dz) to reach it),
    never shorter than 2 cm, then refines the last step by regula falsi.
    """
    t = 0.05
    diff = oz + dz * t - terrain_height(ox + dx * t, oy + dy * t)
    if diff <= 0:
        return np.inf  # origin under the ground
    closing = TERRAIN_MAX_SLOPE * math.sqrt(dx * dx + dy * dy) - dz
    while t < t_end:
        if closing <= 0:
            return np.inf  # the ray climbs faster than any slope
        t2 = min(t + max(0.02, diff / closing), t_end)
        diff2 = oz + dz * t2 - terrain_height(ox + dx * t2, oy + dy * t2)
        if diff2 <= 0:
            # Regula falsi on the bracketing step: the terrain is smooth at this scale.
            lo, hi, flo, fhi = t, t2, diff, diff2
            mid = hi
            for _ in range(8):
                mid = lo + (hi - lo) * flo / (flo - fhi)
                fm = oz + dz * mid - terrain_height(ox + dx * mid, oy + dy * mid)
                if abs(fm) < 1e-7:
                    break
                if fm > 0:
                    lo, flo = mid, fm
                else:
                    hi, fhi = mid, fm
            return mid
        if dz >= 0 and oz + dz * t2 > TERRAIN_MAX_M:
            return np.inf
        t, diff = t2, diff2
    return np.inf


@numba.njit(cache=True)
def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


class _Objects(NamedTuple):
    """The world's objects as the ray kernel reads them (`_object_tables`)."""

    cylinders: np.ndarray
    spheres: np.ndarray
    boxes: np.ndarray
    bounds: np.ndarray  # (K, 3): x, y, radius of each object's bounding circle
    kinds: np.ndarray  # (K, 2): 0 cylinder / 1 sphere / 2 box, row in its array
    labels: np.ndarray  # (K,) i4


class _GroundRaster(NamedTuple):
    labels: np.ndarray  # [gy, gx]
    origin: np.ndarray
    res_m: float


@numba.njit(cache=True)
def _cast_rays(origin, dirs, columns, max_range, objects, ground_raster):
    """Nearest hit per ray: (t or inf, label). Rays are beam-major in `columns` columns.

    Objects are culled per column: an object is tested only against columns whose world azimuth
    range overlaps the object's azimuth range seen from the sensor (its bounding circle).
    """
    cyl, sph, box, bounds, kinds, labels_of = objects
    ground, g_origin, g_res = ground_raster
    n = dirs.shape[0]
    beams = n // columns
    ts = np.full(n, np.inf)
    labels = np.zeros(n, np.int32)
    n_obj = bounds.shape[0]
    obj_az = np.empty(n_obj)
    obj_half = np.empty(n_obj)
    obj_ok = np.zeros(n_obj, np.bool_)
    for k in range(n_obj):
        ddx, ddy = bounds[k, 0] - origin[0], bounds[k, 1] - origin[1]
        dist = math.sqrt(ddx * ddx + ddy * ddy)
        rad = bounds[k, 2]
        if dist - rad > max_range:
            continue
        obj_ok[k] = True
        obj_az[k] = math.atan2(ddy, ddx)
        obj_half[k] = np.pi if dist <= rad + 1e-3 else math.asin(min(1.0, rad / dist))
    cand = np.empty(n_obj, np.int64)
    h, w = ground.shape
    for c in range(columns):
        # The column's azimuth span over its beams (the sensor may be tilted).
        az0 = math.atan2(dirs[c, 1], dirs[c, 0])
        lo, hi = 0.0, 0.0
        for b in range(beams):
            i = b * columns + c
            dev = _wrap(math.atan2(dirs[i, 1], dirs[i, 0]) - az0)
            lo, hi = min(lo, dev), max(hi, dev)
        centre, half = _wrap(az0 + 0.5 * (lo + hi)), 0.5 * (hi - lo) + 1e-6
        nc = 0
        for k in range(n_obj):
            if obj_ok[k] and abs(_wrap(obj_az[k] - centre)) <= obj_half[k] + half:
                cand[nc] = k
                nc += 1
        for b in range(beams):
            i = b * columns + c
            dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
            best, lab = max_range, -1
            for m in range(nc):
                k = cand[m]
                kind, j = kinds[k, 0], kinds[k, 1]
                if kind == 0:
                    t = ray_cylinder(origin[0], origin[1], origin[2], dx, dy, dz, cyl[j])
                elif kind == 1:
                    t = _ray_sphere(origin[0], origin[1], origin[2], dx, dy, dz, sph[j])
                else:
                    t = _ray_box(origin[0], origin[1], origin[2], dx, dy, dz, box[j])
                if t < best:
                    best, lab = t, labels_of[k]
            tg = ray_ground(origin[0], origin[1], origin[2], dx, dy, dz, best)
            if tg < best:
                best = tg
                gx = int(math.floor((origin[0] + dx * tg - g_origin[0]) / g_res))
                gy = int(math.floor((origin[1] + dy * tg - g_origin[1]) / g_res))
                lab = ground[gy, gx] if 0 <= gx < w and 0 <= gy < h else GRASS
            if lab >= 0:
                ts[i] = best
                labels[i] = lab
    return ts, labels


def _object_tables(world: SyntheticWorld):
    """Flat per-object arrays for the kernel: kind/index, label and xy bounding circle."""
    c, s, b = world.cylinders, world.spheres, world.boxes
    kinds = np.concatenate(
        [
            np.stack([np.zeros(len(c)), np.arange(len(c))], 1),
            np.stack([np.ones(len(s)), np.arange(len(s))], 1),
            np.stack([np.full(len(b), 2), np.arange(len(b))], 1),
        ]
    ).astype(np.int64)
    half = 0.5 * (b[:, 3:5] - b[:, 0:2])
    bounds = np.concatenate(
        [
            c[:, [0, 1, 2]],
            s[:, [0, 1, 3]],
            np.column_stack(
                [0.5 * (b[:, 0] + b[:, 3]), 0.5 * (b[:, 1] + b[:, 4]), np.linalg.norm(half, axis=1)]
            ),
        ]
    )
    labels = np.concatenate([world.cylinder_labels, world.sphere_labels, world.box_labels])
    return kinds, bounds, labels.astype(np.int32)


def cast_rays(
    world: SyntheticWorld,
    origin: np.ndarray,
    dirs: np.ndarray,
    columns: int,
    max_range_m: float = 100.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the first surface along each world-frame ray (inf: none) and its label."""
    origin = np.asarray(origin, np.float64)
    dirs = np.ascontiguousarray(dirs, np.float64)
    if origin.shape != (3,) or dirs.ndim != 2 or dirs.shape[1] != 3:
        raise ValueError("origin must be (3,) and dirs (N, 3)")
    if columns <= 0 or dirs.shape[0] % columns:
        raise ValueError(f"{dirs.shape[0]} rays do not fill {columns} columns")
    if not np.allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6):
        raise ValueError("ray directions must be unit vectors")
    kinds, bounds, labels = _object_tables(world)
    return _cast_rays(
        origin,
        dirs,
        columns,
        float(max_range_m),
        _Objects(world.cylinders, world.spheres, world.boxes, bounds, kinds, labels),
        _GroundRaster(world.ground_labels, world.ground_origin, world.ground_res_m),
    )


def simulate_scan(
    world: SyntheticWorld,
    pose: np.ndarray,
    beams: int = 64,
    columns: int = 2048,
    max_range_m: float = 100.0,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One OS1-like scan: points f4[beams*columns, 3] in the sensor frame, RELLIS-3D labels
    u4[...] and remission f4[...]. Rays without a return are (0, 0, 0) with label void, as in
    the dataset's files."""
    d_sensor = beam_directions(beams, columns)
    d_world = d_sensor @ pose[:3, :3].T
    t, lab = cast_rays(world, pose[:3, 3], d_world, columns, max_range_m)
    hit = np.isfinite(t)
    if noise_m > 0:
        rng = rng or np.random.default_rng(0)
        t = np.where(hit, t + rng.normal(scale=noise_m, size=t.shape), t)
    pts = np.zeros((t.size, 3), np.float32)
    pts[hit] = (d_sensor[hit] * t[hit, None]).astype(np.float32)
    labels = np.where(hit, lab, VOID).astype(np.uint32)
    remission = np.where(hit, 0.2 + 0.6 * ((labels * 37) % 11) / 10.0, 0.0).astype(np.float32)
    return pts, labels, remission


# -- writing ----------------------------------------------------------------------------------


@dataclass
class SyntheticConfig:
    """A synthetic sequence: how many scans, the LiDAR's beams and columns, the motion, noise."""

    n_scans: int = 100
    beams: int = 64
    columns: int = 2048
    rate_hz: float = 10.0
    speed_mps: float = 1.5
    seed: int = 0
    max_range_m: float = 100.0
    noise_m: float = 0.01


def _fmt_row(m: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in m[:3, :4].reshape(-1))


def write_rellis_sequence(
    out_dir: str | Path, params: SyntheticConfig | None = None, progress=None
) -> Path:
    """Write a synthetic sequence; returns the sequence folder (`.../Rellis-3D/00000`).

    An existing sequence with the same parameters is reused (its `synthetic.json` matches).
    """
    params = params or SyntheticConfig()
    if params.n_scans < 1 or params.beams < 2 or params.columns < 4:
        raise ValueError("need n_scans >= 1, beams >= 2, columns >= 4")
    seq = Path(out_dir) / "Rellis-3D" / "00000"
    manifest = seq / "synthetic.json"
    wanted = {**asdict(params), "world_version": WORLD_VERSION}
    if manifest.is_file() and json.loads(manifest.read_text()) == wanted:
        return seq
    bins, labs = seq / "os1_cloud_node_kitti_bin", seq / "os1_cloud_node_semantickitti_label_id"
    for d in (bins, labs):
        d.mkdir(parents=True, exist_ok=True)
        for f in d.iterdir():
            f.unlink()
    manifest.unlink(missing_ok=True)
    world = make_world(params.seed)
    poses = trajectory_poses(world, params.n_scans, params.rate_hz, params.speed_mps)
    rng = np.random.default_rng(params.seed + 1)
    for k, pose in enumerate(poses):
        pts, labels, rem = simulate_scan(
            world, pose, params.beams, params.columns, params.max_range_m, params.noise_m, rng
        )
        np.column_stack([pts, rem]).astype(np.float32).tofile(bins / f"{k:06d}.bin")
        labels.astype(np.uint32).tofile(labs / f"{k:06d}.label")
        if progress is not None:
            progress(k + 1, params.n_scans)
    # KITTI stores camera poses: P = Tr @ pose_lidar @ inv(Tr), undone by the reader.
    tr = LIDAR_TO_CAMERA
    cam = tr @ poses @ np.linalg.inv(tr)
    (seq / "poses.txt").write_text("".join(_fmt_row(p) + "\n" for p in cam))
    proj = np.array([[500.0, 0, 320, 0], [0, 500, 240, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    lines = [f"P{i}: {_fmt_row(proj)}" for i in range(4)] + [f"Tr: {_fmt_row(tr)}"]
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    manifest.write_text(json.dumps(wanted, indent=1))
    return seq
