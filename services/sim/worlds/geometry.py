"""Solid primitives (box, sphere, cylinder, ellipsoid) that procedural worlds are made of: their
footprint and top surface seen from above, inside tests, and points sampled on their surface.
Frames follow REP-103: metres, z up, `yaw` about z."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .base import WorldError

BOX, SPHERE, CYLINDER, ELLIPSOID = "box", "sphere", "cylinder", "ellipsoid"
SHAPES = (BOX, SPHERE, CYLINDER, ELLIPSOID)


@dataclass(frozen=True)
class Primitive:
    """A solid: box (half extents), sphere (r, r, r), cylinder (r, r, half height) or ellipsoid
    (semi-axes), centred at `centre` and turned by `yaw` about z."""

    shape: str
    centre: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    yaw: float = 0.0

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise WorldError(f"unknown primitive shape {self.shape!r}")
        if not all(h > 0 for h in self.half_extents):
            raise WorldError(f"primitive extents must be > 0, got {self.half_extents}")

    def shifted(self, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> Primitive:
        cx, cy, cz = self.centre
        return replace(self, centre=(cx + dx, cy + dy, cz + dz))

    def _local_xy(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = x - self.centre[0], y - self.centre[1]
        return c * dx + s * dy, -s * dx + c * dy

    def horizontal_radius(self) -> float:
        hx, hy, _ = self.half_extents
        return math.hypot(hx, hy) if self.shape == BOX else max(hx, hy)

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.horizontal_radius()
        hz = self.half_extents[2]
        c = np.array(self.centre)
        ext = np.array([r, r, hz])
        return c - ext, c + ext

    def top_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Altitude of the upper surface above (x, y); -inf outside the footprint."""
        lx, ly = self._local_xy(np.asarray(x, float), np.asarray(y, float))
        a, b, c = self.half_extents
        cz = self.centre[2]
        if self.shape == BOX:
            inside = (np.abs(lx) <= a) & (np.abs(ly) <= b)
            return np.where(inside, cz + c, -np.inf)
        if self.shape == CYLINDER:
            return np.where(lx * lx + ly * ly <= a * a, cz + c, -np.inf)
        # sphere and ellipsoid: z = cz + c * sqrt(1 - (x/a)^2 - (y/b)^2)
        q = 1.0 - (lx / a) ** 2 - (ly / b) ** 2
        return np.where(q >= 0, cz + c * np.sqrt(np.maximum(q, 0.0)), -np.inf)

    def contains(self, pts: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Points strictly inside the solid shrunk by `margin` (so surface samples are not)."""
        pts = np.asarray(pts, float)
        lx, ly = self._local_xy(pts[:, 0], pts[:, 1])
        lz = pts[:, 2] - self.centre[2]
        a, b, c = (h - margin for h in self.half_extents)
        if min(a, b, c) <= 0:
            return np.zeros(len(pts), bool)
        if self.shape == BOX:
            return (np.abs(lx) < a) & (np.abs(ly) < b) & (np.abs(lz) < c)
        if self.shape == CYLINDER:
            return (lx * lx + ly * ly < a * a) & (np.abs(lz) < c)
        return (lx / a) ** 2 + (ly / b) ** 2 + (lz / c) ** 2 < 1.0

    def sample_surface(self, spacing_m: float) -> np.ndarray:
        """Points on the surface, about `spacing_m` apart."""
        a, b, c = self.half_extents
        if self.shape == BOX:
            local = _box_surface(a, b, c, spacing_m)
        elif self.shape == CYLINDER:
            local = _cylinder_surface(a, c, spacing_m)
        else:
            area = _ellipsoid_area(a, b, c)
            n = max(int(math.ceil(area / spacing_m**2)), 8)
            local = _fibonacci_sphere(n) * np.array([a, b, c])
        cs, sn = math.cos(self.yaw), math.sin(self.yaw)
        rot = np.array([[cs, -sn, 0.0], [sn, cs, 0.0], [0.0, 0.0, 1.0]])
        return np.einsum("ij,kj->ik", local, rot) + np.array(self.centre)


def _grid_1d(half: float, spacing: float) -> np.ndarray:
    n = max(int(math.ceil(2 * half / spacing)), 1)
    return (np.arange(n) + 0.5) * (2 * half / n) - half


def _box_surface(a: float, b: float, c: float, s: float) -> np.ndarray:
    out = []
    for axis, (h0, h1, h2) in enumerate(((a, b, c), (b, c, a), (c, a, b))):
        u, v = np.meshgrid(_grid_1d(h1, s), _grid_1d(h2, s), indexing="ij")
        for sign in (-1.0, 1.0):
            face = np.stack([np.full(u.size, sign * h0), u.ravel(), v.ravel()], axis=1)
            # rotate the (normal, u, v) triple back into (x, y, z)
            out.append(np.roll(face, axis, axis=1))
    return np.concatenate(out)


def _cylinder_surface(r: float, hz: float, s: float) -> np.ndarray:
    n_t = max(int(math.ceil(2 * math.pi * r / s)), 8)
    t = np.arange(n_t) * (2 * math.pi / n_t)
    z = _grid_1d(hz, s)
    tt, zz = np.meshgrid(t, z, indexing="ij")
    side = np.stack([r * np.cos(tt.ravel()), r * np.sin(tt.ravel()), zz.ravel()], axis=1)
    g = _grid_1d(r, s)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    keep = gx * gx + gy * gy <= r * r
    disk = np.stack([gx[keep], gy[keep]], axis=1)
    caps = [np.column_stack([disk, np.full(len(disk), sign * hz)]) for sign in (-1.0, 1.0)]
    return np.concatenate([side, *caps])


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _ellipsoid_area(a: float, b: float, c: float) -> float:
    p = 1.6075  # Knud Thomsen's approximation, within about 1 %
    return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
