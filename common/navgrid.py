"""The tiled 2.5D navigation grid: navgraph builds it, the planner keeps a copy from its patches.

The grid covers fixed bounds given at start, but memory is only allocated for square tiles of
`tile_size` x `tile_size` nodes that received data (paper 3.3.1: nodes are allocated only when map
data at their position arrives). A small dense `tile_map` (one int32 per tile over the bounds)
points into a pool of allocated tiles; every per-node layer is a pool array of shape
(capacity, T, T), so a node's flat index `slot * T * T + lx * T + ly` stays valid as the pool grows.

Layers every grid has: `labels` (u2 class id), `heights` (f4 metres, NaN where unknown) and `flags`
(u1: FLAG_KNOWN | FLAG_OBSTACLE | FLAG_SAFETY_ZONE | FLAG_DOUBTFUL, the bits GraphPatch carries).
Navgraph adds its own bookkeeping layers with `add_layer`; the planner only needs the three above.

Optional layers (`RISK_LAYERS`, added by `add_risk_layers`) hold how sure the map is of a node's
label: `alt_labels` (u2, the second most likely class id, 0 = none), `p_label` (u1, probability of
the `labels` class x 255, rounded) and `p_alt` (u1, probability of `alt_labels` x 255); the rest,
`1 - (p_label + p_alt) / 255`, is "other or unknown". A grid without them, or a node never given a
distribution, reads as certain: p_label 255, p_alt 0.

Cells are integer (ix, iy) indices from `origin_xy` (the bounds' minimum corner): node (ix, iy)
covers [origin + i * res, origin + (i + 1) * res) and its centre is at origin + (i + 0.5) * res.
"""

from __future__ import annotations

import collections

import numpy as np

# Node flags: bits of a node's `flags` layer, and of GraphPatch.flags on the wire. This module
# needs no codec, so the navgraph and planner cores import them from here.
CHANGE_LOG = 64  # versions whose changed cells a NavGrid remembers
FLAG_KNOWN = 1
FLAG_OBSTACLE = 2
FLAG_SAFETY_ZONE = 4
# A known node showing an obstacle class with an uncertain label and no height over its column's
# lowest voxel: passable, at the planner's `doubtful_cost`, and no centre of the safety zone
# (services/navgraph/graph.py).
FLAG_DOUBTFUL = 8

UNALLOCATED = -1
# The optional label-distribution layers: (name, dtype, fill). The fills read as certain.
P_SCALE = 255  # p_label and p_alt are probabilities x P_SCALE, rounded
RISK_LAYERS = (
    ("alt_labels", np.uint16, 0),
    ("p_label", np.uint8, P_SCALE),
    ("p_alt", np.uint8, 0),
)
RISK_LAYER_NAMES = tuple(name for name, _, _ in RISK_LAYERS)
_RISK_SPEC = {name: (dtype, fill) for name, dtype, fill in RISK_LAYERS}
MAX_NODES_PER_AXIS = 1 << 20  # cells travel as int32; keeps tile arithmetic far from overflow


