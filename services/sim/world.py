"""Garden worlds for the simulator, and their ground truth.

A `GardenWorld` is a pure description (numpy arrays and primitives, no PyBullet): a ground height
field split into terrain and grass, labelled objects on it (hedges, topiaries, roses, rocks and
boxes, trees), and boundary walls. `scene.BulletScene` turns it into PyBullet bodies; evaluation
code uses it directly. Two ways to get one:

    world = GardenWorld.generate(seed=3, size_m=12.0)       # procedural, 3DRMS-like
    world = GardenWorld.from_ply("garden.ply", voxel_m=0.05)  # from a user's labelled cloud

What the explorer and the evaluation tools need:

- `world.bounds` -> (xmin, ymin, xmax, ymax) in metres, world frame (z up), walls included;
- `world.traversability(robot_radius_m=0.0)` -> `Raster` of bools: the ground seen from above is
  a traversable class and, if a radius is given, no obstacle lies within that radius;
- `world.top_class()` / `world.top_height()` -> `Raster`s of the class and altitude seen from
  above (what a 2.5D navigation graph of the true world would hold);
- `world.gt_cloud(spacing_m)` -> (points f4[N,3], labels u2[N]) sampled on every visible surface
  (faces buried in the ground or inside another object are left out);
- `world.export_ply(path)`, `world.preview_image()`.

Class ids come from the class table (3DRMS garden by default: 1 grass, 2 terrain, 4 hedge,
5 topiary, 6 rose, 7 obstacle, 8 tree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from smana.common.classes import ClassTable

from .ply import read_labelled_ply, write_labelled_ply

BOX, SPHERE, CYLINDER, ELLIPSOID = "box", "sphere", "cylinder", "ellipsoid"
SHAPES = (BOX, SPHERE, CYLINDER, ELLIPSOID)

# 3DRMS class ids of the garden table; a procedural world needs to know which is which.
GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE = 1, 2, 4, 5, 6, 7, 8
_SINK_M = 0.05  # objects are sunk a little so that no gap shows between them and a sloped ground


class WorldError(ValueError):
    """A world cannot be built from the given parameters or data."""


# -- geometry ----------------------------------------------------------------------------------


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


# -- ground and rasters ------------------------------------------------------------------------


@dataclass
class Raster:
    """A 2D grid aligned with the ground's vertices: cell (i, j) is centred at
    origin_xy + (i, j) * resolution_m; `data` is indexed [ix, iy]."""

    origin_xy: tuple[float, float]
    resolution_m: float
    data: np.ndarray

    def index_of(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Nearest cell indices, clipped to the grid."""
        nx, ny = self.data.shape[:2]
        ix = np.rint((np.asarray(x) - self.origin_xy[0]) / self.resolution_m).astype(np.int64)
        iy = np.rint((np.asarray(y) - self.origin_xy[1]) / self.resolution_m).astype(np.int64)
        return np.clip(ix, 0, nx - 1), np.clip(iy, 0, ny - 1)

    def at(self, x, y) -> np.ndarray:
        return self.data[self.index_of(x, y)]

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        nx, ny = self.data.shape[:2]
        xs = self.origin_xy[0] + np.arange(nx) * self.resolution_m
        ys = self.origin_xy[1] + np.arange(ny) * self.resolution_m
        return xs, ys


