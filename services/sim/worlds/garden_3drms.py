"""The "3drms" layout of the procedural garden (`sim.garden.layout = "3drms"`): a garden with the
statistics of the paper's 3DRMS world (section 4.3: 48 % of the surface free, 55 % of it terrain).

Gravel plazas (terrain) at well-spread points, one at the centre where the robot spawns, joined by
curved gravel paths along a minimum spanning tree plus a loop or two; the rest of the garden is cut
into parcels (Voronoi cells split by the paths), some of them lawns (grass) that touch a path,
the others planted beds: hedges lining them along paths, lawns and walls, then the biggest hole left
in a bed filled, over and over, with a tree crown, a topiary, a rose bush or a rock of that size.
Beds end up almost covered from above (the bare soil left, terrain, is counted in the targets), so
what is free is mostly the paths, plazas and lawns, sized to the targets.

    ground, objects = layout_3drms(config, heights, rng)    # garden.generate() calls it
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

from .garden import GardenConfig
from .geometry import BOX, CYLINDER, ELLIPSOID, SPHERE, Primitive
from .ground import GroundModel
from .objects import GRASS, HEDGE, OBSTACLE, ROSE, SINK_M, TERRAIN, TOPIARY, TREE, WorldObject

BED_GAPS = 0.05  # share of the raster the bed filling leaves bare (measured: 0.04-0.06)
PARCEL_AREA_M2 = 4.0  # mean Voronoi parcel before the paths split it: lawns come in these pieces
LAWN_GAP_M = 0.85  # clear ground around an object on a lawn, so the lawn stays connected (> 0.8)
FILL_MIN_RADIUS_M = 0.15  # holes in beds smaller than this stay (each object costs render time)
MAX_CROWN_M = 1.3  # the largest tree crown radius
PLAZA_RADIUS_M = (0.8, 1.2)  # plazas other than the central one (its radius: plaza_clearance_m)


def raster(cfg: GardenConfig, heights: np.ndarray):
    """(cell size, half side, x and y of every cell centre, cells inside the walls) of the
    ground raster a layout classifies: the walls cover cells up to wall_thickness_m in, the one
    right at it only by rounding."""
    res = cfg.ground_resolution_m
    n = heights.shape[0]
    half = (n - 1) * res / 2
    xs = -half + np.arange(n) * res
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    edge_m = np.minimum(half - np.abs(gx), half - np.abs(gy))  # distance to the outer edge
    return res, half, gx, gy, edge_m > cfg.wall_thickness_m - res / 2


def layout_3drms(
    cfg: GardenConfig, heights: np.ndarray, rng: np.random.Generator
) -> tuple[GroundModel, list[WorldObject]]:
    """The ground (classes on `heights`) and the objects, walls excepted."""
    res, half, gx, gy, inner = raster(cfg, heights)
    n_cells = gx.size  # the stats count the whole raster, walls included
    # beds keep some uncovered gaps (free, terrain underneath): the paths leave room for them
    gaps = BED_GAPS * n_cells
    terrain_target = cfg.free_share * cfg.terrain_share * n_cells - gaps
    terrain = _paths_and_plazas(cfg, gx, gy, half, terrain_target, rng)
    terrain &= inner
    spawn = np.hypot(gx, gy) < cfg.plaza_clearance_m
    lawn = spawn & inner & ~terrain
    lawn_target = cfg.free_share * (1 - cfg.terrain_share) * n_cells
    lawn |= _lawns(
        gx, gy, inner & ~terrain & ~lawn, terrain | lawn, lawn_target - lawn.sum(), res, rng
    )
    bed = inner & ~terrain & ~lawn
    classes = np.where(lawn | ~inner, GRASS, TERRAIN).astype(np.uint16)
    ground = GroundModel((-half, -half), res, heights, classes)

    placer = Placer(ground, gx, gy)
    objects = _lawn_objects(placer, lawn & ~spawn, rng)
    objects += edge_hedges(placer, bed, terrain | lawn | ~inner, rng)  # walls too
    objects += fill_beds(placer, bed, rng)
    return ground, objects


# -- paths, plazas, lawns ------------------------------------------------------------------------


def _spread_points(count: int, lim: float, rng: np.random.Generator) -> np.ndarray:
    """The centre, then best-candidate points (farthest of 16 tries) in [-lim, lim]^2."""
    pts = [np.zeros(2)]
    for _ in range(count - 1):
        cand = rng.uniform(-lim, lim, (16, 2))
        d = np.min(np.linalg.norm(cand[:, None] - np.array(pts)[None], axis=2), axis=1)
        pts.append(cand[int(np.argmax(d))])
    return np.array(pts)


def _bezier(a: np.ndarray, b: np.ndarray, bend: float, step_m: float) -> np.ndarray:
    """Points every ~step_m along a quadratic curve from a to b, bowed sideways by bend x length."""
    d = b - a
    length = float(np.hypot(*d))
    ctrl = (a + b) / 2 + bend * np.array([-d[1], d[0]])
    t = np.linspace(0, 1, max(int(length / step_m) + 2, 2))[:, None]
    return (1 - t) ** 2 * a + 2 * (1 - t) * t * ctrl + t**2 * b


def _paths_and_plazas(cfg, gx, gy, half, target_cells, rng):
    """Terrain mask: plazas and the paths between them (a spanning tree and a loop or two), their
    widths within `path_width_m`, then the plazas' radii, fitted to `target_cells`."""
    res = cfg.ground_resolution_m
    n_plazas = max(2, int(round(cfg.size_m**2 / 36)))
    # plazas and paths keep off the walls, so objects can line them
    lim = max(half - cfg.wall_thickness_m - 1.4, 0.5)
    pts = _spread_points(n_plazas, lim, rng)
    radii = rng.uniform(*PLAZA_RADIUS_M, n_plazas)
    radii[0] = max(cfg.plaza_clearance_m - 0.7, 1.0)  # a lawn ring completes the spawn disk
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    tree = minimum_spanning_tree(dist).toarray() > 0
    edges = [tuple(e) for e in np.argwhere(tree)]
    others = [(i, j) for i in range(n_plazas) for j in range(i + 1, n_plazas) if not tree[i, j]]
    others = [e for e in others if not tree[e[1], e[0]]]
    others.sort(key=lambda e: dist[e])

    def disks(r):
        m = np.zeros(gx.shape, bool)
        for (x, y), rad in zip(pts, r, strict=True):
            m |= np.hypot(gx - x, gy - y) <= rad
        return m

    def centre_distance_m(e):
        line = _bezier(pts[e[0]], pts[e[1]], rng.uniform(-0.2, 0.2), res / 2)
        marks = np.ones(gx.shape, bool)
        ix = np.clip(np.rint((np.clip(line, -lim, lim) + half) / res).astype(int), 0, len(gx) - 1)
        marks[ix[:, 0], ix[:, 1]] = False
        return ndimage.distance_transform_edt(marks) * res

    edges += others[: int(round(n_plazas / 4))]  # a loop or two: more than one way round
    dists = [centre_distance_m(e) for e in edges]
    w_min, w_max = cfg.path_width_m
    widths = rng.uniform(w_min, w_max, len(edges))

    def network(shift_m, r):
        m = disks(r)
        for d, w in zip(dists, np.clip(widths + shift_m, w_min, w_max), strict=True):
            m |= d <= w / 2
        return m

    # the paths' widths, then the plazas, sized so that terrain comes near the target
    span = w_max - w_min
    lo, hi = -span, span
    for _ in range(12):  # bisection: the area grows with the widths
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if network(mid, radii).sum() < target_cells else (lo, mid)
    shift = (lo + hi) / 2
    low = np.full(n_plazas, PLAZA_RADIUS_M[0] - 0.1)
    low[0] = 1.2
    while network(shift, radii).sum() > target_cells and (radii > low).any():
        radii = np.maximum(radii - 0.1, low)
    while network(shift, radii).sum() < target_cells and radii[1:].min() < 2.0:
        radii[1:] = np.minimum(radii[1:] + 0.1, 2.0)
    return network(shift, radii)


