"""The navigation graph builder (paper 3.3.1): map deltas in, changed nodes out. No zenoh here.

Each map voxel is projected to the 2.5D node under it. A node shows the highest occupied voxel of
its column (the first voxel sets label and height, afterwards the highest wins), obstacle classes
come from the class table, and the safety zone marks nodes within `robot_radius_m` of an obstacle.

To recompute a node when the map clears a voxel (an obstacle that moved away) the node must know
what remains below, so every node keeps its column: a linked list of the occupied voxels projected
to it, sorted from the highest down, in a shared entry pool. The list is bounded by
`column_capacity`: when a column overflows, its lowest level is forgotten and the node remembers
that level as its `floor`; voxels at or below the floor are then ignored. The list is therefore
always exactly "every occupied voxel above the floor", and a column that loses all its tracked
voxels while it has a floor becomes unknown rather than showing a ghost or a guess.

The safety zone is kept current incrementally: every node counts the obstacle nodes within the
robot radius (itself included); when a node becomes or stops being an obstacle, the counts of the
nodes of a disc stencil around it change by one. A node is in the safety zone when its count is
positive and it is not an obstacle itself. Tiles within the radius of an obstacle are allocated so
that the zone also covers nodes not seen yet.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba
import numpy as np

from smana.common.classes import ClassTable
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid

BACKENDS = ("octree-max", "octree-bayes", "tsdf")
NO_FLOOR = np.iinfo(np.int32).min
_NO_FLOOR = int(NO_FLOOR)
_KNOWN = FLAG_KNOWN
_OBST = FLAG_OBSTACLE
_SAFE = FLAG_SAFETY_ZONE


@dataclass
class GraphUpdate:
    """What one integration changed: the nodes whose label, height or flags differ afterwards."""

    cells: np.ndarray  # (K, 2) int32 grid indices from the grid origin
    labels: np.ndarray  # (K,) u2
    heights: np.ndarray  # (K,) f4, NaN where the node is not known
    flags: np.ndarray  # (K,) u1
    n_voxels: int = 0
    n_surface: int = 0  # voxels that add to or update a column
    n_out_of_bounds: int = 0
    n_nonfinite: int = 0
    n_unknown_labels: int = 0  # labels outside the class table, read as unknown (id 0)
    n_below_floor: int = 0  # surface voxels ignored because their column overflowed below them
    n_columns_lost: int = 0  # columns emptied above their floor (became unknown)
    n_new_tiles: int = 0
    time_ms: float = 0.0


class NavGraph:
    """A 2.5D semantic navigation graph inside fixed bounds, built from map deltas."""

    def __init__(
        self,
        classes: ClassTable,
        bounds_min_xy=(-50.0, -50.0),
        bounds_max_xy=(50.0, 50.0),
        resolution_m: float = 0.2,
        robot_radius_m: float = 0.4,
        tile_size: int = 32,
        column_capacity: int = 256,
    ):
        if not (np.isfinite(robot_radius_m) and robot_radius_m >= 0):
            raise ValueError(f"robot_radius_m must be >= 0, got {robot_radius_m}")
        if not 1 <= int(column_capacity) <= 4096:
            raise ValueError(f"column_capacity must be 1..4096, got {column_capacity}")
        self.classes = classes
        self.grid = NavGrid.from_bounds(bounds_min_xy, bounds_max_xy, resolution_m, tile_size)
        self.resolution_m = self.grid.resolution_m
        self.robot_radius_m = float(robot_radius_m)
        self.column_capacity = int(column_capacity)
        g = self.grid
        g.add_layer("col_head", np.int32, -1)
        g.add_layer("col_len", np.int32, 0)
        g.add_layer("col_floor", np.int32, NO_FLOOR)
        g.add_layer("obstacle_count", np.int32, 0)
        g.add_layer("epoch", np.uint32, 0)
        self._epoch = 0
        # Entry pool of column voxels: level (z index), sub-column id, label, centre height, next.
        cap = 1024
        self._e_vz = np.zeros(cap, np.int32)
        self._e_sub = np.zeros(cap, np.uint16)
        self._e_label = np.zeros(cap, np.uint16)
        self._e_z = np.zeros(cap, np.float32)
        self._e_next = np.full(cap, -1, np.int32)
        self._e_state = np.array([-1, 0, 0], np.int64)  # free-list head, high-water mark, in use
        self._obstacle_lut = classes.obstacle_lut.copy()
        self._ignored_lut = classes.ignored_lut.copy()
        r_cells = int(np.floor(self.robot_radius_m / self.resolution_m + 1e-9))
        dx, dy = np.meshgrid(np.arange(-r_cells, r_cells + 1), np.arange(-r_cells, r_cells + 1))
        # Centre-to-centre distance; the small slack keeps nodes at exactly the radius inside.
        inside = np.hypot(dx, dy) * self.resolution_m <= self.robot_radius_m + 1e-9
        self._stencil_dx = dx[inside].astype(np.int64)
        self._stencil_dy = dy[inside].astype(np.int64)
        self._stencil_reach = r_cells
        self.n_integrations = 0

    # -- memory --------------------------------------------------------------------------------

    @property
    def nbytes(self) -> int:
        entries = sum(
            a.nbytes for a in (self._e_vz, self._e_sub, self._e_label, self._e_z, self._e_next)
        )
        return self.grid.nbytes + entries

    @property
    def n_column_voxels(self) -> int:
        return int(self._e_state[2])

    def _reserve_entries(self, n: int) -> None:
        need = int(self._e_state[1]) + n
        cap = len(self._e_vz)
        if need <= cap:
            return
        while cap < need:
            cap *= 2

        def grown(a, fill):
            out = np.full(cap, fill, a.dtype)
            out[: len(a)] = a
            return out

        self._e_vz = grown(self._e_vz, 0)
        self._e_sub = grown(self._e_sub, 0)
        self._e_label = grown(self._e_label, 0)
        self._e_z = grown(self._e_z, 0)
        self._e_next = grown(self._e_next, -1)

    # -- integration ---------------------------------------------------------------------------

    def integrate_delta(self, delta) -> GraphUpdate:
        """Integrate a MapDelta (or anything with the same attributes)."""
        return self.integrate(
            delta.centres,
            delta.labels,
            delta.occupied,
            delta.values,
            backend=delta.backend,
            map_resolution_m=delta.resolution_m,
        )

    def integrate(
        self,
        centres,
        labels,
        occupied,
        values=None,
        *,
        backend: str = "octree-max",
        map_resolution_m: float = 0.1,
    ) -> GraphUpdate:
        """Integrate the voxels of one map update and return the nodes that changed.

        Octree back-ends: a voxel with `occupied` set is added to (or relabels) its column, one
        without is removed from it. TSDF: a voxel is a surface voxel when `occupied` is set or
        its |distance| (`values`) is below the graph resolution (the paper's rule); a voxel that
        leaves the band is removed. Rows with non-finite centres are dropped and counted.
        """
        t0 = time.perf_counter()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if not (np.isfinite(map_resolution_m) and map_resolution_m > 0):
            raise ValueError(f"map_resolution_m must be > 0, got {map_resolution_m}")
        if self.resolution_m / map_resolution_m > 255:
            # Sub-column ids pack (gx, gy) modulo 256 each: a node may span at most 255 voxels.
            raise ValueError("graph resolution spans more than 255 map voxels per axis")
        centres = np.asarray(centres)
        if centres.ndim != 2 or centres.shape[1] != 3 or centres.dtype.kind != "f":
            raise ValueError(f"centres must be a float (M, 3) array, got {centres.shape}")
        m = len(centres)
        labels = np.asarray(labels)
        occupied = np.asarray(occupied)
        if labels.shape != (m,) or labels.dtype.kind not in "iu":
            raise ValueError(f"labels must be an integer array of length {m}")
        if occupied.shape != (m,):
            raise ValueError(f"occupied must have length {m}")
        if backend == "tsdf":
            if values is None:
                raise ValueError("a tsdf delta needs values (signed distances)")
            values = np.asarray(values)
            if values.shape != (m,):
                raise ValueError(f"values must have length {m}")

        if labels.dtype != np.uint16:
            if labels.dtype.kind == "i" and m and labels.min() < 0:
                raise ValueError("labels must be >= 0")
            labels = labels.astype(np.int64)
        if occupied.dtype != np.uint8:
            occupied = (occupied != 0).view(np.uint8)
        values = np.zeros(0, np.float32) if values is None else np.asarray(values, np.float32)

        g = self.grid
        ox, oy = float(g.origin_xy[0]), float(g.origin_xy[1])
        nx, ny = g.shape
        t = g.tile_size
        # 1. classify voxels (surface / cleared / unusable row), clean labels, and allocate the
        # tiles of every in-bounds surface voxel, all in one pass.
        cen = centres
        lab, surf, missing, n_nonfinite, n_unknown, n_surface = _prepare(
            centres,
            labels,
            occupied,
            values,
            backend == "tsdf",
            self.resolution_m,
            self.classes.valid_lut,
            self._ignored_lut,
            ox,
            oy,
            g.resolution_m,
            nx,
            ny,
            g.tile_map,
            t,
        )
        n_new = g.allocate_tiles(missing // g.tiles_shape[1], missing % g.tiles_shape[1])
        self._reserve_entries(int(n_surface))

        # 2. columns and node heads.
        self._epoch += 1
        if self._epoch >= np.iinfo(np.uint32).max:  # wrap: clear stamps so none looks current
            g.flat("epoch")[:] = 0
            self._epoch = 1
        n_in = len(cen)
        dirty = np.empty(n_in, np.int64)
        old_lab = np.empty(n_in, np.uint16)
        old_h = np.empty(n_in, np.float32)
        old_f = np.empty(n_in, np.uint8)
        flips = np.empty(n_in, np.int64)
        flip_sign = np.empty(n_in, np.int32)
        counts = _integrate_kernel(
            cen,
            lab,
            surf,
            ox,
            oy,
            g.resolution_m,
            nx,
            ny,
            float(map_resolution_m),
            g.tile_map,
            t,
            self.column_capacity,
            g.flat("labels"),
            g.flat("heights"),
            g.flat("flags"),
            g.flat("col_head"),
            g.flat("col_len"),
            g.flat("col_floor"),
            g.flat("obstacle_count"),
            g.flat("epoch"),
            np.uint32(self._epoch),
            self._e_vz,
            self._e_sub,
            self._e_label,
            self._e_z,
            self._e_next,
            self._e_state,
            self._obstacle_lut,
            dirty,
            old_lab,
            old_h,
            old_f,
            flips,
            flip_sign,
        )
        n_dirty, n_flips, n_oob, n_below, n_lost = (int(c) for c in counts)
        flips, flip_sign = flips[:n_flips], flip_sign[:n_flips]

        # 3. safety zone: allocate the tiles a new obstacle's disc reaches, then update counts.
        dirty2 = np.empty(0, np.int64)
        old2 = (np.empty(0, np.uint16), np.empty(0, np.float32), np.empty(0, np.uint8))
        if n_flips:
            new_obst = flips[flip_sign > 0]
            if len(new_obst):
                ix, iy = g.cells_of_flat(new_obst)
                r = self._stencil_reach
                txs, tys = [], []
                for ddx in (-r, r):
                    for ddy in (-r, r):
                        jx = np.clip(ix + ddx, 0, nx - 1)
                        jy = np.clip(iy + ddy, 0, ny - 1)
                        txs.append(jx // t)
                        tys.append(jy // t)
                # While the disc spans at most two tiles per axis its four corners name them all.
                if 2 * r >= t:
                    txs, tys = _tile_ranges(ix, iy, r, t, nx, ny)
                else:
                    txs, tys = np.concatenate(txs), np.concatenate(tys)
                n_new += g.allocate_tiles(txs, tys)
            cap2 = n_flips * len(self._stencil_dx)
            dirty2 = np.empty(cap2, np.int64)
            old2 = (np.empty(cap2, np.uint16), np.empty(cap2, np.float32), np.empty(cap2, np.uint8))
            n2 = _safety_kernel(
                flips,
                flip_sign,
                self._stencil_dx,
                self._stencil_dy,
                g.tile_coords,
                g.tile_map,
                t,
                nx,
                ny,
                g.flat("obstacle_count"),
                g.flat("labels"),
                g.flat("heights"),
                g.flat("flags"),
                g.flat("epoch"),
                np.uint32(self._epoch),
                dirty2,
                *old2,
            )
            dirty2 = dirty2[:n2]
            old2 = tuple(a[:n2] for a in old2)

        # 4. the nodes that actually differ now.
        all_dirty = np.concatenate([dirty[:n_dirty], dirty2])
        o_lab = np.concatenate([old_lab[:n_dirty], old2[0]])
        o_h = np.concatenate([old_h[:n_dirty], old2[1]])
        o_f = np.concatenate([old_f[:n_dirty], old2[2]])
        n_lab = g.flat("labels")[all_dirty]
        n_h = g.flat("heights")[all_dirty]
        n_f = g.flat("flags")[all_dirty]
        same_h = (n_h == o_h) | (np.isnan(n_h) & np.isnan(o_h))
        changed = (n_lab != o_lab) | (n_f != o_f) | ~same_h
        sel = all_dirty[changed]
        ix, iy = g.cells_of_flat(sel)
        if len(sel):
            g.version += 1
        self.n_integrations += 1
        return GraphUpdate(
            cells=np.stack([ix, iy], axis=1).astype(np.int32),
            labels=n_lab[changed],
            heights=n_h[changed],
            flags=n_f[changed],
            n_voxels=m,
            n_surface=int(n_surface),
            n_out_of_bounds=n_oob,
            n_nonfinite=int(n_nonfinite),
            n_unknown_labels=int(n_unknown),
            n_below_floor=n_below,
            n_columns_lost=n_lost,
            n_new_tiles=n_new,
            time_ms=(time.perf_counter() - t0) * 1e3,
        )

    # -- reading -------------------------------------------------------------------------------

    def node(self, x: float, y: float) -> dict | None:
        """One node's state at world (x, y), or None outside the bounds."""
        ix, iy, ok = self.grid.world_to_cell(np.array([x, y], np.float64))
        if not ok:
            return None
        lab, h, f = self.grid.read_cells(np.array([[ix, iy]]))
        flat = self.grid.flat_index(np.array([ix]), np.array([iy]))[0]
        column = self.column(int(ix), int(iy)) if flat >= 0 else []
        cls = self.classes.classes.get(int(lab[0]))
        return {
            "cell": [int(ix), int(iy)],
            "centre": self.grid.cell_centre(ix, iy).tolist(),
            "label": int(lab[0]),
            "class": cls.name if cls else "?",
            "height": float(h[0]),
            "known": bool(f[0] & FLAG_KNOWN),
            "obstacle": bool(f[0] & FLAG_OBSTACLE),
            "safety_zone": bool(f[0] & FLAG_SAFETY_ZONE),
            "allocated": bool(flat >= 0),
            "column_voxels": len(column),
        }

    def column(self, ix: int, iy: int) -> list[tuple[int, int, int, float]]:
        """The tracked voxels of a node, highest first: (level, sub-column, label, height)."""
        flat = int(self.grid.flat_index(np.array([ix]), np.array([iy]))[0])
        if flat < 0:
            return []
        out = []
        e = int(self.grid.flat("col_head")[flat])
        while e >= 0:
            out.append(
                (
                    int(self._e_vz[e]),
                    int(self._e_sub[e]),
                    int(self._e_label[e]),
                    float(self._e_z[e]),
                )
            )
            e = int(self._e_next[e])
        return out

    def export(self, box_xy: tuple[float, float, float, float] | None = None, known_only=True):
        """cells, labels, heights, flags of the graph, or of a world box (x0, y0, x1, y1)."""
        box = None
        if box_xy is not None:
            x0, y0, x1, y1 = (float(v) for v in box_xy)
            if not all(np.isfinite([x0, y0, x1, y1])) or x1 < x0 or y1 < y0:
                raise ValueError(f"box must be finite x0, y0, x1, y1 with x0<=x1, y0<=y1: {box_xy}")
            res, o = self.resolution_m, self.grid.origin_xy
            # in cells, clipped to the grid: a finite box far outside (1e308 m) overflows an int
            with np.errstate(over="ignore"):
                lo = np.floor((np.array([x0, y0]) - o) / res)
                hi = np.floor((np.array([x1, y1]) - o) / res) + 1
            size = np.array(self.grid.shape, np.float64)
            lo, hi = np.clip(lo, 0, size), np.clip(hi, 0, size)
            box = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
        return self.grid.export(box, known_only)

    def stats(self) -> dict:
        g = self.grid
        return {
            "tiles": g.n_tiles,
            "nodes_allocated": g.n_nodes_allocated,
            "nodes_known": g.n_known(),
            "column_voxels": self.n_column_voxels,
            "bytes": self.nbytes,
            "integrations": self.n_integrations,
        }


def warm_up(classes: ClassTable) -> float:
    """Compile (or load from numba's cache) the kernels for the array types a decoded MapDelta
    has (read-only views), so the first real delta is not slow. Returns the seconds it took."""
    t0 = time.perf_counter()
    g = NavGraph(classes, (0.0, 0.0), (2.0, 2.0), 0.2, robot_radius_m=0.2, tile_size=4)

    def ro(a):
        a.flags.writeable = False
        return a

    ok = classes.obstacle_lut.nonzero()[0]
    lab = int(ok[0]) if len(ok) else 0
    for backend in ("octree-max", "tsdf"):
        for occ in (1, 0):
            g.integrate(
                ro(np.array([[0.55, 0.55, 0.05], [0.65, 0.55, 0.15]], np.float32)),
                ro(np.array([lab, 0], np.uint16)),
                ro(np.array([occ, occ], np.uint8)),
                ro(np.array([0.0, 0.05], np.float32)),
                backend=backend,
                map_resolution_m=0.1,
            )
    return time.perf_counter() - t0


def _tile_ranges(ix, iy, r, t, nx, ny):
    """Every tile a square of half-width r around each cell touches (for radii >= a tile)."""
    txs, tys = [], []
    for x, y in zip(ix.tolist(), iy.tolist(), strict=True):
        tx0, tx1 = max(0, x - r) // t, min(nx - 1, x + r) // t
        ty0, ty1 = max(0, y - r) // t, min(ny - 1, y + r) // t
        gx, gy = np.meshgrid(np.arange(tx0, tx1 + 1), np.arange(ty0, ty1 + 1), indexing="ij")
        txs.append(gx.ravel())
        tys.append(gy.ravel())
    return np.concatenate(txs), np.concatenate(tys)


# -- kernels ---------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _prepare(
    cen,
    labels,
    occupied,
    values,
    is_tsdf,
    band,
    valid_lut,
    ignored_lut,
    ox,
    oy,
    res,
    nx,
    ny,
    tile_map,
    t,
):
    """Per voxel: clean label (ids outside the table -> 0), kind (0 cleared, 1 surface, 2 row
    with a non-finite coordinate), and the ids (tx * nty + ty) of unallocated tiles under
    in-bounds surface voxels, each once."""
    m = len(cen)
    nty = tile_map.shape[1]
    n_lut = len(valid_lut)
    lab = np.empty(m, np.uint16)
    kind = np.empty(m, np.uint8)
    missing = np.empty(m, np.int64)
    n_missing = 0
    n_nonfinite = 0
    n_unknown = 0
    n_surface = 0
    for i in range(m):
        x = cen[i, 0]
        y = cen[i, 1]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(cen[i, 2])):
            kind[i] = 2
            lab[i] = 0
            n_nonfinite += 1
            continue
        lb = labels[i]
        if lb >= n_lut or not valid_lut[lb]:
            lb = 0
            n_unknown += 1
        lab[i] = lb
        surface = occupied[i] != 0
        if is_tsdf and not surface:
            surface = abs(values[i]) < band  # False for NaN
        # An ignored class (sky, ...) is not ground: treat it as a cleared voxel.
        if ignored_lut[lb]:
            surface = False
        kind[i] = 1 if surface else 0
        if not surface:
            continue
        n_surface += 1
        ix = int(np.floor((x - ox) / res))
        iy = int(np.floor((y - oy) / res))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            continue
        tx = ix // t
        ty = iy // t
        if tile_map[tx, ty] == -1:
            tile_map[tx, ty] = -2  # mark so each tile is reported once
            missing[n_missing] = tx * nty + ty
            n_missing += 1
    for k in range(n_missing):
        tile_map[missing[k] // nty, missing[k] % nty] = -1
    return lab, kind, missing[:n_missing], n_nonfinite, n_unknown, n_surface


@numba.njit(cache=True, inline="always")
def _mark_dirty(n, epoch_l, epoch, labels_l, heights_l, flags_l, dirty, old_lab, old_h, old_f, nd):
    if epoch_l[n] != epoch:
        epoch_l[n] = epoch
        dirty[nd] = n
        old_lab[nd] = labels_l[n]
        old_h[nd] = heights_l[n]
        old_f[nd] = flags_l[n]
        return nd + 1
    return nd


@numba.njit(cache=True)
def _integrate_kernel(
    cen,
    lab,
    surf,
    ox,
    oy,
    res,
    nx,
    ny,
    map_res,
    tile_map,
    t,
    cap_col,
    labels_l,
    heights_l,
    flags_l,
    head,
    clen,
    floor_l,
    count_l,
    epoch_l,
    epoch,
    e_vz,
    e_sub,
    e_label,
    e_z,
    e_next,
    e_state,
    obstacle_lut,
    dirty,
    old_lab,
    old_h,
    old_f,
    flips,
    flip_sign,
):
    tt = t * t
    nd = 0
    n_oob = 0
    n_below = 0
    n_lost = 0
    free_head = e_state[0]
    top = e_state[1]
    in_use = e_state[2]
    for i in range(len(cen)):
        if surf[i] == 2:
            continue
        x = cen[i, 0]
        y = cen[i, 1]
        ix = int(np.floor((x - ox) / res))
        iy = int(np.floor((y - oy) / res))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            n_oob += 1
            continue
        slot = tile_map[ix // t, iy // t]
        if slot < 0:
            continue  # a cleared voxel over a region never seen: nothing to recompute
        n = slot * tt + (ix % t) * t + (iy % t)
        gz = np.int32(np.floor(cen[i, 2] / map_res))
        gx = int(np.floor((x - ox) / map_res))
        gy = int(np.floor((y - oy) / map_res))
        sub = np.uint16(((gx & 255) << 8) | (gy & 255))
        # Find the voxel in the column (sorted by level, highest first).
        prev = -1
        e = head[n]
        while e >= 0 and e_vz[e] > gz:
            prev = e
            e = e_next[e]
        found = -1
        found_prev = -1
        p2 = prev
        e2 = e
        while e2 >= 0 and e_vz[e2] == gz:
            if e_sub[e2] == sub:
                found = e2
                found_prev = p2
                break
            p2 = e2
            e2 = e_next[e2]
        if surf[i] == 1:
            if found >= 0:
                if e_label[found] == lab[i]:
                    continue  # same voxel, same label: the node cannot change
                e_label[found] = lab[i]
                e_z[found] = cen[i, 2]
            else:
                if gz <= floor_l[n]:
                    n_below += 1
                    continue
                if free_head >= 0:
                    new = free_head
                    free_head = e_next[new]
                else:
                    new = top
                    top += 1
                in_use += 1
                e_vz[new] = gz
                e_sub[new] = sub
                e_label[new] = lab[i]
                e_z[new] = cen[i, 2]
                # Insert before the first entry of a lower level (after `prev`).
                if prev < 0:
                    e_next[new] = head[n]
                    head[n] = new
                else:
                    e_next[new] = e_next[prev]
                    e_next[prev] = new
                clen[n] += 1
                if clen[n] > cap_col:
                    # Forget the lowest level whole, so the list stays exact above the floor.
                    lowest = e_vz[head[n]]
                    cur = head[n]
                    while cur >= 0:
                        lowest = e_vz[cur]
                        cur = e_next[cur]
                    cut_prev = -1
                    cur = head[n]
                    while cur >= 0 and e_vz[cur] > lowest:
                        cut_prev = cur
                        cur = e_next[cur]
                    if cut_prev < 0:
                        head[n] = -1
                    else:
                        e_next[cut_prev] = -1
                    while cur >= 0:
                        nxt = e_next[cur]
                        e_next[cur] = free_head
                        free_head = cur
                        in_use -= 1
                        clen[n] -= 1
                        cur = nxt
                    floor_l[n] = lowest
        else:
            if found < 0:
                continue  # free voxel that was never in the column
            if found_prev < 0:
                head[n] = e_next[found]
            else:
                e_next[found_prev] = e_next[found]
            e_next[found] = free_head
            free_head = found
            in_use -= 1
            clen[n] -= 1
        nd = _mark_dirty(
            n, epoch_l, epoch, labels_l, heights_l, flags_l, dirty, old_lab, old_h, old_f, nd
        )
    e_state[0] = free_head
    e_state[1] = top
    e_state[2] = in_use

    # Recompute each touched node from its column.
    nf = 0
    for k in range(nd):
        n = dirty[k]
        e = head[n]
        if e < 0:
            if floor_l[n] != _NO_FLOOR and (old_f[k] & _KNOWN):
                n_lost += 1
            labels_l[n] = 0
            heights_l[n] = np.nan
            known = False
            obst = False
        else:
            # Highest level; among voxels of that level an obstacle wins (the conservative
            # choice), then the larger sub-column id, so the result does not depend on order.
            best = e
            lvl = e_vz[e]
            cur = e_next[e]
            while cur >= 0 and e_vz[cur] == lvl:
                ob_c = obstacle_lut[e_label[cur]]
                ob_b = obstacle_lut[e_label[best]]
                if (ob_c and not ob_b) or (ob_c == ob_b and e_sub[cur] > e_sub[best]):
                    best = cur
                cur = e_next[cur]
            labels_l[n] = e_label[best]
            heights_l[n] = e_z[best]
            known = True
            obst = obstacle_lut[e_label[best]]
        f = np.uint8(0)
        if known:
            f |= _KNOWN
        if obst:
            f |= _OBST
        elif count_l[n] > 0:
            f |= _SAFE
        was_obst = (old_f[k] & _OBST) != 0
        if obst != was_obst:
            flips[nf] = n
            flip_sign[nf] = 1 if obst else -1
            nf += 1
        flags_l[n] = f
    return nd, nf, n_oob, n_below, n_lost


@numba.njit(cache=True)
def _safety_kernel(
    flips,
    flip_sign,
    sdx,
    sdy,
    tile_coords,
    tile_map,
    t,
    nx,
    ny,
    count_l,
    labels_l,
    heights_l,
    flags_l,
    epoch_l,
    epoch,
    dirty,
    old_lab,
    old_h,
    old_f,
):
    tt = t * t
    nd = 0
    for k in range(len(flips)):
        n = flips[k]
        slot = n // tt
        local = n % tt
        ix = tile_coords[slot, 0] * t + local // t
        iy = tile_coords[slot, 1] * t + local % t
        s = flip_sign[k]
        for j in range(len(sdx)):
            jx = ix + sdx[j]
            jy = iy + sdy[j]
            if jx < 0 or jy < 0 or jx >= nx or jy >= ny:
                continue
            sl = tile_map[jx // t, jy // t]
            if sl < 0:
                continue  # only when removing an obstacle whose disc was never allocated
            m = sl * tt + (jx % t) * t + (jy % t)
            nd = _mark_dirty(
                m, epoch_l, epoch, labels_l, heights_l, flags_l, dirty, old_lab, old_h, old_f, nd
            )
            count_l[m] += s
            f = flags_l[m]
            if count_l[m] > 0 and not (f & _OBST):
                f |= _SAFE
            else:
                f &= ~np.uint8(_SAFE)
            flags_l[m] = f
    return nd