@dataclass
class GroundModel:
    """Heights and ground classes at the vertices of a regular grid (x index first).

    `height_at` interpolates exactly as Bullet's height field triangulates each cell (the diagonal
    joins vertex (i+1, j) to (i, j+1)), so points on the simulated ground agree with it.
    """

    origin_xy: tuple[float, float]
    resolution_m: float
    heights: np.ndarray  # f8[nx, ny]
    classes: np.ndarray  # u2[nx, ny]

    def __post_init__(self):
        if self.heights.shape != self.classes.shape or self.heights.ndim != 2:
            raise WorldError("ground heights and classes must be 2D arrays of one shape")
        if min(self.heights.shape) < 2:
            raise WorldError("ground grid needs at least 2 x 2 vertices")

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    @property
    def extent(self) -> tuple[float, float, float, float]:
        nx, ny = self.shape
        x0, y0 = self.origin_xy
        return x0, y0, x0 + (nx - 1) * self.resolution_m, y0 + (ny - 1) * self.resolution_m

    def height_at(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        nx, ny = self.shape
        fx = np.clip((x - self.origin_xy[0]) / self.resolution_m, 0, nx - 1)
        fy = np.clip((y - self.origin_xy[1]) / self.resolution_m, 0, ny - 1)
        i = np.minimum(fx.astype(np.int64), nx - 2)
        j = np.minimum(fy.astype(np.int64), ny - 2)
        s, t = fx - i, fy - j
        h = self.heights
        h00, h10, h01, h11 = h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]
        lower = h00 + s * (h10 - h00) + t * (h01 - h00)
        upper = h11 + (1 - s) * (h01 - h11) + (1 - t) * (h10 - h11)
        return np.where(s + t <= 1.0, lower, upper)

    def class_at(self, x, y) -> np.ndarray:
        return self.class_raster().at(x, y)

    def class_raster(self) -> Raster:
        return Raster(self.origin_xy, self.resolution_m, self.classes)

    def height_raster(self) -> Raster:
        return Raster(self.origin_xy, self.resolution_m, self.heights)


# -- objects -----------------------------------------------------------------------------------


@dataclass
class WorldObject:
    """One labelled thing in the world: a union of primitives, or voxels (worlds from a cloud)."""

    kind: str
    class_id: int
    primitives: tuple[Primitive, ...] = ()
    voxel_centres: np.ndarray | None = None  # f8[M, 3], for kind "voxels"
    voxel_m: float = 0.0

    def __post_init__(self):
        if bool(self.primitives) == (self.voxel_centres is not None):
            raise WorldError("an object has either primitives or voxels")

    def contains(self, pts: np.ndarray, margin: float = 1e-4) -> np.ndarray:
        if self.voxel_centres is None:
            inside = np.zeros(len(pts), bool)
            for p in self.primitives:
                inside |= p.contains(pts, margin)
            return inside
        keys, origin = _voxel_keys(self.voxel_centres, self.voxel_m)
        q = np.floor((pts - origin) / self.voxel_m).astype(np.int64)
        inside_grid = np.all((q >= 0) & (q < 1 << 20), axis=1)
        k = (q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2]
        pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        return inside_grid & (keys[pos] == k)


def _voxel_keys(centres: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    origin = centres.min(axis=0) - voxel_m / 2
    q = np.floor((centres - origin) / voxel_m).astype(np.int64)
    return np.sort((q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2]), origin


# -- the procedural recipe ---------------------------------------------------------------------


@dataclass(frozen=True)
class GardenSpec:
    """Knobs of the procedural garden. The defaults give a world like the paper's 3DRMS garden:
    12 m x 12 m, terrain and grass in about equal parts, and objects covering enough of it that
    about half of the ground is free and traversable once the robot's radius is accounted for."""

    size_m: float = 12.0
    ground_resolution_m: float = 0.1
    terrain_fraction: float = 0.5  # of the ground, terrain (cost 1) rather than grass (cost 2)
    height_amplitude_m: float = 0.25
    max_slope: float = 0.15  # rise over run
    # share of the area inside the walls to cover with objects, seen from above; the gap between
    # objects caps what random placement reaches at about 0.2 (the default world is ~80 % free,
    # ~55 % free once grown by a 0.3 m robot radius)
    clutter: float = 0.35
    min_gap_m: float = 0.7  # between objects, so the free space stays connected for the robot
    spawn_clearance_m: float = 1.2  # free disk kept around the centre where the robot starts
    wall_height_m: float = 1.0
    wall_thickness_m: float = 0.2
    # relative frequencies of the object kinds
    hedges: float = 0.25
    topiaries: float = 0.2
    roses: float = 0.2
    obstacles: float = 0.2
    trees: float = 0.15

    def validate(self) -> None:
        if not 2.0 <= self.size_m <= 1000.0:
            raise WorldError(f"size_m must be within 2..1000, got {self.size_m}")
        if not 0.01 <= self.ground_resolution_m <= self.size_m / 4:
            raise WorldError(f"ground_resolution_m out of range: {self.ground_resolution_m}")
        if (self.size_m / self.ground_resolution_m) > 4000:
            raise WorldError("ground grid would exceed 4000 x 4000; use a coarser resolution")
        for name in ("terrain_fraction", "clutter"):
            if not 0.0 <= getattr(self, name) <= 0.9:
                raise WorldError(f"{name} must be within 0..0.9, got {getattr(self, name)}")
        for name in ("height_amplitude_m", "max_slope", "min_gap_m", "spawn_clearance_m"):
            if not getattr(self, name) >= 0:
                raise WorldError(f"{name} must be >= 0")
        weights = [self.hedges, self.topiaries, self.roses, self.obstacles, self.trees]
        if min(weights) < 0 or sum(weights) <= 0:
            raise WorldError("object frequencies must be >= 0 and not all 0")


def _smooth_noise(rng: np.random.Generator, shape, sigma_cells: float) -> np.ndarray:
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_cells, mode="reflect")
    f -= f.mean()
    return f / (f.std() + 1e-12)