def _lawns(gx, gy, free, reachable, target_cells, res, rng) -> np.ndarray:
    """Parcels of `free` (Voronoi cells split by the paths) touching `reachable` along >= 1 m,
    chosen in random order while they bring the lawn area nearer `target_cells`."""
    lawn = np.zeros(free.shape, bool)
    if target_cells <= 0 or not free.any():
        return lawn
    area_m2 = free.sum() * res * res
    seeds = np.column_stack(
        [rng.uniform(gx.min(), gx.max(), max(int(area_m2 / PARCEL_AREA_M2), 1)) for _ in "xy"]
    )
    owner = np.full(free.shape, -1)
    owner[free] = cKDTree(seeds).query(np.column_stack([gx[free], gy[free]]))[1]
    # a parcel is a connected piece of one Voronoi cell, which a path may have split
    parcels, count = np.zeros(free.shape, np.int64), 0
    for k in range(len(seeds)):
        pieces, n_pieces = ndimage.label(owner == k)
        parcels[pieces > 0] = pieces[pieces > 0] + count
        count += n_pieces
    size = np.bincount(parcels.ravel(), minlength=count + 1)
    chosen, total, reach = [], 0, reachable.copy()
    grew = True
    while grew:  # a lawn reached through another lawn counts as touching the paths
        grew = False
        border = ndimage.binary_dilation(reach) & ~reach
        touch_m = np.bincount(parcels[border], minlength=count + 1) * res
        for p in rng.permutation(np.arange(1, count + 1)):
            near = abs(target_cells - total - size[p]) < target_cells - total
            if p not in chosen and touch_m[p] >= 1.0 and near:
                chosen.append(p)
                total += size[p]
                reach |= parcels == p
                grew = True
    return np.isin(parcels, chosen)


