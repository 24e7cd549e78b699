"""A world and what can be asked of it, whichever source built it (`worlds/__init__.py`).

A `World` is a pure description (numpy arrays and primitives, no PyBullet): a ground height field
with a class per vertex, labelled objects on it and boundary walls. `scene.BulletScene` turns it
into PyBullet bodies; evaluation code uses it directly. What the explorer and the evaluation
tools need:

- `world.bounds` -> (xmin, ymin, xmax, ymax) in metres, world frame (z up), walls included;
- `world.traversability(robot_radius_m=0.0)` -> `Raster` of bools: the ground seen from above is
  a traversable class and, if a radius is given, no obstacle lies within that radius;
- `world.top_class()` / `world.top_height()` -> `Raster`s of the class and altitude seen from
  above (what a 2.5D navigation graph of the true world would hold);
- `world.terrain_share()`, `world.reachable_fraction(robot_radius_m)` -> the statistics the paper
  gives its garden (terrain share of the traversable surface) and how much of the free space
  connects to the spawn;
- `world.gt_cloud(spacing_m)` -> (points f4[N,3], labels u2[N]) sampled on every visible surface
  (faces buried in the ground or inside another object are left out);
- `world.export_ply(path)`; `preview.py` shades its classes for `smana world preview`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smana.common.classes import ClassTable

from ..labelled_ply import write_labelled_ply
from .base import WorldError
from .ground import GroundModel, Raster
from .objects import TERRAIN, WorldObject


class World:
    """Ground, objects and walls, plus everything evaluation needs (module docstring)."""

    def __init__(
        self,
        ground: GroundModel,
        objects: list[WorldObject],
        classes: ClassTable | None = None,
        *,
        name: str = "garden",
        seed: int | None = None,
        source_cloud: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.ground = ground
        self.objects = list(objects)
        self.classes = classes or ClassTable.load("garden3drms")
        self.name = name
        self.seed = seed
        # a world built from a labelled cloud keeps that cloud as its ground truth
        self.source_cloud = source_cloud
        self._top: tuple[Raster, Raster] | None = None
        self._gt: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._spawn: dict[float, tuple[float, float, float]] = {}  # spawn_pose, per radius
        used = {int(c) for c in np.unique(ground.classes)} | {o.class_id for o in self.objects}
        missing = sorted(c for c in used if c not in self.classes)
        if missing:
            raise WorldError(f"class ids {missing} are not in class table {self.classes.name!r}")

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
            from scipy import ndimage  # here: a sim on a cached world never needs it (spawn_pose)

            clearance = ndimage.distance_transform_edt(ok) * top.resolution_m
            ok = clearance > robot_radius_m
        return Raster(top.origin_xy, top.resolution_m, ok)

    def free_fraction(self, robot_radius_m: float = 0.0) -> float:
        return float(self.traversability(robot_radius_m).data.mean())

    def terrain_share(self) -> float:
        """Share of the traversable surface seen from above whose class is terrain (the paper's
        3DRMS garden: 0.55, the rest grass)."""
        top = self.top_class().data
        traversable = self.classes.traversable_lut[top]
        return float((top[traversable] == TERRAIN).sum() / max(int(traversable.sum()), 1))

    def reachable_fraction(self, robot_radius_m: float, only_class: int | None = None) -> float:
        """Share of the cells with `robot_radius_m` clearance (of class `only_class`, if given)
        that connect to the spawn pose through such cells, side by side (4-neighbours: a
        diagonal squeeze between two corners does not count)."""
        ok = self.traversability(robot_radius_m)
        if only_class is not None:
            ok = Raster(
                ok.origin_xy, ok.resolution_m, ok.data & (self.top_class().data == only_class)
            )
        if not ok.data.any():
            return 0.0
        x, y, _ = self.spawn_pose(robot_radius_m)
        from scipy import ndimage

        labels, _ = ndimage.label(ok.data)
        here = labels[ok.index_of(x, y)]
        return float((labels == here).sum() / ok.data.sum()) if here else 0.0

    def spawn_pose(self, robot_radius_m: float = 0.45) -> tuple[float, float, float]:
        """(x, y, z_ground) of the free spot nearest the centre with that much clearance. Kept
        per radius: a world read from the world cache carries the sim's (worlds/cache.py)."""
        key = float(robot_radius_m)
        if key not in self._spawn:
            self._spawn[key] = self._find_spawn(key)
        return self._spawn[key]

    def _find_spawn(self, robot_radius_m: float) -> tuple[float, float, float]:
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

    def summary(self, robot_radius_m: float = 0.4) -> dict:
        """What `smana world info` prints; `robot_radius_m` is the navigation graph's safety
        radius (`navgraph.robot_radius_m`). Shares are of the whole raster seen from above,
        walls included, as the paper counts its 48 % free surface."""
        r = robot_radius_m
        counts: dict[str, int] = {}
        for o in self.objects:
            counts[o.kind] = counts.get(o.kind, 0) + 1
        ground = self.ground.classes
        top = self.top_class().data
        # each forbidden class (the wet garden's water): its share of the raster seen from above
        forbidden = {
            f"{c.name}_share": float(np.mean(top == c.id))
            for c in self.classes.classes.values()
            if c.forbidden
        }
        return {
            "name": self.name,
            "bounds": self.bounds,
            "objects": counts,
            "terrain_share_of_ground": float(np.mean(ground == TERRAIN)),
            "free_fraction": self.free_fraction(),
            "free_fraction_r0.35": self.free_fraction(0.35),
            f"free_fraction_r{r:g}": self.free_fraction(r),
            "terrain_share_of_traversable": self.terrain_share(),
            f"reachable_share_r{r:g}": self.reachable_fraction(r),
            f"terrain_reachable_share_r{r:g}": self.reachable_fraction(r, TERRAIN),
            **forbidden,
        }
