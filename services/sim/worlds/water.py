"""The wet garden (issue 29): ponds of water, a class only semantics can see, on the lawns of a
procedural garden (`sim.garden.water_share` > 0; 0, the default, leaves the world as it was).

Water is flat ground (the height field is not touched) of class 9, kind "forbidden" in the class
table `garden3drms_wet`: geometry sees a lawn, the planner must never enter it. Ponds are placed
where a route that looks only at geometry goes: half of them beside the paths (centred on lawn
0.2 to 0.8 m from the gravel, where corners are cut), half across the open lawns. They cover lawn
only, never gravel, the spawn disk (`plaza_clearance_m`) or ground under an object, so the paths
keep connecting the garden. Each pond is one to three overlapping disks of 0.35 to 0.7 m radius;
ponds are added until the water covers `water_share` of the raster seen from above.

The ponds draw from their own random stream (seeded from the world's seed), so a wet garden is
its dry twin with lawns turned to water: everything else is where it was.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from smana.common.classes import ClassTable

from .base import WorldError
from .ground import GroundModel
from .objects import GRASS, TERRAIN, WATER, WorldObject
from .params import GardenConfig

BESIDE_PATH_M = (0.2, 0.8)  # a pond "beside a path": its centre this far from the gravel
POND_RADIUS_M = (0.35, 0.7)


def check_water_class(classes: ClassTable) -> None:
    if WATER not in classes or not classes[WATER].forbidden:
        raise WorldError(
            f"sim.garden.water_share > 0 needs a class table with water (id {WATER}, kind "
            f'"forbidden"): set general.class_table = "garden3drms_wet" '
            f"({classes.name!r} has none)"
        )


def add_water(
    ground: GroundModel,
    objects: list[WorldObject],
    config: GardenConfig,
    classes: ClassTable,
    seed: int,
) -> GroundModel:
    """`ground` with ponds of WATER on its visible lawn, `config.water_share` of the raster."""
    from .world import World  # the top-down view of the objects

    check_water_class(classes)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x3A7E12]))
    top = World(ground, objects, classes).top_class().data
    res = ground.resolution_m
    nx, ny = ground.shape
    xs = ground.origin_xy[0] + np.arange(nx) * res
    ys = ground.origin_xy[1] + np.arange(ny) * res
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    cx, cy = (xs[0] + xs[-1]) / 2, (ys[0] + ys[-1]) / 2
    spawn = np.hypot(gx - cx, gy - cy) < config.plaza_clearance_m
    lawn = (top == GRASS) & (ground.classes == GRASS) & ~spawn
    # the ground a lawn border may stand on (under the walls the raster is grass as well)
    path = top == TERRAIN
    to_path_m = ndimage.distance_transform_edt(~path) * res
    beside = np.flatnonzero(
        lawn & (to_path_m >= BESIDE_PATH_M[0]) & (to_path_m <= BESIDE_PATH_M[1])
    )
    across = np.flatnonzero(lawn & (to_path_m > BESIDE_PATH_M[1]))
    target = config.water_share * top.size
    water = np.zeros(ground.shape, bool)
    for attempt in range(2000):
        if water.sum() >= target:
            break
        pool = beside if (attempt % 2 == 0 and beside.size) or not across.size else across
        if not pool.size:
            break
        i, j = np.unravel_index(rng.choice(pool), ground.shape)
        pond = np.zeros(ground.shape, bool)
        for _ in range(int(rng.integers(1, 4))):
            r = rng.uniform(*POND_RADIUS_M)
            ox, oy = rng.uniform(-0.5, 0.5, 2) * (r if pond.any() else 0.0)
            pond |= np.hypot(gx - gx[i, j] - ox, gy - gy[i, j] - oy) <= r
        water |= pond & lawn
    classes_ = np.where(water, np.uint16(WATER), ground.classes).astype(np.uint16)
    return GroundModel(ground.origin_xy, res, ground.heights, classes_)
