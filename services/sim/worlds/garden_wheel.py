"""The "wheel" layout of the procedural garden (`sim.garden.layout = "wheel"`): the "3drms"
layout's statistics (48 % of the surface free, 55 % of it terrain) in a garden where grass is a
way through, so that the grass cost has something to decide (docs/experiments.md, "A garden where
the grass cost decides": `smana experiment routes --layout wheel`).

In the "3drms" layout the gravel paths are the only way between places: lawns hang off them, so
the cheapest routes travel 66 % terrain when grass costs what terrain costs and 82 % from a grass
cost of x1.25 up: nothing is left for a higher cost to decide. Here the garden is a round lawn:
a central lawn circle, where the robot starts, seven gravel spokes (terrain) from its edge, and
grass between the spokes out to a rim of grass walks from spoke end to spoke end. A trip between
two spokes can cross the grass or follow the gravel round by the central lawn's edge, 1.9 times
longer between the spokes' ends (4.3 m out) and less further in, and a trip across the garden
crosses the central lawn or goes round its edge (pi / 2 = 1.6 times longer); the planner charges
grass at x2 1.8 times and at x4 3.4 times what terrain costs per metre, so the choice moves with
the grass cost. Beds fill the corners
and what the grass leaves between the spokes, planted as in "3drms" (hedges lining them, then
plants in the holes). Made for the experiments' 12 m garden (seeds 3 to 12:
tests/test_garden_stats.py); a 6 m garden has room for short spokes only (42 % free, 34 % of it
terrain), and larger gardens get more rims but not the statistics.

    ground, objects = layout_wheel(config, heights, rng)    # garden.generate() calls it
"""

from __future__ import annotations

import math

import numpy as np

from smana.services.sim.worlds.garden import GardenConfig

from .garden_3drms import BED_GAPS, Placer, edge_hedges, fill_beds, raster
from .ground import GroundModel
from .objects import GRASS, TERRAIN, WorldObject

# a rim walk is 2 sin(pi / SPOKES) = 0.87 spoke long: with the central lawn's radius, the way
# round on gravel is 1.9 times longer at the spokes' ends (6 spokes: 1.7, 8: 2.1)
SPOKES = 7
RIM_SPACING_M = 5.0  # rims about this far apart: a 12 m garden has one, a 30 m garden three
# the central lawn, where the robot starts; the spokes begin at its edge, where neighbours touch
# (7 spokes 1.4 m wide are 1.35 m apart there): a trip across the garden crosses the lawn or goes
# round it on the spokes' ends
HUB_RADIUS_M = 1.5
WALL_MARGIN_M = 0.5  # beds at least this wide between the outer rim and the walls
# the beds here are narrower than "3drms"'s: fewer bare gaps, measured 2-3 % of the raster
GAPS_SHARE = 0.5 * BED_GAPS


def layout_wheel(
    cfg: GardenConfig, heights: np.ndarray, rng: np.random.Generator
) -> tuple[GroundModel, list[WorldObject]]:
    """The ground (classes on `heights`) and the objects, walls excepted."""
    res, half, gx, gy, inner = raster(cfg, heights)
    n_cells = gx.size  # the stats count the whole raster, walls included
    terrain_target = (cfg.free_share * cfg.terrain_share - GAPS_SHARE) * n_cells
    grass_target = cfg.free_share * (1 - cfg.terrain_share) * n_cells
    terrain, grass = _wheel(cfg, gx, gy, half, terrain_target, grass_target, rng)
    terrain &= inner
    grass &= inner
    bed = inner & ~terrain & ~grass
    classes = np.where(grass | ~inner, GRASS, TERRAIN).astype(np.uint16)
    ground = GroundModel((-half, -half), res, heights, classes)

    placer = Placer(ground, gx, gy)
    objects = edge_hedges(placer, bed, terrain | grass | ~inner, rng)
    objects += fill_beds(placer, bed, rng)
    return ground, objects


def _distance_to_segment(gx, gy, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    t = ((gx - a[0]) * d[0] + (gy - a[1]) * d[1]) / max(float(d @ d), 1e-12)
    t = np.clip(t, 0.0, 1.0)
    return np.hypot(gx - a[0] - t * d[0], gy - a[1] - t * d[1])


def _fit(area, target: float, lo: float, hi: float) -> float:
    """x in [lo, hi] whose area(x) (growing with x) comes nearest `target`, by bisection."""
    for _ in range(14):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if area(mid) < target else (lo, mid)
    return (lo + hi) / 2


def _wheel(cfg, gx, gy, half, terrain_target, grass_target, rng):
    """(terrain, grass) masks: the spokes, `path_width_m[0]` wide, their length fitted to
    `terrain_target` cells; the central lawn and the rims (walks from spoke end to spoke end),
    their widths fitted to `grass_target` cells within `path_width_m`."""
    w_min, w_max = cfg.path_width_m
    lim = max(half - cfg.wall_thickness_m - WALL_MARGIN_M - w_max / 2, 1.0)
    angles = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.arange(SPOKES) / SPOKES
    angles += rng.uniform(-0.12, 0.12, SPOKES)  # a garden drawn by hand, not by compass
    stretch = rng.uniform(0.9, 1.1, SPOKES)
    stretch /= stretch.max()  # the longest spoke reaches the outer rim's radius
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    n_rims = max(1, int(round(lim / RIM_SPACING_M)))
    centre = np.hypot(gx, gy)
    hub = centre <= HUB_RADIUS_M

    def spokes(radius_m):
        # narrow, so that the terrain budget makes them long: the rim walks lie far out
        m = np.zeros(gx.shape, bool)
        for d, s in zip(dirs, stretch, strict=True):
            m |= _distance_to_segment(gx, gy, np.zeros(2), d * radius_m * s) <= w_min / 2
        return m & ~hub

    radius = _fit(lambda r: spokes(r).sum(), terrain_target, HUB_RADIUS_M + 0.5, lim)
    terrain = spokes(radius)
    rim_w = rng.uniform(w_min, w_max, (n_rims, SPOKES))
    rim_d = []
    for k in range(1, n_rims + 1):
        ends = dirs * (stretch * radius * k / n_rims)[:, None]
        rim_d.append(
            [_distance_to_segment(gx, gy, ends[i], ends[(i + 1) % SPOKES]) for i in range(SPOKES)]
        )

    def rims(shift_m):
        m = hub.copy()
        for ds, ws in zip(rim_d, rim_w, strict=True):
            for d, w in zip(ds, np.clip(ws + shift_m, w_min, w_max), strict=True):
                m |= d <= w / 2
        return m & ~terrain

    shift = _fit(lambda s: rims(s).sum(), grass_target, -(w_max - w_min), w_max - w_min)
    return terrain, rims(shift)
