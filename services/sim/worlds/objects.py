"""The labelled things a world holds: `WorldObject` (a union of primitives, or voxels for worlds
built from a cloud) and the boundary walls every world gets.

Class ids are those of the class table; the procedural garden and the walls use the 3DRMS garden
ids below (1 grass, 2 terrain, 4 hedge, 5 topiary, 6 rose, 7 obstacle, 8 tree).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import WorldError
from .geometry import BOX, Primitive
from .ground import GroundModel

# 3DRMS class ids of the garden table; a procedural world needs to know which is which.
GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE = 1, 2, 4, 5, 6, 7, 8
WATER = 9  # the wet garden's forbidden class (class table garden3drms_wet, sim.garden.water_share)
SINK_M = 0.05  # objects are sunk a little so that no gap shows between them and a sloped ground


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


def walls(
    ground: GroundModel, height_m: float, thickness_m: float, class_id: int = OBSTACLE
) -> list[WorldObject]:
    """Four boxes along the edges of the ground, `height_m` above its highest point."""
    x0, y0, x1, y1 = ground.extent
    t = thickness_m
    zmin = float(ground.heights.min()) - SINK_M
    ztop = float(ground.heights.max()) + height_m
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
    return [WorldObject("wall", class_id, (b,)) for b in boxes]
