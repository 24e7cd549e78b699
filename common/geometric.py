"""The geometric labeller: ground versus obstacle for LiDAR clouds that carry no labels.

A fallback for clouds without a label field (ROS 2 topics, bags, KITTI `.bin` scans without
`.label`): each point gets an id of the `geometric` class table (common/classes/geometric.toml),
judged against the robot's limits, so that the rest of the stack (mapper, navgraph, planner) works
on it unchanged. When a cloud has labels, they win; this only runs when there are none.

    labeller = GeometricLabeller.from_config(config)     # a SmanaConfig
    labels = labeller.label(points_world, sensor_origin)  # u2[N]: UNKNOWN, GROUND or OBSTACLE

The method, on a 2D grid of `geometric.cell_m` cells in the world frame (z up):

1. per cell, the number of points and the lowest height: the cell's ground height. A cell with
   fewer than `min_points` points is unknown.
2. a pit is a cell lower than most of its (8) neighbours by more than the step height: a hole,
   or a return from below the ground; a step is a cell higher than one of its neighbours by more
   than `planner.max_step_m` (the edge of a ledge, a box, a car over ground it hides).
3. the slope of the other cells: along x and along y, the median of the height differences over
   run of the pairs of cells in a window of about the robot's footprint (`navgraph.robot_radius_m`
   each side). The median ignores a step inside the window, so a climbable step is not read as a
   steep slope. A cell with no pair to measure is unknown (an isolated return).
4. a point more than the step height above its cell's ground is an obstacle (walls, trunks,
   bushes), whatever the cell; any other point takes its cell's kind: ground where the cell is
   neither a pit nor a step and its slope is at most `geometric.max_slope_deg`, an obstacle where
   it is one of those, unknown where the cell is.

The kernels are single-threaded and deterministic; a 124k-point KITTI scan takes a few
milliseconds (tests/test_geometric_kitti.py prints the figure).
"""

from __future__ import annotations

import math

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
    window = window_cells(cfg.cell_m, robot_radius_m)
    _label_kernel(
        np.ascontiguousarray(pts, np.float32),
        origin,
        float(cfg.cell_m),
        float(max_step_m),
        math.tan(math.radians(cfg.max_slope_deg)),
        window,
        int(cfg.min_points),
        float(cfg.max_distance_m),
        out,
    )
    return out


def window_cells(cell_m: float, robot_radius_m: float) -> int:
    """Cells each side of a cell that its slope is measured over: the robot's radius, one cell
    at the least (a slope is what the robot's footprint feels, not a 0.2 m wrinkle)."""
    return max(1, int(round(robot_radius_m / cell_m)))


# -- kernels -----------------------------------------------------------------------------------


@numba.njit(cache=True)
def _insertion_sort(a, n):
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v


@numba.njit(cache=True)
def _median(a, n):
    """Median of a[:n] (n >= 1), sorting it in place; even n: the mean of the middle two."""
    _insertion_sort(a, n)
    h = n // 2
    if n % 2:
        return a[h]
    return 0.5 * (a[h - 1] + a[h])


