"""The geometric labeller: ground versus obstacle for LiDAR clouds that carry no labels.

A fallback for clouds without a label field (ROS 2 topics, bags, KITTI `.bin` scans without
`.label`): each point gets an id of the `geometric` class table (common/classes/geometric.toml),
judged against the robot's limits, so that the rest of the stack (mapper, navgraph, planner) works
on it unchanged. When a cloud has labels, they win; this only runs when there are none.

    labeller = GeometricLabeller.from_config(config)     # a SmanaConfig
    labels = labeller.label(points_world, sensor_origin)  # u2[N]: UNKNOWN, GROUND or OBSTACLE

The method, on a 2D grid of `geometric.cell_m` cells in the world frame (z up):

1. per cell, the number of points, the highest and the lowest height: the cell's ground
   height. A cell with fewer than `min_points` points is unknown.
2. obstacle cells: a cell whose points rise more than the step height (`planner.max_step_m`)
   above its lowest has something standing in it (a wall, a trunk, a car; its foot hidden or
   not); a pit is a cell lower than most of its (8) neighbours by more than the step height (a
   hole, or a return from below the ground); a step is a cell higher than one of its neighbours
   by more than the step height (the edge of a ledge, a box, a car over ground it hides).
3. the slope of the other cells: along x and along y, the median of the height differences over
   run of the pairs of cells in a window of about the robot's footprint (`navgraph.robot_radius_m`
   each side). The median ignores a step inside the window, so a climbable step is not read as a
   steep slope. A cell with no pair to measure is unknown (an isolated return).
4. each point takes its cell's kind: ground where the slope is at most
   `geometric.max_slope_deg` and the cell is none of step 2's, an obstacle where it is one of
   those or steeper, unknown where the cell is (a point more than the step height above its
   cell's ground is an obstacle in any cell with enough points).

The kernels are single-threaded and deterministic. They work on the occupied cells only (a
dense grid holds their compact index): a 124k-point KITTI scan spanning 156 x 100 m takes about
20 ms of CPU on a loaded 2-core machine, a third binning the points, two thirds in the cells'
kinds, most of it the slope medians (tests/test_geometric_scans.py prints the figure).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from smana.common.config.geometric import GeometricConfig

TABLE = "geometric"  # the class table the labels belong to
UNKNOWN, GROUND, OBSTACLE = 0, 1, 2  # its ids (common/classes/geometric.toml)

# Cell kinds (internal).
_CELL_UNKNOWN, _CELL_GROUND, _CELL_OBSTACLE = 0, 1, 2


class GeometricLabeller:
    """Labels world-frame clouds by geometry (see the module docstring). Holds only parameters:
    one instance serves any number of scans, from any thread."""

    def __init__(self, config: GeometricConfig, max_step_m: float, robot_radius_m: float):
        if not max_step_m > 0 or not math.isfinite(max_step_m):
            raise ValueError(f"max_step_m must be a number > 0, got {max_step_m}")
        if not robot_radius_m >= 0 or not math.isfinite(robot_radius_m):
            raise ValueError(f"robot_radius_m must be a number >= 0, got {robot_radius_m}")
        self.config = config
        self.max_step_m = float(max_step_m)
        self.robot_radius_m = float(robot_radius_m)
        self.window_cells = window_cells(config.cell_m, robot_radius_m)

    @classmethod
    def from_config(cls, config) -> GeometricLabeller:
        """From a whole SmanaConfig: [geometric], planner.max_step_m, navgraph.robot_radius_m."""
        return cls(config.geometric, config.planner.max_step_m, config.navgraph.robot_radius_m)

    def label(self, points_world, sensor_origin) -> np.ndarray:
        """f4[N, 3] world-frame points and the sensor's world position -> u2[N] table ids."""
        return label_geometric(
            points_world,
            sensor_origin,
            self.config,
            self.max_step_m,
            self.robot_radius_m,
        )


