"""The procedural garden (`sim.world = "garden"`): gentle hills of grass and terrain with gravel
paths across, hedges, topiaries, roses, rocks and boxes, and trees placed with gaps between them,
inside four walls. Like the paper's 3DRMS garden by default (`[sim.garden]`, GardenConfig).

    world = generate(seed=3)                              # the default 12 m garden
    world = generate(seed=1, size_m=30.0, ground_resolution_m=0.2)
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage

from smana.common.classes import ClassTable
from smana.common.config import ConfigError, SimConfig

from .base import WorldError, WorldSource
from .geometry import BOX, CYLINDER, ELLIPSOID, SPHERE, Primitive
from .ground import GroundModel
from .objects import (
    GRASS,
    HEDGE,
    OBSTACLE,
    ROSE,
    SINK_M,
    TERRAIN,
    TOPIARY,
    TREE,
    WorldObject,
    walls,
)
from .params import GardenConfig
from .world import World


class Garden(WorldSource):
    config_key = "garden"
    config_class = GardenConfig
    """`sim.world = "garden"`: from `sim.seed` and `[sim.garden]`."""

    def build(self, config: SimConfig, classes: ClassTable) -> World:
        return generate(config.seed, config.garden, classes)


def generate(
    seed: int = 0,
    config: GardenConfig | None = None,
    classes: ClassTable | None = None,
    **overrides,
) -> World:
    """A procedural garden; the same seed and config always give the same world. `overrides`
    are `GardenConfig` fields (`size_m=6.0`)."""
    try:
        config = dataclasses.replace(config or GardenConfig(), **overrides)
    except ConfigError as exc:
        raise WorldError(str(exc)) from None
    except TypeError as exc:  # a keyword that is not a field
        raise WorldError(f"sim.garden: {exc}") from None
    classes = classes or ClassTable.load("garden3drms")
    for cid in (GRASS, TERRAIN, HEDGE, TOPIARY, ROSE, OBSTACLE, TREE):
        if cid not in classes:
            raise WorldError(
                f"procedural gardens use 3DRMS ids; class {cid} missing from {classes.name}"
            )
    if config.water_share > 0:
        from .water import check_water_class

        check_water_class(classes)  # before the work, not after
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
    if config.layout == "3drms":
        from .garden_3drms import layout_3drms

        ground, placed = layout_3drms(config, _heights(config, rng), rng)
        objects = walls(ground, config.wall_height_m, config.wall_thickness_m) + placed
    elif config.layout == "wheel":
        from .garden_wheel import layout_wheel

        ground, placed = layout_wheel(config, _heights(config, rng), rng)
        objects = walls(ground, config.wall_height_m, config.wall_thickness_m) + placed
    else:
        ground = _make_ground(config, rng)
        objects = walls(ground, config.wall_height_m, config.wall_thickness_m)
        objects += _place_objects(config, ground, rng)
    if config.water_share > 0:  # the wet garden: its dry twin with ponds on the lawns
        from .water import add_water

        ground = add_water(ground, objects, config, classes, seed)
    return World(ground, objects, classes, name=f"garden-{seed}", seed=seed)


def _smooth_noise(rng: np.random.Generator, shape, sigma_cells: float) -> np.ndarray:
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_cells, mode="reflect")
    f -= f.mean()
    return f / (f.std() + 1e-12)


def _heights(cfg: GardenConfig, rng: np.random.Generator) -> np.ndarray:
    """The ground's height field, f8[n, n], vertices `ground_resolution_m` apart."""
    res = cfg.ground_resolution_m
    n = int(round(cfg.size_m / res)) + 1
    # a few metres between bumps: gentle hills, not a washboard
    heights = _smooth_noise(rng, (n, n), 1.5 / res) * (cfg.height_amplitude_m / 2.5)
    if n > 2:
        gx, gy = np.gradient(heights, res)
        steepest = float(np.hypot(gx, gy).max())
        if steepest > cfg.max_slope:
            heights *= cfg.max_slope / steepest
    return heights


def _make_ground(cfg: GardenConfig, rng: np.random.Generator) -> GroundModel:
    res = cfg.ground_resolution_m
    heights = _heights(cfg, rng)
    n = heights.shape[0]
    half = (n - 1) * res / 2
    xs = -half + np.arange(n) * res
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    # gravel paths: straight terrain strips across the garden, as gardens have
    paths = np.zeros((n, n), bool)
    for _ in range(max(1, int(round(cfg.size_m / 8)))):
        angle = rng.uniform(0, math.pi)
        offset = rng.uniform(-0.3, 0.3) * cfg.size_m
        width = rng.uniform(0.8, 1.2)
        dist = np.abs(-math.sin(angle) * gx + math.cos(angle) * gy - offset)
        paths |= dist < width / 2
    patches = _smooth_noise(rng, (n, n), 1.2 / res)
    share_left = (cfg.terrain_fraction - paths.mean()) / max(1.0 - paths.mean(), 1e-9)
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
        return HEDGE, [Primitive(BOX, (0, 0, c - SINK_M), (a, b, c), yaw)]
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
            return OBSTACLE, [Primitive(BOX, (0, 0, c - SINK_M), (a, b, c), yaw)]
        a, b = u(0.25, 0.6), u(0.25, 0.6)  # a rock, half buried
        c = u(0.2, 0.45)
        return OBSTACLE, [Primitive(ELLIPSOID, (0, 0, 0.3 * c), (a, b, c), yaw)]
    if kind == "tree":
        r_trunk, h_trunk = u(0.08, 0.18), u(1.2, 2.2)
        r_crown = u(0.7, 1.3)
        crown_z = h_trunk + 0.6 * r_crown
        return TREE, [
            Primitive(CYLINDER, (0, 0, h_trunk / 2 - SINK_M), (r_trunk, r_trunk, h_trunk / 2)),
            Primitive(SPHERE, (0, 0, crown_z), (r_crown, r_crown, r_crown)),
        ]
    raise WorldError(f"unknown object kind {kind!r}")


def _disk(radius_cells: float) -> np.ndarray:
    r = int(math.ceil(radius_cells))
    g = np.arange(-r, r + 1)
    return (g[:, None] ** 2 + g[None, :] ** 2) <= radius_cells**2 + 1e-9


def _place_objects(
    cfg: GardenConfig, ground: GroundModel, rng: np.random.Generator
) -> list[WorldObject]:
    res = ground.resolution_m
    n = ground.shape[0]
    xs = ground.origin_xy[0] + np.arange(n) * res
    gap_cells = cfg.min_gap_m / res
    # cells an object may not cover: near the walls (plus the gap) and the robot's start disk
    margin = cfg.wall_thickness_m + cfg.min_gap_m
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    x0, y0, x1, y1 = ground.extent
    blocked = (gx < x0 + margin) | (gx > x1 - margin) | (gy < y0 + margin) | (gy > y1 - margin)
    blocked |= np.hypot(gx, gy) < cfg.spawn_clearance_m
    inner_area = max(x1 - x0 - 2 * cfg.wall_thickness_m, 0) ** 2
    target = cfg.clutter * inner_area
    kinds = ["hedge", "topiary", "rose", "obstacle", "tree"]
    weights = np.array([cfg.hedges, cfg.topiaries, cfg.roses, cfg.obstacles, cfg.trees])
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