# -- objects ------------------------------------------------------------------------------------


class Placer:
    """Footprints of objects on the ground raster, and the objects standing on the ground."""

    def __init__(self, ground: GroundModel, gx: np.ndarray, gy: np.ndarray):
        self.ground, self.gx, self.gy = ground, gx, gy
        self.covered = np.zeros(gx.shape, bool)

    def footprint(self, prims) -> tuple[tuple[slice, slice], np.ndarray]:
        res, n = self.ground.resolution_m, self.gx.shape[0]
        lo = np.min([p.aabb()[0][:2] for p in prims], axis=0)
        hi = np.max([p.aabb()[1][:2] for p in prims], axis=0)
        o = self.ground.origin_xy[0]
        i0, j0 = (max(int((v - o) / res), 0) for v in lo)
        i1, j1 = (min(int((v - o) / res) + 2, n) for v in hi)
        win = (slice(i0, i1), slice(j0, j1))
        mask = np.zeros(self.gx[win].shape, bool)
        for p in prims:
            mask |= np.isfinite(p.top_height(self.gx[win], self.gy[win]))
        return win, mask

    def place(self, kind, class_id, prims, cx, cy, allowed) -> WorldObject | None:
        """The object at (cx, cy) on the ground if its footprint lies within `allowed`."""
        prims = [p.shifted(cx, cy) for p in prims]
        win, mask = self.footprint(prims)
        if not mask.any() or (mask & ~allowed[win]).any():
            return None
        base_z = float(self.ground.heights[win][mask].min())
        self.covered[win] |= mask
        return WorldObject(kind, class_id, tuple(p.shifted(dz=base_z) for p in prims))


def _plant(radius_m: float, rng: np.random.Generator) -> tuple[str, int, list[Primitive]]:
    """A tree, topiary, rose bush or rock whose footprint fits a disk of `radius_m` at (0, 0)."""
    u, r = rng.uniform, radius_m
    roll = u()
    if r >= 0.7 and roll < 0.75:  # the big holes get trees: one crown covers a lot of ground
        crown = min(r, MAX_CROWN_M)
        trunk_r, trunk_h = u(0.08, 0.18), u(1.2, 2.2)
        return (
            "tree",
            TREE,
            [
                Primitive(CYLINDER, (0, 0, trunk_h / 2 - SINK_M), (trunk_r, trunk_r, trunk_h / 2)),
                Primitive(SPHERE, (0, 0, trunk_h + 0.6 * crown), (crown, crown, crown)),
            ],
        )
    r = min(r, 0.8)
    if roll < 0.45 or r < 0.25:  # topiary: a clipped ball or egg
        c = r * (u(1.2, 1.8) if u() < 0.5 else 1.0)
        return "topiary", TOPIARY, [Primitive(ELLIPSOID, (0, 0, 0.9 * c), (r, r, c))]
    if roll < 0.85:  # a rose bush: a few balls of leaves, the largest filling the hole
        prims = [Primitive(SPHERE, (0, 0, 0.8 * r), (r, r, 0.8 * r))]
        for _ in range(int(rng.integers(1, 3))):
            s = r * u(0.35, 0.55)
            ang, d = u(0, 2 * math.pi), u(0, r - s)
            prims.append(
                Primitive(SPHERE, (d * math.cos(ang), d * math.sin(ang), 1.4 * r), (s,) * 3)
            )
        return "rose", ROSE, prims
    b = r * u(0.6, 1.0)  # a rock, half buried
    c = u(0.2, 0.45)
    return "obstacle", OBSTACLE, [Primitive(ELLIPSOID, (0, 0, 0.3 * c), (r, b, c), u(0, math.pi))]


