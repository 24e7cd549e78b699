"""The planner's dense search window: the NavGrid's tile pools as the gather kernels read them
(`TilePools`), the dense copy the search runs on (`Window`), filled whole (`gather_window`) or
node by node after a patch (`gather_cells`)."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from smana.common.navgrid import FLAG_KNOWN, NavGrid


class TilePools(NamedTuple):
    """The NavGrid's node layers as the gather kernels read them: pools of (slot, T, T)."""

    tile_map: np.ndarray  # (ntx, nty) int32: slot of each tile, < 0 where not allocated
    labels: np.ndarray
    heights: np.ndarray
    flags: np.ndarray
    tile_size: int

    @classmethod
    def of(cls, g: NavGrid) -> TilePools:
        return cls(g.tile_map, g.layer("labels"), g.layer("heights"), g.layer("flags"), g.tile_size)


class Window(NamedTuple):
    """The planner's dense copy of a window of the grid."""

    labels: np.ndarray  # u2 (w, h)
    flags: np.ndarray  # u1 (w, h)
    known_h: np.ndarray  # f4 (w, h): heights, NaN where not known


@numba.njit(cache=True)
def gather_window(pools, ix0, iy0, window):
    """Fill `window` (dense labels, flags and known heights, NaN where not known) with the w x h
    nodes from (ix0, iy0), (w, h) its shape, from the tile pools; unallocated tiles read as
    unknown. Walks tile by tile along y so that no division happens per node."""
    tile_map, labels_pool, heights_pool, flags_pool, t = pools
    labels, flags, known_h = window
    w, h = labels.shape
    for i in range(w):
        gx = ix0 + i
        tx = gx // t
        lx = gx - tx * t
        j = 0
        while j < h:
            gy = iy0 + j
            ty = gy // t
            ly0 = gy - ty * t
            run = min(t - ly0, h - j)
            slot = tile_map[tx, ty]
            if slot >= 0:
                for k in range(run):
                    f = flags_pool[slot, lx, ly0 + k]
                    flags[i, j + k] = f
                    labels[i, j + k] = labels_pool[slot, lx, ly0 + k]
                    known_h[i, j + k] = (
                        heights_pool[slot, lx, ly0 + k] if f & FLAG_KNOWN else np.nan
                    )
            else:
                for k in range(run):
                    flags[i, j + k] = 0
                    labels[i, j + k] = 0
                    known_h[i, j + k] = np.nan
            j += run


@numba.njit(cache=True)
def gather_cells(pools, grid_cells, cells, window):
    """`gather_window` for a list of nodes: `grid_cells` in the grid, `cells` in the window."""
    tile_map, labels_pool, heights_pool, flags_pool, t = pools
    labels, flags, known_h = window
    for k in range(len(cells)):
        gx, gy = grid_cells[k, 0], grid_cells[k, 1]
        i, j = cells[k, 0], cells[k, 1]
        slot = tile_map[gx // t, gy // t]
        if slot >= 0:
            lx, ly = gx % t, gy % t
            f = flags_pool[slot, lx, ly]
            flags[i, j] = f
            labels[i, j] = labels_pool[slot, lx, ly]
            known_h[i, j] = heights_pool[slot, lx, ly] if f & FLAG_KNOWN else np.nan
        else:
            flags[i, j] = 0
            labels[i, j] = 0
            known_h[i, j] = np.nan
