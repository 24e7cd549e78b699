"""Worlds from a labelled point cloud (paper 4.1; `sim.world = "ply:PATH"` or a path to a .ply):
points of traversable classes become the height field (the median height and the majority class
per cell), points of every other class become voxels of `voxel_m`, one body per class. Walls are
added around it. Knobs: `[sim.ply]` (PlyConfig).

    world = from_ply("garden.ply")
    world = from_cloud(points, labels, voxel_m=0.1)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import ndimage

from smana.common.classes import ClassTable
from smana.common.config import ConfigError, SimConfig

from ..labelled_ply import read_labelled_ply
from .base import WorldError, WorldSource
from .ground import GroundModel
from .objects import WorldObject, walls
from .params import PlyConfig
from .world import World


class PlyWorld(WorldSource):
    config_key = "ply"
    config_class = PlyConfig
    """`sim.world = "ply:PATH"`: the labelled cloud at PATH, with `[sim.ply]`."""

    def build(self, config: SimConfig, classes: ClassTable) -> World:
        path = self.arg or ""
        if not Path(path).is_file():
            raise WorldError(f"sim.world: {config.world!r} is neither 'garden' nor a PLY file")
        return from_ply(path, classes, config.ply)


def from_ply(
    path: str | Path,
    classes: ClassTable | None = None,
    config: PlyConfig | None = None,
    **overrides,
) -> World:
    """A world from a labelled PLY file (module docstring); `overrides` are PlyConfig fields."""
    config = _config(config, overrides)
    points, labels = read_labelled_ply(path, config.label_field or None)
    return from_cloud(points, labels, classes, config, name=Path(path).stem)


def from_cloud(
    points: np.ndarray,
    labels: np.ndarray,
    classes: ClassTable | None = None,
    config: PlyConfig | None = None,
    *,
    name: str = "cloud",
    **overrides,
) -> World:
    """A world from points (N, 3) and their class ids (N,) (module docstring)."""
    cfg = _config(config, overrides)
    classes = classes or ClassTable.load("garden3drms")
    points = np.asarray(points, np.float64)
    labels = np.asarray(labels, np.int64)
    if points.ndim != 2 or points.shape[1] != 3 or len(labels) != len(points):
        raise WorldError("expected points (N,3) and labels (N,)")
    finite = np.all(np.isfinite(points), axis=1)
    points, labels = points[finite], labels[finite]
    labels, n_bad = classes.sanitise(labels)
    if n_bad:
        raise WorldError(f"{n_bad} points carry ids that are not in {classes.name!r}")
    is_ground = classes.traversable_lut[labels]
    is_object = ~is_ground & (labels != 0) & ~classes.ignored_lut[labels]
    if not is_ground.any():
        raise WorldError("the cloud has no points of a traversable class to build ground from")
    ground = _ground_from_points(points[is_ground], labels[is_ground], cfg.ground_resolution_m)
    objects = []
    voxel_m = cfg.voxel_m
    for cid in np.unique(labels[is_object]):
        sel = points[is_object & (labels == cid)]
        q = np.unique(np.floor(sel / voxel_m).astype(np.int64), axis=0)
        centres = (q + 0.5) * voxel_m
        objects.append(WorldObject("voxels", int(cid), voxel_centres=centres, voxel_m=voxel_m))
    if cfg.walls:
        wall_class = next(
            (c.id for c in classes.classes.values() if c.obstacle and c.name == "obstacle"),
            None,
        ) or next(c.id for c in classes.classes.values() if c.obstacle)
        objects = walls(ground, cfg.wall_height_m, cfg.wall_thickness_m, wall_class) + objects
    keep = labels != 0
    return World(ground, objects, classes, name=name, source_cloud=(points[keep], labels[keep]))


def _config(config: PlyConfig | None, overrides: dict) -> PlyConfig:
    try:
        return dataclasses.replace(config or PlyConfig(), **overrides)
    except ConfigError as exc:
        raise WorldError(str(exc)) from None
    except TypeError as exc:  # a keyword that is not a field
        raise WorldError(f"sim.ply: {exc}") from None


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
