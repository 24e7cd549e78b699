"""Deterministic Ouster-OS1-64-like labelled scans of a synthetic garden (benchmark, tests).

The world: a smooth height field with slopes (grass, with terrain paths and a terrain ramp),
trees (vertical cylinders), hedges (boxes), topiary and roses (spheres), rocks ('obstacle'
boxes), and a distant ring wall (labelled obstacle) so that every beam returns, as an outdoor
OS1 mostly does within its 120 m range. The sensor rides 0.8 m above the ground along a gently
curving path; each scan is 64 beams x 2048 columns over a 33.2 degree vertical field of view,
with 1 cm range noise, uniform confidences in [0.33, 1] (the paper's protocol) and a few label
flips so that the fusion rules have something to do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE = 1, 2, 4, 5, 6, 7, 8
SENSOR_HEIGHT_M = 0.8
WALL_RADIUS_M = 60.0


@dataclass
class Scan:
    points: np.ndarray  # float32 N x 3, world frame
    labels: np.ndarray  # uint16 N
    confidences: np.ndarray  # float32 N
    origin: np.ndarray  # float64 3, sensor position
    yaw: float


@njit(cache=True)
def _height(x, y):
    h = 0.35 * np.sin(0.13 * x) * np.cos(0.09 * y) + 0.04 * x
    if 20.0 < x < 28.0:  # a ramp: +1.2 m over 8 m
        h += 0.15 * (x - 20.0)
    elif x >= 28.0:
        h += 1.2
    return h


@njit(cache=True)
def _ground_label(x, y):
    path_y = 2.0 * np.sin(0.05 * x)
    if abs(y - path_y) < 1.2 or 20.0 < x < 28.0:
        return TERRAIN
    return GRASS


class _Garden(NamedTuple):
    """The garden's objects as the kernels read them, and the centre of its ring wall."""

    cyl: np.ndarray  # trees: x, y, radius, height
    sph: np.ndarray  # x, y, z, radius, label
    box: np.ndarray  # xmin, ymin, zmin, xmax, ymax, zmax, label
    wall_x: float
    wall_y: float


@njit(cache=True)
def _cast(ox, oy, oz, dx, dy, dz, garden):
    """Distance along the unit ray to the first surface, and its label."""
    cyl, sph, box, cx, cy = garden
    best = 1e30
    label = OBSTACLE
    # ring wall, seen from inside: |(o + t d)_xy - c| = R
    ax = ox - cx
    ay = oy - cy
    a = dx * dx + dy * dy
    if a > 1e-12:
        b = ax * dx + ay * dy
        c = ax * ax + ay * ay - WALL_RADIUS_M * WALL_RADIUS_M
        t = (-b + np.sqrt(b * b - a * c)) / a
        if t > 0:
            best = t
    for k in range(cyl.shape[0]):  # trees: x, y, radius, height
        ex = ox - cyl[k, 0]
        ey = oy - cyl[k, 1]
        if a < 1e-12:
            continue
        b = ex * dx + ey * dy
        c = ex * ex + ey * ey - cyl[k, 2] * cyl[k, 2]
        disc = b * b - a * c
        if disc < 0:
            continue
        t = (-b - np.sqrt(disc)) / a
        if 0 < t < best:
            z = oz + t * dz
            base = _height(cyl[k, 0], cyl[k, 1]) - 0.2
            if base < z < base + cyl[k, 3]:
                best = t
                label = TREE
    for k in range(sph.shape[0]):  # x, y, z, radius, label
        ex = ox - sph[k, 0]
        ey = oy - sph[k, 1]
        ez = oz - sph[k, 2]
        b = ex * dx + ey * dy + ez * dz
        c = ex * ex + ey * ey + ez * ez - sph[k, 3] * sph[k, 3]
        disc = b * b - c
        if disc < 0:
            continue
        t = -b - np.sqrt(disc)
        if 0 < t < best:
            best = t
            label = np.int64(sph[k, 4])
    for k in range(box.shape[0]):  # xmin, ymin, zmin, xmax, ymax, zmax, label (slab test)
        t0 = 0.0
        t1 = best
        o3 = (ox, oy, oz)
        d3 = (dx, dy, dz)
        ok = True
        for j in range(3):
            if abs(d3[j]) < 1e-12:
                if o3[j] < box[k, j] or o3[j] > box[k, j + 3]:
                    ok = False
                    break
            else:
                ta = (box[k, j] - o3[j]) / d3[j]
                tb = (box[k, j + 3] - o3[j]) / d3[j]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
                if t0 > t1:
                    ok = False
                    break
        if ok and 0 < t0 < best:
            best = t0
            label = np.int64(box[k, 6])
    # ground: conservative march (the field's slope stays below 0.5), then bisection
    t = 0.0
    prev = 0.0
    while t < best:
        x = ox + t * dx
        y = oy + t * dy
        gap = oz + t * dz - _height(x, y)
        if gap <= 0:
            lo = prev
            hi = t
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                if oz + mid * dz - _height(ox + mid * dx, oy + mid * dy) > 0:
                    lo = mid
                else:
                    hi = mid
            best = hi
            label = _ground_label(ox + hi * dx, oy + hi * dy)
            break
        prev = t
        t += max(0.02, gap / (1.0 + 0.6 * abs(dz) + 0.6))
        if dz >= 0 and gap > 5.0:
            break
    return best, label