def label_geometric(
    points_world,
    sensor_origin,
    config: GeometricConfig | None = None,
    max_step_m: float = 0.3,
    robot_radius_m: float = 0.4,
) -> np.ndarray:
    """Label a world-frame cloud by geometry: u2[N] ids of the `geometric` table (UNKNOWN, GROUND,
    OBSTACLE). Non-finite points, and points farther than `config.max_distance_m` from the sensor
    on x or y, are UNKNOWN. Raises ValueError on malformed input."""
    cfg = config if config is not None else GeometricConfig()
    pts = np.asarray(points_world)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if pts.dtype.kind != "f":
        raise ValueError(f"points must be floats, got {pts.dtype}")
    origin = np.asarray(sensor_origin, np.float64).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ValueError(f"sensor_origin must be 3 finite numbers, got {sensor_origin!r}")
    if not max_step_m > 0 or not math.isfinite(max_step_m):
        raise ValueError(f"max_step_m must be a number > 0, got {max_step_m}")
    if not robot_radius_m >= 0 or not math.isfinite(robot_radius_m):
        raise ValueError(f"robot_radius_m must be a number >= 0, got {robot_radius_m}")
    out = np.zeros(pts.shape[0], np.uint16)
    if pts.shape[0] == 0:
        return out
    params = _Params(
        float(cfg.cell_m),
        float(max_step_m),
        math.tan(math.radians(cfg.max_slope_deg)),
        window_cells(cfg.cell_m, robot_radius_m),
        int(cfg.min_points),
        float(cfg.max_distance_m),
    )
    _label_kernel(np.ascontiguousarray(pts, np.float32), origin, params, out)
    return out


def window_cells(cell_m: float, robot_radius_m: float) -> int:
    """Cells each side of a cell that its slope is measured over: the robot's radius, one cell
    at the least (a slope is what the robot's footprint feels, not a 0.2 m wrinkle)."""
    return max(1, int(round(robot_radius_m / cell_m)))


# -- kernels -----------------------------------------------------------------------------------


class _Params(NamedTuple):
    """The labeller's parameters as the kernels read them."""

    cell_m: float
    max_step: float  # metres
    tan_slope: float  # tan(max_slope_deg)
    window: int  # cells each side of a cell that its slope is measured over
    min_points: int
    max_dist: float  # metres from the sensor on x or y