def _make_ground(spec: GardenSpec, rng: np.random.Generator) -> GroundModel:
    res = spec.ground_resolution_m
    n = int(round(spec.size_m / res)) + 1
    half = (n - 1) * res / 2
    # a few metres between bumps: gentle hills, not a washboard
    heights = _smooth_noise(rng, (n, n), 1.5 / res) * (spec.height_amplitude_m / 2.5)
    if n > 2:
        gx, gy = np.gradient(heights, res)
        steepest = float(np.hypot(gx, gy).max())
        if steepest > spec.max_slope:
            heights *= spec.max_slope / steepest
    xs = -half + np.arange(n) * res
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    # gravel paths: straight terrain strips across the garden, as gardens have
    paths = np.zeros((n, n), bool)
    for _ in range(max(1, int(round(spec.size_m / 8)))):
        angle = rng.uniform(0, math.pi)
        offset = rng.uniform(-0.3, 0.3) * spec.size_m
        width = rng.uniform(0.8, 1.2)
        dist = np.abs(-math.sin(angle) * gx + math.cos(angle) * gy - offset)
        paths |= dist < width / 2
    patches = _smooth_noise(rng, (n, n), 1.2 / res)
    share_left = (spec.terrain_fraction - paths.mean()) / max(1.0 - paths.mean(), 1e-9)
    share_left = float(np.clip(share_left, 0.0, 1.0))
    if share_left <= 0:
        terrain = paths
    else:
        threshold = np.quantile(patches[~paths], 1.0 - share_left) if (~paths).any() else 0.0
        terrain = paths | (patches > threshold)
    classes = np.where(terrain, TERRAIN, GRASS).astype(np.uint16)
    return GroundModel((-half, -half), res, heights, classes)


def _random_object(kind: str, rng: np.random.Generator) -> tuple[int, list[Primitive]]:
    """Primitives of one object around (0, 0), standing on z = 0."""
    u = rng.uniform
    yaw = u(0, 2 * math.pi)
    if kind == "hedge":
        # hedges are usually planted along the garden's axes
        yaw = rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.05) if u() < 0.7 else yaw
        a, b, c = u(0.75, 2.0), u(0.25, 0.4), u(0.4, 0.8)
        return HEDGE, [Primitive(BOX, (0, 0, c - _SINK_M), (a, b, c), yaw)]
    if kind == "topiary":
        r = u(0.3, 0.6)
        if u() < 0.4:  # a ball
            return TOPIARY, [Primitive(SPHERE, (0, 0, 0.9 * r), (r, r, r))]
        if u() < 0.5:  # an egg
            c = u(1.2, 2.0) * r
            return TOPIARY, [Primitive(ELLIPSOID, (0, 0, 0.9 * c), (r, r, c))]
        r2 = r * u(0.55, 0.75)  # two stacked balls
        return TOPIARY, [
            Primitive(SPHERE, (0, 0, 0.9 * r), (r, r, r)),
            Primitive(SPHERE, (0, 0, 1.8 * r + 0.8 * r2), (r2, r2, r2)),
        ]
    if kind == "rose":
        prims = []
        for _ in range(int(rng.integers(3, 8))):
            r = u(0.12, 0.25)
            ang, dist = u(0, 2 * math.pi), u(0, 0.35)
            prims.append(
                Primitive(
                    SPHERE,
                    (dist * math.cos(ang), dist * math.sin(ang), r + u(0.0, 0.4)),
                    (r, r, r),
                )
            )
        return ROSE, prims
    if kind == "obstacle":
        if u() < 0.5:  # a box, crate or bench-like block
            a, b, c = u(0.2, 0.6), u(0.2, 0.6), u(0.15, 0.5)
            return OBSTACLE, [Primitive(BOX, (0, 0, c - _SINK_M), (a, b, c), yaw)]
        a, b = u(0.25, 0.6), u(0.25, 0.6)  # a rock, half buried
        c = u(0.2, 0.45)
        return OBSTACLE, [Primitive(ELLIPSOID, (0, 0, 0.3 * c), (a, b, c), yaw)]
    if kind == "tree":
        r_trunk, h_trunk = u(0.08, 0.18), u(1.2, 2.2)
        r_crown = u(0.7, 1.3)
        crown_z = h_trunk + 0.6 * r_crown
        return TREE, [
            Primitive(CYLINDER, (0, 0, h_trunk / 2 - _SINK_M), (r_trunk, r_trunk, h_trunk / 2)),
            Primitive(SPHERE, (0, 0, crown_z), (r_crown, r_crown, r_crown)),
        ]
    raise WorldError(f"unknown object kind {kind!r}")