@njit(cache=True)
def _scan(ox, oy, oz, yaw, elev, n_cols, garden, noise):
    n = elev.shape[0] * n_cols
    pts = np.empty((n, 3), np.float32)
    labels = np.empty(n, np.uint16)
    i = 0
    for r in range(elev.shape[0]):
        ce = np.cos(elev[r])
        se = np.sin(elev[r])
        for c in range(n_cols):
            az = yaw + 2.0 * np.pi * c / n_cols
            dx = ce * np.cos(az)
            dy = ce * np.sin(az)
            dz = se
            t, lab = _cast(ox, oy, oz, dx, dy, dz, garden)
            t += noise[i]
            pts[i, 0] = ox + t * dx
            pts[i, 1] = oy + t * dy
            pts[i, 2] = oz + t * dz
            labels[i] = lab
            i += 1
    return pts, labels


class GardenWorld:
    """The synthetic world and the sensor path; `scan(k)` is the k-th scan, always the same."""

    def __init__(self, seed: int = 7, n_beams: int = 64, n_cols: int = 2048, step_m: float = 0.3):
        self.seed, self.n_beams, self.n_cols, self.step_m = seed, n_beams, n_cols, step_m
        rng = np.random.default_rng(seed)
        xs = np.linspace(-15, 60, 40)
        cyl, sph, box = [], [], []
        for x in xs:  # obstacles on both sides of the path, some close to it
            for side in (-1, 1):
                y = 2.0 * np.sin(0.05 * x) + side * rng.uniform(2.5, 9.0)
                kind = rng.integers(0, 5)
                if kind == 0:
                    cyl.append([x, y, rng.uniform(0.15, 0.4), rng.uniform(3.0, 7.0)])
                elif kind == 1:
                    h = 0.0
                    box.append([x, y, h - 0.5, x + rng.uniform(1, 4), y + 0.6, h + 1.6, HEDGE])
                elif kind == 2:
                    r = rng.uniform(0.4, 0.9)
                    sph.append([x, y, _height(x, y) + r * 0.8, r, TOPIARY])
                elif kind == 3:
                    r = rng.uniform(0.2, 0.4)
                    sph.append([x, y, _height(x, y) + r * 0.7, r, ROSE])
                else:
                    s = rng.uniform(0.3, 1.0)
                    z0 = _height(x, y) - 0.3
                    box.append([x, y, z0, x + s, y + s, z0 + s, OBSTACLE])
        self.cyl = np.array(cyl, np.float64).reshape(-1, 4)
        self.sph = np.array(sph, np.float64).reshape(-1, 5)
        self.box = np.array(box, np.float64).reshape(-1, 7)
        self.elev = np.deg2rad(np.linspace(-16.6, 16.6, n_beams))

    def pose(self, k: int) -> tuple[np.ndarray, float]:
        x = k * self.step_m
        y = 2.0 * np.sin(0.05 * x)
        yaw = float(np.arctan(0.1 * np.cos(0.05 * x)))
        return np.array([x, y, _height(x, y) + SENSOR_HEIGHT_M]), yaw

    def scan(self, k: int, label_flip: float = 0.03) -> Scan:
        origin, yaw = self.pose(k)
        rng = np.random.default_rng((self.seed, k))
        n = self.n_beams * self.n_cols
        noise = rng.normal(0.0, 0.01, n)
        pts, labels = _scan(
            origin[0],
            origin[1],
            origin[2],
            yaw,
            self.elev,
            self.n_cols,
            _Garden(self.cyl, self.sph, self.box, 20.0, 0.0),
            noise,
        )
        conf = rng.uniform(0.33, 1.0, n).astype(np.float32)
        flip = rng.random(n) < label_flip
        labels[flip] = rng.choice(np.array([1, 2, 4, 5, 6, 7, 8], np.uint16), int(flip.sum()))
        return Scan(pts, labels, conf, origin, yaw)