class NavGrid:
    """A bounded 2.5D grid of nodes stored in lazily allocated tiles.

    Reading an unallocated node gives label 0, height NaN, flags 0 (unknown).
    """

    def __init__(
        self,
        origin_xy: tuple[float, float],
        shape: tuple[int, int],
        resolution_m: float,
        tile_size: int = 32,
        initial_tiles: int = 16,
    ):
        nx, ny = (int(s) for s in shape)
        if not (0 < nx <= MAX_NODES_PER_AXIS and 0 < ny <= MAX_NODES_PER_AXIS):
            raise ValueError(f"grid shape must be 1..{MAX_NODES_PER_AXIS} per axis, got {shape}")
        if not (np.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        if not 1 <= int(tile_size) <= 256:
            raise ValueError(f"tile_size must be 1..256, got {tile_size}")
        origin = np.asarray(origin_xy, np.float64).reshape(-1)
        if origin.shape != (2,) or not np.isfinite(origin).all():
            raise ValueError(f"origin_xy must be two finite numbers, got {origin_xy}")
        self.origin_xy = origin
        self.shape = (nx, ny)
        self.resolution_m = float(resolution_m)
        self.tile_size = int(tile_size)
        t = self.tile_size
        self.tiles_shape = (-(-nx // t), -(-ny // t))
        self.tile_map = np.full(self.tiles_shape, UNALLOCATED, np.int32)
        self.n_tiles = 0
        self._capacity = max(1, int(initial_tiles))
        self.tile_coords = np.zeros((self._capacity, 2), np.int32)  # slot -> (tx, ty)
        self._layers: dict[str, np.ndarray] = {}
        self._fills: dict[str, object] = {}
        self.add_layer("labels", np.uint16, 0)
        self.add_layer("heights", np.float32, np.nan)
        self.add_layer("flags", np.uint8, 0)
        # Bumped on every change so readers (the planner's dense window) can cache; the last
        # changes are logged by version so a reader can refresh only the cells that changed.
        self.version = 0
        self._changes: collections.deque = collections.deque(maxlen=CHANGE_LOG)

    @classmethod
    def from_bounds(
        cls,
        bounds_min_xy,
        bounds_max_xy,
        resolution_m: float,
        tile_size: int = 32,
        initial_tiles: int = 16,
    ) -> NavGrid:
        lo = np.asarray(bounds_min_xy, np.float64).reshape(-1)
        hi = np.asarray(bounds_max_xy, np.float64).reshape(-1)
        if (
            lo.shape != (2,)
            or hi.shape != (2,)
            or not (np.isfinite(lo).all() and np.isfinite(hi).all())
        ):
            raise ValueError("bounds must be two finite (x, y) pairs")
        if not (hi > lo).all():
            raise ValueError(f"bounds_max_xy {hi.tolist()} must exceed bounds_min_xy {lo.tolist()}")
        if not (np.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        # A node is kept when its cell starts inside the bounds; the last one may reach past them.
        shape = tuple(int(np.ceil((hi[i] - lo[i]) / resolution_m - 1e-9)) for i in range(2))
        return cls(lo, shape, resolution_m, tile_size, initial_tiles)

    # -- layers ----------------------------------------------------------------------------------

    def add_layer(self, name: str, dtype, fill) -> np.ndarray:
        if name in self._layers:
            raise ValueError(f"layer {name!r} exists")
        t = self.tile_size
        self._layers[name] = np.full((self._capacity, t, t), fill, dtype)
        self._fills[name] = fill
        return self._layers[name]

    def add_risk_layers(self) -> None:
        """Add the label-distribution layers (`RISK_LAYERS`), every node certain; idempotent."""
        for name, dtype, fill in RISK_LAYERS:
            if name not in self._layers:
                self.add_layer(name, dtype, fill)

    def has_risk(self) -> bool:
        """Whether the grid holds the label-distribution layers (without them it reads certain)."""
        return all(name in self._layers for name in RISK_LAYER_NAMES)

    def layer(self, name: str) -> np.ndarray:
        """The pool array (capacity, T, T) of a layer. Re-fetch after allocating tiles."""
        return self._layers[name]

    def flat(self, name: str) -> np.ndarray:
        """A layer as a flat view indexed by flat node index (for numba kernels)."""
        return self._layers[name].reshape(-1)

    @property
    def labels(self) -> np.ndarray:
        return self._layers["labels"]

    @property
    def heights(self) -> np.ndarray:
        return self._layers["heights"]

    @property
    def flags(self) -> np.ndarray:
        return self._layers["flags"]

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def nbytes(self) -> int:
        """Bytes held by the grid: the tile map plus every layer's pool (allocated capacity)."""
        return int(
            self.tile_map.nbytes
            + self.tile_coords.nbytes
            + sum(a.nbytes for a in self._layers.values())
        )

    @property
    def n_nodes_allocated(self) -> int:
        return self.n_tiles * self.tile_size * self.tile_size

    def n_known(self) -> int:
        return int(np.count_nonzero(self.flags[: self.n_tiles] & FLAG_KNOWN))

    # -- geometry --------------------------------------------------------------------------------

    def world_to_cell(self, xy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ix, iy) int64 arrays and an in-bounds mask for world points (..., 2)."""
        xy = np.asarray(xy, np.float64)
        idx = np.floor((xy - self.origin_xy) / self.resolution_m)
        ok = np.isfinite(idx).all(axis=-1)
        idx = np.where(np.isfinite(idx), idx, -1).astype(np.int64)
        ix, iy = idx[..., 0], idx[..., 1]
        ok &= (ix >= 0) & (iy >= 0) & (ix < self.shape[0]) & (iy < self.shape[1])
        return ix, iy, ok

    def cell_centre(self, ix, iy) -> np.ndarray:
        """World (x, y) of node centres, shape (..., 2)."""
        ix = np.asarray(ix, np.float64)
        iy = np.asarray(iy, np.float64)
        res = self.resolution_m
        return np.stack(
            [self.origin_xy[0] + (ix + 0.5) * res, self.origin_xy[1] + (iy + 0.5) * res], axis=-1
        )

    def in_bounds(self, ix, iy) -> np.ndarray:
        ix = np.asarray(ix)
        iy = np.asarray(iy)
        return (ix >= 0) & (iy >= 0) & (ix < self.shape[0]) & (iy < self.shape[1])

    # -- allocation ------------------------------------------------------------------------------

    def _grow(self, need: int) -> None:
        if need <= self._capacity:
            return
        cap = self._capacity
        while cap < need:
            cap *= 2
        t = self.tile_size
        for name, arr in self._layers.items():
            new = np.full((cap, t, t), self._fills[name], arr.dtype)
            new[: self._capacity] = arr
            self._layers[name] = new
        coords = np.zeros((cap, 2), np.int32)
        coords[: self._capacity] = self.tile_coords
        self.tile_coords = coords
        self._capacity = cap

    def allocate_tiles(self, tx, ty) -> int:
        """Allocate the tiles (tx, ty) that are not yet allocated; returns how many were new."""
        tx = np.asarray(tx, np.int64).reshape(-1)
        ty = np.asarray(ty, np.int64).reshape(-1)
        if tx.size == 0:
            return 0
        ntx, nty = self.tiles_shape
        if (tx < 0).any() or (ty < 0).any() or (tx >= ntx).any() or (ty >= nty).any():
            raise ValueError("tile index outside the grid")
        missing = self.tile_map[tx, ty] == UNALLOCATED
        if not missing.any():
            return 0
        ids = np.unique(tx[missing] * nty + ty[missing])
        n_new = len(ids)
        self._grow(self.n_tiles + n_new)
        slots = np.arange(self.n_tiles, self.n_tiles + n_new, dtype=np.int32)
        mtx, mty = ids // nty, ids % nty
        self.tile_map[mtx, mty] = slots
        self.tile_coords[slots, 0] = mtx
        self.tile_coords[slots, 1] = mty
        self.n_tiles += n_new
        # New tiles hold the fill values, which is what an unallocated node reads as: no node
        # a reader sees changed.
        self.changed(np.zeros((0, 2), np.int32))
        return n_new

    def allocate_cells(self, ix, iy) -> int:
        t = self.tile_size
        return self.allocate_tiles(np.asarray(ix) // t, np.asarray(iy) // t)

    def flat_index(self, ix, iy) -> np.ndarray:
        """Flat node indices of in-bounds cells; -1 where the tile is not allocated."""
        ix = np.asarray(ix, np.int64)
        iy = np.asarray(iy, np.int64)
        t = self.tile_size
        slot = self.tile_map[ix // t, iy // t].astype(np.int64)
        flat = slot * (t * t) + (ix % t) * t + (iy % t)
        return np.where(slot >= 0, flat, -1)

    def cells_of_flat(self, flat) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of flat_index for allocated nodes."""
        flat = np.asarray(flat, np.int64)
        t = self.tile_size
        slot, local = flat // (t * t), flat % (t * t)
        ix = self.tile_coords[slot, 0].astype(np.int64) * t + local // t
        iy = self.tile_coords[slot, 1].astype(np.int64) * t + local % t
        return ix, iy

    # -- reading and writing nodes ---------------------------------------------------------------

    def _check_cells(self, cells) -> np.ndarray:
        cells = np.asarray(cells)
        if cells.ndim != 2 or cells.shape[1] != 2 or cells.dtype.kind not in "iu":
            raise ValueError(
                f"cells must be an integer array (K, 2), got {cells.dtype} {cells.shape}"
            )
        return cells.astype(np.int64, copy=False)

    def read_cells(self, cells) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """labels, heights, flags of (K, 2) cells; out-of-bounds or unallocated read as unknown."""
        cells = self._check_cells(cells)
        k = len(cells)
        labels = np.zeros(k, np.uint16)
        heights = np.full(k, np.nan, np.float32)
        flags = np.zeros(k, np.uint8)
        ok = self.in_bounds(cells[:, 0], cells[:, 1])
        flat = np.full(k, -1, np.int64)
        flat[ok] = self.flat_index(cells[ok, 0], cells[ok, 1])
        have = flat >= 0
        labels[have] = self.flat("labels")[flat[have]]
        heights[have] = self.flat("heights")[flat[have]]
        flags[have] = self.flat("flags")[flat[have]]
        return labels, heights, flags

    def geometry_mismatch(self, resolution_m: float, origin_xy) -> str:
        """Why nodes laid out at `resolution_m` from `origin_xy` (a GraphPatch's) are not this
        grid's nodes, or "" when they are."""
        if abs(resolution_m - self.resolution_m) <= 1e-9 and np.allclose(origin_xy, self.origin_xy):
            return ""
        return (
            f"nodes at {resolution_m} m from {np.asarray(origin_xy).tolist()}, the grid's at "
            f"{self.resolution_m} m from {self.origin_xy.tolist()}"
        )

    def read_risk(self, cells) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """alt_labels, p_label, p_alt of (K, 2) cells; a grid without the layers, and nodes out of
        bounds or unallocated, read as certain (0, 255, 0)."""
        cells = self._check_cells(cells)
        k = len(cells)
        out = tuple(np.full(k, fill, dtype) for _, dtype, fill in RISK_LAYERS)
        if not self.has_risk() or k == 0:
            return out
        ok = self.in_bounds(cells[:, 0], cells[:, 1])
        flat = np.full(k, -1, np.int64)
        flat[ok] = self.flat_index(cells[ok, 0], cells[ok, 1])
        have = flat >= 0
        for a, name in zip(out, RISK_LAYER_NAMES, strict=True):
            a[have] = self.flat(name)[flat[have]]
        return out

    def apply_patch(self, cells, labels, heights, flags, risk=None) -> int:
        """Write nodes (allocating their tiles). Returns how many cells were out of bounds and
        skipped. A patch lists each node once; if one repeats, the last value wins.

        `risk` is (alt_labels, p_label, p_alt) per cell, or None for a patch that carries no
        distribution: its nodes are then certain. Risk layers are added on the first patch that
        carries them; `p_alt` is cut to `255 - p_label`, and to 0 where `alt_labels` is 0."""
        cells = self._check_cells(cells)
        labels = np.asarray(labels)
        heights = np.asarray(heights, np.float32)
        flags = np.asarray(flags)
        k = len(cells)
        if not (len(labels) == len(heights) == len(flags) == k):
            raise ValueError("cells, labels, heights and flags must have the same length")
        if risk is not None:
            risk = tuple(np.asarray(a) for a in risk)
            if len(risk) != len(RISK_LAYERS) or any(len(a) != k for a in risk):
                raise ValueError("risk must be (alt_labels, p_label, p_alt), one value per cell")
            # what a patch from anywhere may hold: a second class 0 has no probability, and the
            # two probabilities never pass 1
            alt, p_label, p_alt = (
                a.astype(d, copy=False) for a, (_, d, _) in zip(risk, RISK_LAYERS)
            )
            p_alt = np.where(alt == 0, 0, np.minimum(p_alt, P_SCALE - p_label)).astype(np.uint8)
            risk = (alt, p_label, p_alt)
            self.add_risk_layers()
        ok = self.in_bounds(cells[:, 0], cells[:, 1])
        n_bad = int(k - ok.sum())
        if n_bad:
            cells, labels, heights, flags = cells[ok], labels[ok], heights[ok], flags[ok]
            if risk is not None:
                risk = tuple(a[ok] for a in risk)
        if len(cells) == 0:
            return n_bad
        self.allocate_cells(cells[:, 0], cells[:, 1])
        flat = self.flat_index(cells[:, 0], cells[:, 1])
        self.flat("labels")[flat] = labels
        self.flat("heights")[flat] = heights
        self.flat("flags")[flat] = flags
        if self.has_risk():
            for i, name in enumerate(RISK_LAYER_NAMES):
                fill = _RISK_SPEC[name][1]
                self.flat(name)[flat] = fill if risk is None else risk[i]
        self.changed(cells)
        return n_bad

    def changed(self, cells: np.ndarray | None) -> None:
        """A new version: the nodes at `cells` (K, 2) changed, or None when a writer cannot say
        which (a reader then rebuilds what it cached)."""
        self.version += 1
        self._changes.append((self.version, None if cells is None else np.array(cells, np.int32)))

    def changes_since(self, version: int) -> np.ndarray | None:
        """The cells (K, 2) written after `version`, repeats included; None when the log does
        not reach back that far or a change there was not told by cells."""
        if version == self.version:
            return np.zeros((0, 2), np.int32)
        if version > self.version or not self._changes or self._changes[0][0] > version + 1:
            return None
        out = []
        for v, cells in self._changes:
            if v > version:
                if cells is None:
                    return None
                out.append(cells)
        return np.concatenate(out) if out else np.zeros((0, 2), np.int32)

    def known_box(self) -> tuple[int, int, int, int] | None:
        """Half-open cell box (ix0, iy0, ix1, iy1) covering every allocated tile, or None."""
        if self.n_tiles == 0:
            return None
        tc = self.tile_coords[: self.n_tiles]
        t = self.tile_size
        ix0, iy0 = (int(v) * t for v in tc.min(axis=0))
        ix1, iy1 = ((int(v) + 1) * t for v in tc.max(axis=0))
        return ix0, iy0, min(ix1, self.shape[0]), min(iy1, self.shape[1])

    def box(self, ix0: int, iy0: int, ix1: int, iy1: int, layers=("labels", "heights", "flags")):
        """Dense arrays [ix1 - ix0, iy1 - iy0] of the given layers over a half-open cell box
        (clipped to the grid); unallocated nodes take the layer's fill value. Returns a tuple.
        A risk layer the grid does not hold reads as its fill (certain)."""
        ix0, iy0 = max(0, int(ix0)), max(0, int(iy0))
        ix1, iy1 = min(self.shape[0], int(ix1)), min(self.shape[1], int(iy1))
        w, h = max(0, ix1 - ix0), max(0, iy1 - iy0)
        absent = {n for n in layers if n not in self._layers and n in _RISK_SPEC}
        if w == 0 or h == 0 or absent:
            if w == 0 or h == 0:
                return tuple(np.zeros((w, h), self._dtype(n)) for n in layers)
            got = iter(self.box(ix0, iy0, ix1, iy1, [n for n in layers if n not in absent]))
            return tuple(
                np.full((w, h), _RISK_SPEC[n][1], _RISK_SPEC[n][0]) if n in absent else next(got)
                for n in layers
            )
        t = self.tile_size
        tx0, ty0, tx1, ty1 = ix0 // t, iy0 // t, (ix1 - 1) // t + 1, (iy1 - 1) // t + 1
        slots = self.tile_map[tx0:tx1, ty0:ty1]
        have = slots >= 0
        out = []
        for name in layers:
            pool = self._layers[name]
            # Gather whole tiles, then lay them out as one dense block and crop.
            block = pool[np.where(have, slots, 0)]  # (ntx, nty, T, T)
            block = np.where(have[:, :, None, None], block, np.array(self._fills[name], pool.dtype))
            dense = block.transpose(0, 2, 1, 3).reshape((tx1 - tx0) * t, (ty1 - ty0) * t)
            ox, oy = ix0 - tx0 * t, iy0 - ty0 * t
            out.append(np.ascontiguousarray(dense[ox : ox + w, oy : oy + h]))
        return tuple(out)

    def _dtype(self, name: str):
        return self._layers[name].dtype if name in self._layers else np.dtype(_RISK_SPEC[name][0])

    def export(self, box: tuple[int, int, int, int] | None = None, known_only: bool = True):
        """Nodes as flat arrays: cells (K, 2) int32, labels, heights, flags. By default only nodes
        with any flag set (known, or in a safety zone) inside `box` (half-open, cells)."""
        n = self.n_tiles
        if n == 0:
            return (
                np.zeros((0, 2), np.int32),
                np.zeros(0, np.uint16),
                np.zeros(0, np.float32),
                np.zeros(0, np.uint8),
            )
        flags = self.flat("flags")[: n * self.tile_size**2]
        keep = flags != 0 if known_only else np.ones(len(flags), bool)
        flat = np.flatnonzero(keep)
        ix, iy = self.cells_of_flat(flat)
        inside = self.in_bounds(ix, iy)
        if box is not None:
            bx0, by0, bx1, by1 = box
            inside &= (ix >= bx0) & (iy >= by0) & (ix < bx1) & (iy < by1)
        flat, ix, iy = flat[inside], ix[inside], iy[inside]
        cells = np.stack([ix, iy], axis=1).astype(np.int32)
        return (
            cells,
            self.flat("labels")[flat].copy(),
            self.flat("heights")[flat].copy(),
            self.flat("flags")[flat].copy(),
        )