def _walls(ground: GroundModel, spec: GardenSpec) -> list[WorldObject]:
    x0, y0, x1, y1 = ground.extent
    t = spec.wall_thickness_m
    zmin = float(ground.heights.min()) - _SINK_M
    ztop = float(ground.heights.max()) + spec.wall_height_m
    hz = (ztop - zmin) / 2
    cz = (ztop + zmin) / 2
    hx, hy = (x1 - x0) / 2, (y1 - y0) / 2
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    boxes = [
        Primitive(BOX, (cx, y0 + t / 2, cz), (hx, t / 2, hz)),
        Primitive(BOX, (cx, y1 - t / 2, cz), (hx, t / 2, hz)),
        Primitive(BOX, (x0 + t / 2, cy, cz), (t / 2, hy - t, hz)),
        Primitive(BOX, (x1 - t / 2, cy, cz), (t / 2, hy - t, hz)),
    ]
    return [WorldObject("wall", OBSTACLE, (b,)) for b in boxes]


def _disk(radius_cells: float) -> np.ndarray:
    r = int(math.ceil(radius_cells))
    g = np.arange(-r, r + 1)
    return (g[:, None] ** 2 + g[None, :] ** 2) <= radius_cells**2 + 1e-9


def _place_objects(
    spec: GardenSpec, ground: GroundModel, rng: np.random.Generator
) -> list[WorldObject]:
    res = ground.resolution_m
    n = ground.shape[0]
    xs = ground.origin_xy[0] + np.arange(n) * res
    gap_cells = spec.min_gap_m / res
    # cells an object may not cover: near the walls (plus the gap) and the robot's start disk
    margin = spec.wall_thickness_m + spec.min_gap_m
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    x0, y0, x1, y1 = ground.extent
    blocked = (gx < x0 + margin) | (gx > x1 - margin) | (gy < y0 + margin) | (gy > y1 - margin)
    blocked |= np.hypot(gx, gy) < spec.spawn_clearance_m
    inner_area = max(x1 - x0 - 2 * spec.wall_thickness_m, 0) ** 2
    target = spec.clutter * inner_area
    kinds = ["hedge", "topiary", "rose", "obstacle", "tree"]
    weights = np.array([spec.hedges, spec.topiaries, spec.roses, spec.obstacles, spec.trees])
    weights = weights / weights.sum()
    structure = _disk(gap_cells)
    pad = structure.shape[0] // 2
    objects: list[WorldObject] = []
    covered, failures = 0.0, 0
    max_failures = 400 + 20 * int(target)
    while covered < target and failures < max_failures:
        kind = str(rng.choice(kinds, p=weights))
        class_id, prims = _random_object(kind, rng)
        reach = max(math.hypot(p.centre[0], p.centre[1]) + p.horizontal_radius() for p in prims)
        cx, cy = rng.uniform(x0 + margin, x1 - margin, 2)
        # the object's window of cells, grown by the gap for the dilation below
        i0 = max(int((cx - reach - ground.origin_xy[0]) / res) - pad - 1, 0)
        i1 = min(int((cx + reach - ground.origin_xy[0]) / res) + pad + 2, n)
        j0 = max(int((cy - reach - ground.origin_xy[1]) / res) - pad - 1, 0)
        j1 = min(int((cy + reach - ground.origin_xy[1]) / res) + pad + 2, n)
        wx, wy = gx[i0:i1, j0:j1], gy[i0:i1, j0:j1]
        mask = np.zeros(wx.shape, bool)
        for p in prims:
            mask |= np.isfinite(p.top_height(wx - cx, wy - cy))
        if not mask.any() or (mask & blocked[i0:i1, j0:j1]).any():
            failures += 1
            continue
        base_z = float(ground.heights[i0:i1, j0:j1][mask].min())
        placed = tuple(p.shifted(cx, cy, base_z) for p in prims)
        objects.append(WorldObject(kind, class_id, placed))
        blocked[i0:i1, j0:j1] |= ndimage.binary_dilation(mask, structure)
        covered += mask.sum() * res * res
    return objects