def _lawn_objects(placer: Placer, lawn: np.ndarray, rng) -> list[WorldObject]:
    """A few objects on the lawns, each with LAWN_GAP_M of lawn all round."""
    res = placer.ground.resolution_m
    out = []
    open_m = ndimage.distance_transform_edt(lawn) * res
    for _ in range(int(lawn.sum() * res * res / 12)):
        r = rng.uniform(0.2, 0.9)
        ok = np.flatnonzero(open_m > r + LAWN_GAP_M)
        if not ok.size:
            continue
        i, j = np.unravel_index(rng.choice(ok), lawn.shape)
        kind, cid, prims = _plant(r, rng)
        obj = placer.place(kind, cid, prims, placer.gx[i, j], placer.gy[i, j], lawn)
        if obj is not None:
            out.append(obj)
            near = np.hypot(placer.gx - placer.gx[i, j], placer.gy - placer.gy[i, j])
            open_m = np.minimum(open_m, np.maximum(near - r, 0))
    return out


def edge_hedges(placer: Placer, bed: np.ndarray, open_: np.ndarray, rng) -> list[WorldObject]:
    """Hedges lining the beds where they border `open_` ground (paths, lawns): boxes laid along
    the border, as long as fits. Round plants cannot cover a straight border strip; boxes can."""
    res = placer.ground.resolution_m
    to_edge_m = ndimage.distance_transform_edt(bed) * res
    nx, ny = np.gradient(to_edge_m)  # points into the bed
    border = bed & (ndimage.distance_transform_edt(~open_) * res <= 1.5 * res)
    out = []
    for c in rng.permutation(np.flatnonzero(border)):
        i, j = np.unravel_index(c, bed.shape)
        norm = math.hypot(nx[i, j], ny[i, j])
        if placer.covered[i, j] or norm < 1e-9:
            continue
        n = np.array([nx[i, j], ny[i, j]]) / norm
        b, h = rng.uniform(0.2, 0.32), rng.uniform(0.35, 0.7)
        yaw = math.atan2(n[0], -n[1])  # the box's long side along the border
        centre = np.array([placer.gx[i, j], placer.gy[i, j]]) + n * (b - to_edge_m[i, j] + res)
        for length in (3.0, 2.2, 1.5, 1.0):
            box = Primitive(BOX, (centre[0], centre[1], h - SINK_M), (length / 2, b, h), yaw)
            win, mask = placer.footprint([box])
            if (mask & ~bed[win]).any() or (mask & ~placer.covered[win]).sum() < 0.5 * mask.sum():
                continue  # out of the bed, or mostly on hedges already there
            local = box.shifted(-centre[0], -centre[1])
            obj = placer.place("hedge", HEDGE, [local], centre[0], centre[1], bed)
            if obj is not None:  # None only if rounding moved the footprint by a cell
                out.append(obj)
            break
    return out


def fill_beds(placer: Placer, bed: np.ndarray, rng) -> list[WorldObject]:
    """The biggest hole in the beds gets a plant of its size, until only small holes are left."""
    res = placer.ground.resolution_m
    to_edge_m = ndimage.distance_transform_edt(bed) * res  # a plant may overlap plants, not paths
    hole_m = ndimage.distance_transform_edt(bed & ~placer.covered) * res
    out = []
    for _ in range(2000):
        biggest = float(hole_m.max())
        if biggest < FILL_MIN_RADIUS_M:
            break
        i, j = np.unravel_index(rng.choice(np.flatnonzero(hole_m >= 0.85 * biggest)), bed.shape)
        radius = min(1.3 * hole_m[i, j], to_edge_m[i, j] - 0.6 * res)
        kind, cid, prims = _plant(radius, rng)
        obj = placer.place(kind, cid, prims, placer.gx[i, j], placer.gy[i, j], bed)
        if obj is None:  # a footprint rasterised a cell too wide: give this centre up
            hole_m[i, j] = 0.0
            continue
        out.append(obj)
        # only cells nearer the new footprint than the biggest hole can see their hole shrink
        win, mask = placer.footprint(obj.primitives)
        pad = int(math.ceil(biggest / res)) + 1
        n = bed.shape[0]
        big = tuple(slice(max(w.start - pad, 0), min(w.stop + pad, n)) for w in win)
        fresh = np.ones(hole_m[big].shape, bool)
        fresh[
            win[0].start - big[0].start : win[0].stop - big[0].start,
            win[1].start - big[1].start : win[1].stop - big[1].start,
        ] = ~mask
        hole_m[big] = np.minimum(hole_m[big], ndimage.distance_transform_edt(fresh) * res)
    return out
