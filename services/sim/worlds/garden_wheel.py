"""The "wheel" layout of the procedural garden (`sim.garden.layout = "wheel"`): the "3drms"
layout's statistics (48 % of the surface free, 55 % of it terrain) with grass that is a way
through, built to test whether the grass cost can decide routes (docs/experiments.md, "A garden
whose grass is a way through").

In the "3drms" layout the gravel paths are the only way between places: lawns hang off them, so
the cheapest routes travel 66 % terrain when grass costs what terrain costs and 82 % from a grass
cost of x1.25 up (`smana experiment routes`). Here the garden is a wheel: six gravel spokes
(terrain) from a central plaza with a small lawn at its middle, and a rim of grass walks joining
the spokes' ends. Between two neighbouring spoke ends the way round on gravel, through the centre,
is 1 / sin(pi / 6) = 2 times the rim walk's length, so the choice between walk and gravel is still
open at grass x2 (the planner charges 1.8 times terrain's cost per metre) and made at x4 (3.4
times). Beds fill the corners and the gaps between spokes, planted as in "3drms" (hedges lining
them, then plants in the holes).

    ground, objects = layout_wheel(config, heights, rng)    # garden.generate() calls it
"""

from __future__ import annotations

import math

import numpy as np

from smana.common.config.sim import GardenConfig

from .garden_3drms import BED_GAPS, _edge_hedges, _fill_beds, _Placer
from .ground import GroundModel
from .objects import GRASS, TERRAIN, WorldObject

SPOKES = 6  # a rim walk is 2 sin(pi / SPOKES) = 1 spoke long: half the way round (5: 0.59 of it)
RIM_SPACING_M = 5.0  # rims about this far apart: a 12 m garden has one, a 30 m garden three
SPAWN_RADIUS_M = 1.2  # the central plaza: the robot starts on it
HUB_RADIUS_M = 0.8  # the lawn at the plaza's middle, so a trip across passes grass at x1
WALL_MARGIN_M = 0.5  # beds at least this wide between the outer rim and the walls
# the beds here are narrower than "3drms"'s: fewer bare gaps, measured 2-3 % of the raster
GAPS_SHARE = 0.5 * BED_GAPS


def layout_wheel(
    cfg: GardenConfig, heights: np.ndarray, rng: np.random.Generator
) -> tuple[GroundModel, list[WorldObject]]:
    """The ground (classes on `heights`) and the objects, walls excepted."""
    res = cfg.ground_resolution_m
    n = heights.shape[0]
    half = (n - 1) * res / 2
    xs = -half + np.arange(n) * res
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    edge_m = np.minimum(half - np.abs(gx), half - np.abs(gy))
    inner = edge_m > cfg.wall_thickness_m - res / 2
    n_cells = n * n  # the stats count the whole raster, walls included
    terrain_target = (cfg.free_share * cfg.terrain_share - GAPS_SHARE) * n_cells
    grass_target = cfg.free_share * (1 - cfg.terrain_share) * n_cells
    terrain, grass = _wheel(cfg, gx, gy, half, terrain_target, grass_target, rng)
    terrain &= inner
    grass &= inner
    bed = inner & ~terrain & ~grass
    classes = np.where(grass | ~inner, GRASS, TERRAIN).astype(np.uint16)
    ground = GroundModel((-half, -half), res, heights, classes)

    placer = _Placer(ground, gx, gy)
    objects = _edge_hedges(placer, bed, terrain | grass | ~inner, rng)
    objects += _fill_beds(placer, bed, rng)
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
    """(terrain, grass) masks: the plaza and the spokes, `path_width_m[0]` wide, their length
    fitted to `terrain_target` cells; the hub and the rims (walks from spoke end to spoke end),
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
        m = centre <= SPAWN_RADIUS_M
        for d, s in zip(dirs, stretch, strict=True):
            m |= _distance_to_segment(gx, gy, np.zeros(2), d * radius_m * s) <= w_min / 2
        return m & ~hub

    radius = _fit(lambda r: spokes(r).sum(), terrain_target, SPAWN_RADIUS_M + 0.5, lim)
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