# -- the world ---------------------------------------------------------------------------------


class GardenWorld:
    """A garden: ground, objects and walls, plus everything evaluation needs (module docstring)."""

    def __init__(
        self,
        ground: GroundModel,
        objects: list[WorldObject],
        classes: ClassTable | None = None,
        *,
        name: str = "garden",
        seed: int | None = None,
        spec: GardenSpec | None = None,
        source_cloud: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.ground = ground
        self.objects = list(objects)
        self.classes = classes or ClassTable.load("garden3drms")
        self.name = name
        self.seed = seed
        self.spec = spec
        # a world built from a labelled cloud keeps that cloud as its ground truth
        self.source_cloud = source_cloud
        self._top: tuple[Raster, Raster] | None = None
        self._gt: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        used = {int(c) for c in np.unique(ground.classes)} | {o.class_id for o in self.objects}
        missing = sorted(c for c in used if c not in self.classes)
        if missing:
            raise WorldError(f"class ids {missing} are not in class table {self.classes.name!r}")

    # -- construction ----------------------------------------------------------------------------

    @classmethod
    def generate(
        cls,
        seed: int = 0,
        size_m: float = 12.0,
        classes: ClassTable | None = None,
        spec: GardenSpec | None = None,
        **overrides,
    ) -> GardenWorld:
        """A procedural garden; the same seed and spec always give the same world."""
        spec = replace(spec or GardenSpec(), size_m=size_m, **overrides)
        spec.validate()
        classes = classes or ClassTable.load("garden3drms")
        for cid in (GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE):
            if cid not in classes:
                raise WorldError(
                    f"procedural gardens use 3DRMS ids; class {cid} missing from {classes.name}"
                )
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
        ground = _make_ground(spec, rng)
        objects = _walls(ground, spec) + _place_objects(spec, ground, rng)
        return cls(ground, objects, classes, name=f"garden-{seed}", seed=seed, spec=spec)

    @classmethod
    def from_config(cls, sim_config, classes: ClassTable | None = None) -> GardenWorld:
        """The world a `[sim]` config section describes: `world = "garden"` (procedural, from
        `seed`, `size_m`, `ground_resolution_m`) or a labelled PLY (`"ply:PATH"` or a path,
        with `voxel_m`). The same config always gives the same world."""
        spec = sim_config.world
        res = getattr(sim_config, "ground_resolution_m", 0.1)
        if spec == "garden":
            return cls.generate(
                sim_config.seed, size_m=sim_config.size_m, classes=classes, ground_resolution_m=res
            )
        path = spec[4:] if spec.startswith("ply:") else spec
        if not Path(path).is_file():
            raise WorldError(f"sim.world: {spec!r} is neither 'garden' nor a PLY file")
        voxel = getattr(sim_config, "voxel_m", 0.05)
        return cls.from_ply(path, classes, voxel_m=voxel, ground_resolution_m=res)

    @classmethod
    def from_ply(
        cls,
        path: str | Path,
        classes: ClassTable | None = None,
        *,
        voxel_m: float = 0.05,
        ground_resolution_m: float = 0.1,
        label_field: str | None = None,
        walls: bool = True,
        wall_height_m: float = 1.0,
    ) -> GardenWorld:
        """A world from a labelled point cloud (paper 4.1): points of traversable classes become
        the height field (one height and the majority class per cell), points of every other
        class become voxels of `voxel_m`, one body per class. Walls are added around it."""
        points, labels = read_labelled_ply(path, label_field)
        return cls.from_cloud(
            points,
            labels,
            classes,
            voxel_m=voxel_m,
            ground_resolution_m=ground_resolution_m,
            walls=walls,
            wall_height_m=wall_height_m,
            name=Path(path).stem,
        )

    @classmethod
    def from_cloud(
        cls,
        points: np.ndarray,
        labels: np.ndarray,
        classes: ClassTable | None = None,
        *,
        voxel_m: float = 0.05,
        ground_resolution_m: float = 0.1,
        walls: bool = True,
        wall_height_m: float = 1.0,
        name: str = "cloud",
    ) -> GardenWorld:
        classes = classes or ClassTable.load("garden3drms")
        points = np.asarray(points, np.float64)
        labels = np.asarray(labels, np.int64)
        if points.ndim != 2 or points.shape[1] != 3 or len(labels) != len(points):
            raise WorldError("expected points (N,3) and labels (N,)")
        finite = np.all(np.isfinite(points), axis=1)
        points, labels = points[finite], labels[finite]
        if voxel_m <= 0 or ground_resolution_m <= 0:
            raise WorldError("voxel_m and ground_resolution_m must be > 0")
        labels, n_bad = classes.sanitise(labels)
        if n_bad:
            raise WorldError(f"{n_bad} points carry ids that are not in {classes.name!r}")
        is_ground = classes.traversable_lut[labels]
        is_object = ~is_ground & (labels != 0) & ~classes.ignored_lut[labels]
        if not is_ground.any():
            raise WorldError("the cloud has no points of a traversable class to build ground from")
        ground = _ground_from_points(points[is_ground], labels[is_ground], ground_resolution_m)
        objects = []
        for cid in np.unique(labels[is_object]):
            sel = points[is_object & (labels == cid)]
            q = np.unique(np.floor(sel / voxel_m).astype(np.int64), axis=0)
            centres = (q + 0.5) * voxel_m
            objects.append(WorldObject("voxels", int(cid), voxel_centres=centres, voxel_m=voxel_m))
        if walls:
            wall_class = next(
                (c.id for c in classes.classes.values() if c.obstacle and c.name == "obstacle"),
                None,
            ) or next(c.id for c in classes.classes.values() if c.obstacle)
            spec = GardenSpec(size_m=max(ground.extent[2] - ground.extent[0], 2.0))
            spec = replace(spec, wall_height_m=wall_height_m)
            objects = [replace(w, class_id=wall_class) for w in _walls(ground, spec)] + objects
        keep = labels != 0
        return cls(ground, objects, classes, name=name, source_cloud=(points[keep], labels[keep]))

    # -- geometry queries ------------------------------------------------------------------------

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the ground, walls included."""
        return self.ground.extent

    @property
    def size_m(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.bounds
        return x1 - x0, y1 - y0

    def _tops(self) -> tuple[Raster, Raster]:
        if self._top is None:
            g = self.ground
            height = g.heights.copy()
            cls_ = g.classes.copy()
            xs = g.origin_xy[0] + np.arange(g.shape[0]) * g.resolution_m
            ys = g.origin_xy[1] + np.arange(g.shape[1]) * g.resolution_m
            for obj in self.objects:
                if obj.voxel_centres is not None:
                    c = obj.voxel_centres
                    ix, iy = g.class_raster().index_of(c[:, 0], c[:, 1])
                    top = np.full(g.shape, -np.inf)
                    np.maximum.at(top, (ix, iy), c[:, 2] + obj.voxel_m / 2)
                    win = top > height
                    height[win], cls_[win] = top[win], obj.class_id
                    continue
                for p in obj.primitives:
                    lo, hi = p.aabb()
                    i0, i1 = np.searchsorted(xs, [lo[0], hi[0]])
                    j0, j1 = np.searchsorted(ys, [lo[1], hi[1]])
                    wx, wy = np.meshgrid(xs[i0:i1], ys[j0:j1], indexing="ij")
                    top = p.top_height(wx, wy)
                    win = top > height[i0:i1, j0:j1]
                    height[i0:i1, j0:j1][win] = top[win]
                    cls_[i0:i1, j0:j1][win] = obj.class_id
            self._top = (
                Raster(g.origin_xy, g.resolution_m, cls_),
                Raster(g.origin_xy, g.resolution_m, height),
            )
        return self._top

    def top_class(self) -> Raster:
        """Class of the highest surface above each ground vertex (u2)."""
        return self._tops()[0]

    def top_height(self) -> Raster:
        """Altitude of the highest surface above each ground vertex (f8, metres)."""
        return self._tops()[1]

    def traversability(self, robot_radius_m: float = 0.0) -> Raster:
        """Ground-truth traversable cells (bool); with a radius, also clear of obstacles by it."""
        top = self.top_class()
        ok = self.classes.traversable_lut[top.data]
        if robot_radius_m > 0:
            clearance = ndimage.distance_transform_edt(ok) * top.resolution_m
            ok = clearance > robot_radius_m
        return Raster(top.origin_xy, top.resolution_m, ok)

    def free_fraction(self, robot_radius_m: float = 0.0) -> float:
        return float(self.traversability(robot_radius_m).data.mean())

    def spawn_pose(self, robot_radius_m: float = 0.45) -> tuple[float, float, float]:
        """(x, y, z_ground) of the free spot nearest the centre with that much clearance."""
        trav = self.traversability(robot_radius_m)
        if not trav.data.any():
            raise WorldError(f"no free spot with {robot_radius_m} m clearance in {self.name}")
        xs, ys = trav.cell_centres()
        x0, y0, x1, y1 = self.bounds
        gx, gy = np.meshgrid(xs - (x0 + x1) / 2, ys - (y0 + y1) / 2, indexing="ij")
        d = np.where(trav.data, np.hypot(gx, gy), np.inf)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        x, y = float(xs[i]), float(ys[j])
        return x, y, float(self.ground.height_at(x, y))

    def object_class_at(self, pts: np.ndarray, grow_m: float = 0.0) -> np.ndarray:
        """Class of the object containing each point (objects grown by `grow_m`), 0 where none
        does. Where objects overlap, the one listed last wins."""
        out = np.zeros(len(pts), np.uint16)
        for obj in self.objects:
            out[obj.contains(np.asarray(pts, float), margin=-grow_m)] = obj.class_id
        return out

    # -- ground truth ---------------------------------------------------------------------------

    def gt_cloud(self, spacing_m: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
        """(points f4[N,3], labels u2[N]) on every visible surface, about `spacing_m` apart.

        Worlds built from a cloud return that cloud (plus samples on the added walls)."""
        if not spacing_m > 0:
            raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
        key = round(float(spacing_m), 6)
        if key not in self._gt:
            self._gt[key] = self._sample_gt(spacing_m)
        return self._gt[key]

    def _sample_gt(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        prim_pts, prim_lab, prim_idx = [], [], []
        prims = [(o, p) for o in self.objects for p in o.primitives]
        for k, (obj, p) in enumerate(prims):
            if self.source_cloud is not None and obj.kind != "wall":
                continue
            pts = p.sample_surface(s)
            prim_pts.append(pts)
            prim_lab.append(np.full(len(pts), obj.class_id, np.uint16))
            prim_idx.append(np.full(len(pts), k, np.int64))
        if self.source_cloud is not None:
            pts, labs = self.source_cloud
            walls_pts = np.concatenate(prim_pts) if prim_pts else np.zeros((0, 3))
            walls_lab = np.concatenate(prim_lab) if prim_lab else np.zeros(0, np.uint16)
            # the walls' lower faces sit in the ground: drop what is buried
            floor = self.ground.height_at(walls_pts[:, 0], walls_pts[:, 1])
            buried = walls_pts[:, 2] < floor - 0.01
            return (
                np.concatenate([pts, walls_pts[~buried]]).astype(np.float32),
                np.concatenate([labs.astype(np.uint16), walls_lab[~buried]]),
            )
        x0, y0, x1, y1 = self.bounds
        gxs = np.arange(x0 + s / 2, x1, s)
        gys = np.arange(y0 + s / 2, y1, s)
        gx, gy = (a.ravel() for a in np.meshgrid(gxs, gys, indexing="ij"))
        ground = np.stack([gx, gy, self.ground.height_at(gx, gy)], axis=1)
        pts = np.concatenate([ground, *prim_pts])
        labels = np.concatenate([self.ground.class_at(gx, gy).astype(np.uint16), *prim_lab])
        owner = np.concatenate([np.full(len(ground), -1, np.int64), *prim_idx])
        keep = pts[:, 2] >= self.ground.height_at(pts[:, 0], pts[:, 1]) - 0.01
        for k, (_, p) in enumerate(prims):
            lo, hi = p.aabb()
            near = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1) & (owner != k))
            keep[near[p.contains(pts[near], margin=1e-4)]] = False
        return pts[keep].astype(np.float32), labels[keep]

    def export_ply(self, path: str | Path, spacing_m: float = 0.03) -> int:
        """Write the ground-truth cloud as PLY (x y z label red green blue); returns the count."""
        pts, labels = self.gt_cloud(spacing_m)
        write_labelled_ply(path, pts, labels, self.classes.colour_lut[labels])
        return len(pts)

    def preview_image(self, pixels: int = 768) -> np.ndarray:
        """Top-down RGB picture of the classes (x to the right, y up), shaded by altitude."""
        top_c, top_h = self._tops()
        rgb = self.classes.colour_lut[top_c.data].astype(np.float64)
        gx, gy = np.gradient(top_h.data, top_h.resolution_m)
        # hill shading with light from the north-west, so objects read as raised
        shade = np.clip(1.0 - 0.35 * (gx - gy) / np.sqrt(1 + gx * gx + gy * gy), 0.55, 1.25)
        rgb = np.clip(rgb * shade[..., None], 0, 255).astype(np.uint8)
        img = np.ascontiguousarray(np.transpose(rgb, (1, 0, 2))[::-1])
        scale = max(1, pixels // max(img.shape[:2]))
        return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)

    def summary(self) -> dict:
        counts: dict[str, int] = {}
        for o in self.objects:
            counts[o.kind] = counts.get(o.kind, 0) + 1
        ground = self.ground.classes
        return {
            "name": self.name,
            "bounds": self.bounds,
            "objects": counts,
            "terrain_share_of_ground": float(np.mean(ground == TERRAIN)),
            "free_fraction": self.free_fraction(),
            "free_fraction_r0.35": self.free_fraction(0.35),
        }


def _ground_from_points(points: np.ndarray, labels: np.ndarray, res: float) -> GroundModel:
    lo = points[:, :2].min(axis=0)
    hi = points[:, :2].max(axis=0)
    n = np.maximum(np.ceil((hi - lo) / res).astype(int) + 1, 2)
    ix = np.clip(np.rint((points[:, 0] - lo[0]) / res).astype(np.int64), 0, n[0] - 1)
    iy = np.clip(np.rint((points[:, 1] - lo[1]) / res).astype(np.int64), 0, n[1] - 1)
    cell = ix * n[1] + iy
    ncell = int(n[0] * n[1])
    # median height per cell: robust to the superimposed ground layers the paper filtered out
    order = np.lexsort((points[:, 2], cell))
    cell_sorted = cell[order]
    starts = np.searchsorted(cell_sorted, np.arange(ncell))
    ends = np.searchsorted(cell_sorted, np.arange(ncell), side="right")
    have = ends > starts
    mid = (starts + ends - 1) // 2
    heights = np.full(ncell, np.nan)
    heights[have] = points[order[mid[have]], 2]
    # majority class per cell
    ulab, lab_idx = np.unique(labels, return_inverse=True)
    votes = np.zeros((ncell, len(ulab)), np.int64)
    np.add.at(votes, (cell, lab_idx), 1)
    classes = ulab[np.argmax(votes, axis=1)].astype(np.uint16)
    heights = heights.reshape(n)
    classes = classes.reshape(n)
    have = have.reshape(n)
    if not have.all():
        # cells without ground points (under objects, or holes) take their nearest neighbour's
        _, (ii, jj) = ndimage.distance_transform_edt(~have, return_indices=True)
        heights, classes = heights[ii, jj], classes[ii, jj]
    return GroundModel((float(lo[0]), float(lo[1])), res, heights, classes)


__all__ = [
    "GardenSpec",
    "GardenWorld",
    "GroundModel",
    "Primitive",
    "Raster",
    "WorldError",
    "WorldObject",
]