@numba.njit(cache=True)
def _select(a, n, k):
    """Reorder a[:n] in place so that a[k] is its k-th smallest value, nothing smaller after it
    and nothing larger before it (Hoare's selection); returns a[k]."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@numba.njit(cache=True)
def _median(a, n):
    """Median of a[:n] (n >= 1), reordering it; even n: the mean of the middle two."""
    h = n // 2
    upper = _select(a, n, h)
    if n % 2:
        return upper
    lower = a[0]  # the largest of a[:h], all of which are <= upper
    for m in range(1, h):
        lower = max(lower, a[m])
    return 0.5 * (lower + upper)


class _Cells(NamedTuple):
    """The occupied cells of one scan: a dense grid holds each one's index into the compact
    per-cell arrays (-1 where empty), so that passes over cells touch only occupied ones."""

    index: np.ndarray  # i4[nx, ny]: compact index of the cell, -1 if no point fell in it
    ij: np.ndarray  # i4[n, 2]: the grid position of each occupied cell
    count: np.ndarray  # i4[n]: points in it
    zmin: np.ndarray  # f8[n]: its lowest point's height (the ground height)
    zmax: np.ndarray  # f8[n]: its highest point's height


@numba.njit(cache=True)
def _neighbour(cells, i, j):
    """Compact index of the cell at grid position (i, j), -1 if empty or outside the grid."""
    nx, ny = cells.index.shape
    if i < 0 or j < 0 or i >= nx or j >= ny:
        return -1
    return cells.index[i, j]


# Each step below loops over the cells itself: a helper called once per cell would cost numba's
# reference counting (an atomic increment and decrement per array it reads) on every call.


@numba.njit(cache=True)
def _pits(cells, known, max_step):
    """Step 2's pits: known cells lower than most (and at least 2) of their known neighbours by
    more than the step height."""
    n = cells.count.size
    zmin = cells.zmin
    pit = np.zeros(n, np.bool_)
    for c in range(n):
        if not known[c]:
            continue
        i, j = cells.ij[c, 0], cells.ij[c, 1]
        n_known = 0
        n_higher = 0
        for di in range(-1, 2):
            for dj in range(-1, 2):
                e = _neighbour(cells, i + di, j + dj)
                if e >= 0 and e != c and known[e]:
                    n_known += 1
                    if zmin[e] - zmin[c] > max_step:
                        n_higher += 1
        pit[c] = n_known >= 2 and 2 * n_higher > n_known
    return pit


@numba.njit(cache=True)
def _blocked(cells, known, pit, max_step, kind):
    """Step 2's obstacles: a pit, something standing in the cell, or a step above a known
    neighbour that is not a pit. Sets `kind` of those to obstacle; returns the other known
    cells (usable: their slope decides)."""
    zmin = cells.zmin
    usable = np.zeros(cells.count.size, np.bool_)
    for c in range(cells.count.size):
        if not known[c]:
            continue
        if pit[c] or cells.zmax[c] - zmin[c] > max_step:  # a hole, or something standing
            kind[c] = _CELL_OBSTACLE
            continue
        i, j = cells.ij[c, 0], cells.ij[c, 1]
        step = False
        for di in range(-1, 2):
            for dj in range(-1, 2):
                e = _neighbour(cells, i + di, j + dj)
                if e >= 0 and known[e] and not pit[e] and zmin[c] - zmin[e] > max_step:
                    step = True
        if step:
            kind[c] = _CELL_OBSTACLE
        else:
            usable[c] = True
    return usable


@numba.njit(cache=True)
def _pair_slopes(win, w, cell_m, gx, gy):
    """The height differences over run of every pair of known heights in a window `win` (NaN
    where unknown) along x into gx and along y into gy; returns how many of each. Takes only
    arrays and numbers: called once per cell, it reads no tuple field (no reference counting)."""
    nxs = 0
    nys = 0
    for u in range(2 * w + 1):  # the row (or column) across the axis
        for s in range(2 * w + 1):  # first cell of the pair along the axis
            for d in range(1, min(w, 2 * w - s) + 1):  # the second, d further, in the window
                # along x: window cells (s, u) and (s + d, u); along y: (u, s), (u, s + d)
                h0, h1 = win[s, u], win[s + d, u]
                if h0 == h0 and h1 == h1:
                    gx[nxs] = (h1 - h0) / (d * cell_m)
                    nxs += 1
                h0, h1 = win[u, s], win[u, s + d]
                if h0 == h0 and h1 == h1:
                    gy[nys] = (h1 - h0) / (d * cell_m)
                    nys += 1
    return nxs, nys


@numba.njit(cache=True)
def _slopes(cells, usable, p, kind):
    """Step 3 for the usable cells: the medians of the height differences over run along x and
    along y, over the pairs of usable cells in the window around each; `kind` is unknown where
    no pair exists, an obstacle where steeper than `p.tan_slope`, ground otherwise."""
    w = p.window
    cell_m = p.cell_m
    zmin = cells.zmin
    size = (2 * w + 1) * w * (2 * w + 1)  # pairs along one axis in the window, at most
    gx = np.empty(size, np.float64)
    gy = np.empty(size, np.float64)
    # the window's usable ground heights (NaN elsewhere), gathered once per cell: every pair
    # below reads this small array instead of the grid
    win = np.empty((2 * w + 1, 2 * w + 1), np.float64)
    for c in range(cells.count.size):
        if not usable[c]:
            continue
        i, j = cells.ij[c, 0], cells.ij[c, 1]
        for a in range(2 * w + 1):
            for b in range(2 * w + 1):
                e = _neighbour(cells, i + a - w, j + b - w)
                win[a, b] = zmin[e] if e >= 0 and usable[e] else np.nan
        nxs, nys = _pair_slopes(win, w, cell_m, gx, gy)
        if nxs + nys == 0:
            kind[c] = _CELL_UNKNOWN  # an isolated return
            continue
        mx = _median(gx, nxs) if nxs else 0.0
        my = _median(gy, nys) if nys else 0.0
        if mx * mx + my * my > p.tan_slope * p.tan_slope:
            kind[c] = _CELL_OBSTACLE
        else:
            kind[c] = _CELL_GROUND


@numba.njit(cache=True)
def _cell_kinds(cells, p):
    """Per occupied cell: unknown, ground or obstacle (module docstring, steps 1-3)."""
    known = cells.count >= p.min_points
    pit = _pits(cells, known, p.max_step)
    kind = np.zeros(cells.count.size, np.uint8)
    usable = _blocked(cells, known, pit, p.max_step, kind)
    _slopes(cells, usable, p, kind)
    return kind


@numba.njit(cache=True)
def _bin_points(points, origin, cell_m, max_dist):
    """The occupied cells of a cloud, and each point's cell (-1: non-finite or too far)."""
    n = points.shape[0]
    valid = np.zeros(n, np.bool_)
    ix = np.empty(n, np.int64)
    iy = np.empty(n, np.int64)
    lo_x = lo_y = np.iinfo(np.int64).max
    hi_x = hi_y = np.iinfo(np.int64).min
    n_valid = 0
    for k in range(n):
        x, y, z = float(points[k, 0]), float(points[k, 1]), float(points[k, 2])
        ok = np.isfinite(x) and np.isfinite(y) and np.isfinite(z)
        if not ok or abs(x - origin[0]) > max_dist or abs(y - origin[1]) > max_dist:
            continue
        a, b = int(np.floor(x / cell_m)), int(np.floor(y / cell_m))
        valid[k], ix[k], iy[k] = True, a, b
        lo_x, hi_x = min(lo_x, a), max(hi_x, a)
        lo_y, hi_y = min(lo_y, b), max(hi_y, b)
        n_valid += 1
    if n_valid == 0:
        lo_x = hi_x = lo_y = hi_y = 0
    index = np.full((hi_x - lo_x + 1, hi_y - lo_y + 1), -1, np.int32)
    ij = np.empty((n_valid, 2), np.int32)
    count = np.zeros(n_valid, np.int32)
    zmin = np.full(n_valid, np.inf)
    zmax = np.full(n_valid, -np.inf)
    cell_of = np.full(n, -1, np.int32)
    n_cells = 0
    for k in range(n):
        if not valid[k]:
            continue
        a, b = ix[k] - lo_x, iy[k] - lo_y
        c = index[a, b]
        if c < 0:
            c = n_cells
            index[a, b] = c
            ij[c, 0], ij[c, 1] = a, b
            n_cells += 1
        cell_of[k] = c
        count[c] += 1
        zmin[c] = min(zmin[c], float(points[k, 2]))
        zmax[c] = max(zmax[c], float(points[k, 2]))
    cells = _Cells(index, ij[:n_cells], count[:n_cells], zmin[:n_cells], zmax[:n_cells])
    return cells, cell_of


@numba.njit(cache=True)
def _point_labels(points, cells, cell_of, kind, p, out):
    """Module docstring, step 4."""
    min_points = p.min_points
    max_step = p.max_step
    for k in range(points.shape[0]):
        c = cell_of[k]
        if c < 0 or cells.count[c] < min_points:
            continue
        if float(points[k, 2]) - cells.zmin[c] > max_step:
            out[k] = OBSTACLE
        elif kind[c] == _CELL_GROUND:
            out[k] = GROUND
        elif kind[c] == _CELL_OBSTACLE:
            out[k] = OBSTACLE


@numba.njit(cache=True)
def _label_kernel(points, origin, p, out):
    cells, cell_of = _bin_points(points, origin, p.cell_m, p.max_dist)
    kind = _cell_kinds(cells, p)
    _point_labels(points, cells, cell_of, kind, p, out)