@numba.njit(cache=True)
def _cell_kinds(count, zmin, cell_m, min_points, max_step, tan_slope, window):
    """Per cell: unknown, ground or obstacle (module docstring, steps 1-3)."""
    nx, ny = count.shape
    known = count >= min_points
    pit = np.zeros((nx, ny), np.bool_)
    for i in range(nx):
        for j in range(ny):
            if not known[i, j]:
                continue
            g = zmin[i, j]
            n_known = 0
            n_higher = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    a, b = i + di, j + dj
                    if (di == 0 and dj == 0) or a < 0 or b < 0 or a >= nx or b >= ny:
                        continue
                    if known[a, b]:
                        n_known += 1
                        if zmin[a, b] - g > max_step:
                            n_higher += 1
            pit[i, j] = n_known >= 2 and 2 * n_higher > n_known
    kind = np.zeros((nx, ny), np.uint8)
    usable = np.zeros((nx, ny), np.bool_)
    for i in range(nx):
        for j in range(ny):
            if not known[i, j]:
                continue
            if pit[i, j]:
                kind[i, j] = _CELL_OBSTACLE
                continue
            g = zmin[i, j]
            step = False
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    a, b = i + di, j + dj
                    if a < 0 or b < 0 or a >= nx or b >= ny:
                        continue
                    if known[a, b] and not pit[a, b] and g - zmin[a, b] > max_step:
                        step = True
            if step:
                kind[i, j] = _CELL_OBSTACLE
            else:
                usable[i, j] = True
    w = window
    size = (2 * w + 1) * w * (2 * w + 1)  # pairs along one axis in the window, at most
    gx = np.empty(size, np.float64)
    gy = np.empty(size, np.float64)
    for i in range(nx):
        for j in range(ny):
            if not usable[i, j]:
                continue
            nxs = 0
            nys = 0
            for u in range(-w, w + 1):  # the row (or column) across the axis
                for s in range(-w, w + 1):  # first cell of the pair along the axis
                    for d in range(1, w + 1):  # its distance to the second
                        t = s + d
                        if t > w:
                            break
                        # along x: cells (i+s, j+u) and (i+t, j+u)
                        a0, a1, b = i + s, i + t, j + u
                        if a0 >= 0 and a1 < nx and 0 <= b < ny:
                            if usable[a0, b] and usable[a1, b]:
                                gx[nxs] = (zmin[a1, b] - zmin[a0, b]) / (d * cell_m)
                                nxs += 1
                        # along y: cells (i+u, j+s) and (i+u, j+t)
                        a, b0, b1 = i + u, j + s, j + t
                        if b0 >= 0 and b1 < ny and 0 <= a < nx:
                            if usable[a, b0] and usable[a, b1]:
                                gy[nys] = (zmin[a, b1] - zmin[a, b0]) / (d * cell_m)
                                nys += 1
            if nxs + nys == 0:
                kind[i, j] = _CELL_UNKNOWN
                continue
            mx = _median(gx, nxs) if nxs else 0.0
            my = _median(gy, nys) if nys else 0.0
            if mx * mx + my * my > tan_slope * tan_slope:
                kind[i, j] = _CELL_OBSTACLE
            else:
                kind[i, j] = _CELL_GROUND
    return kind


@numba.njit(cache=True)
def _label_kernel(points, origin, cell_m, max_step, tan_slope, window, min_points, max_dist, out):
    n = points.shape[0]
    valid = np.zeros(n, np.bool_)
    ix = np.zeros(n, np.int64)
    iy = np.zeros(n, np.int64)
    lo_x = lo_y = np.iinfo(np.int64).max
    hi_x = hi_y = np.iinfo(np.int64).min
    for k in range(n):
        x, y, z = float(points[k, 0]), float(points[k, 1]), float(points[k, 2])
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        if abs(x - origin[0]) > max_dist or abs(y - origin[1]) > max_dist:
            continue
        valid[k] = True
        ix[k] = int(np.floor(x / cell_m))
        iy[k] = int(np.floor(y / cell_m))
        lo_x, hi_x = min(lo_x, ix[k]), max(hi_x, ix[k])
        lo_y, hi_y = min(lo_y, iy[k]), max(hi_y, iy[k])
    if lo_x > hi_x:
        return  # nothing valid: all unknown
    nx, ny = hi_x - lo_x + 1, hi_y - lo_y + 1
    count = np.zeros((nx, ny), np.int32)
    zmin = np.full((nx, ny), np.inf)
    for k in range(n):
        if valid[k]:
            a, b = ix[k] - lo_x, iy[k] - lo_y
            count[a, b] += 1
            zmin[a, b] = min(zmin[a, b], float(points[k, 2]))
    kind = _cell_kinds(count, zmin, cell_m, min_points, max_step, tan_slope, window)
    for k in range(n):
        if not valid[k]:
            continue
        a, b = ix[k] - lo_x, iy[k] - lo_y
        if count[a, b] < min_points:
            continue
        if float(points[k, 2]) - zmin[a, b] > max_step:
            out[k] = OBSTACLE
        elif kind[a, b] == _CELL_GROUND:
            out[k] = GROUND
        elif kind[a, b] == _CELL_OBSTACLE:
            out[k] = OBSTACLE
