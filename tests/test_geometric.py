"""The geometric labeller (common/geometric.py): hand-built scenes against the robot's limits, and
the kernel against a slow, obvious reference on random scenes."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import ConfigError, GeometricConfig, SmanaConfig
from smana.common.geometric import (
    GROUND,
    OBSTACLE,
    TABLE,
    UNKNOWN,
    GeometricLabeller,
    label_geometric,
    window_cells,
)

STEP = 0.3  # planner.max_step_m's default
RADIUS = 0.4  # navgraph.robot_radius_m's default
CFG = GeometricConfig()  # 0.2 m cells, 20 degrees, 2 points a cell


# -- the reference: plain Python, one rule at a time -------------------------------------------


def reference_labels(points, origin, cfg=CFG, max_step=STEP, radius=RADIUS) -> np.ndarray:
    pts = np.asarray(points, np.float32).astype(np.float64)
    ox, oy = float(origin[0]), float(origin[1])
    cells: dict[tuple[int, int], list[float]] = {}
    where = []
    for x, y, z in pts:
        ok = math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        ok = ok and abs(x - ox) <= cfg.max_distance_m and abs(y - oy) <= cfg.max_distance_m
        if not ok:
            where.append(None)
            continue
        c = (math.floor(x / cfg.cell_m), math.floor(y / cfg.cell_m))
        cells.setdefault(c, []).append(z)
        where.append(c)
    ground = {c: min(zs) for c, zs in cells.items() if len(zs) >= cfg.min_points}
    tall = {c for c in ground if max(cells[c]) - ground[c] > max_step}  # something stands in it

    def neighbours(c):
        return [
            (c[0] + di, c[1] + dj)
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
            if (di, dj) != (0, 0) and (c[0] + di, c[1] + dj) in ground
        ]

    pits = set()
    for c, g in ground.items():
        nb = neighbours(c)
        higher = [n for n in nb if ground[n] - g > max_step]
        if len(nb) >= 2 and 2 * len(higher) > len(nb):
            pits.add(c)
    steps = {
        c
        for c, g in ground.items()
        if c not in pits and any(n not in pits and g - ground[n] > max_step for n in neighbours(c))
    }
    steps -= tall  # (an obstacle either way)
    usable = {c for c in ground if c not in pits and c not in steps and c not in tall}
    w = window_cells(cfg.cell_m, radius)
    kind = {c: "obstacle" for c in pits | steps | tall}
    tan = math.tan(math.radians(cfg.max_slope_deg))
    for c in usable:
        gx, gy = [], []
        for u in range(-w, w + 1):
            for s in range(-w, w + 1):
                for t in range(s + 1, w + 1):
                    d = t - s
                    if d > w:
                        continue
                    a, b = (c[0] + s, c[1] + u), (c[0] + t, c[1] + u)
                    if a in usable and b in usable:
                        gx.append((ground[b] - ground[a]) / (d * cfg.cell_m))
                    a, b = (c[0] + u, c[1] + s), (c[0] + u, c[1] + t)
                    if a in usable and b in usable:
                        gy.append((ground[b] - ground[a]) / (d * cfg.cell_m))
        if not gx and not gy:
            kind[c] = "unknown"
            continue
        mx = statistics.median(gx) if gx else 0.0
        my = statistics.median(gy) if gy else 0.0
        kind[c] = "obstacle" if mx * mx + my * my > tan * tan else "ground"
    out = np.zeros(len(pts), np.uint16)
    for k, c in enumerate(where):
        if c is None or c not in ground:
            continue
        if pts[k, 2] - ground[c] > max_step:
            out[k] = OBSTACLE
        else:
            out[k] = {"unknown": UNKNOWN, "ground": GROUND, "obstacle": OBSTACLE}[kind[c]]
    return out


# -- scene helpers ----------------------------------------------------------------------------


def grid_xy(x0, x1, y0, y1, spacing=0.05):
    xs = np.arange(x0 + spacing / 2, x1, spacing)
    ys = np.arange(y0 + spacing / 2, y1, spacing)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return gx.ravel(), gy.ravel()


def surface(x0, x1, y0, y1, height, spacing=0.05):
    """Points on z = height(x, y) over a rectangle."""
    x, y = grid_xy(x0, x1, y0, y1, spacing)
    return np.c_[x, y, height(x, y)].astype(np.float32)


def flat(x0=-4, x1=4, y0=-4, y1=4, z=0.0):
    return surface(x0, x1, y0, y1, lambda x, y: np.full_like(x, z))


def wall(x, y0, y1, z0, z1, spacing=0.05):
    """A vertical wall in the plane x = const."""
    ys = np.arange(y0 + spacing / 2, y1, spacing)
    zs = np.arange(z0, z1, spacing)
    gy, gz = np.meshgrid(ys, zs, indexing="ij")
    return np.c_[np.full(gy.size, x), gy.ravel(), gz.ravel()].astype(np.float32)


def trunk(cx, cy, radius, height, spacing=0.03):
    a = np.arange(0, 2 * np.pi, spacing / radius)
    zs = np.arange(0.0, height, spacing)
    ga, gz = np.meshgrid(a, zs, indexing="ij")
    return np.c_[
        cx + radius * np.cos(ga.ravel()), cy + radius * np.sin(ga.ravel()), gz.ravel()
    ].astype(np.float32)


def label(points):
    out = label_geometric(points, [0.0, 0.0, 1.0], CFG, STEP, RADIUS)
    np.testing.assert_array_equal(out, reference_labels(points, [0.0, 0.0, 1.0]))
    return out


def share(labels, mask, value):
    return float(np.mean(labels[mask] == value))


# -- the class table --------------------------------------------------------------------------


def test_table_matches_the_labeller_ids():
    t = ClassTable.load(TABLE)
    assert t.by_name("unknown").id == UNKNOWN and t[UNKNOWN].kind == "unknown"
    assert t.by_name("ground").id == GROUND and t[GROUND].traversable and t[GROUND].cost > 0
    assert t.by_name("obstacle").id == OBSTACLE and t[OBSTACLE].obstacle
    assert not t.maps_dataset_ids  # the labeller writes table ids


# -- hand-built scenes ------------------------------------------------------------------------


def test_flat_ground_is_ground():
    pts = flat()
    labels = label(pts)
    assert np.all(labels == GROUND)


@pytest.mark.parametrize(
    ("degrees", "expected"), [(10.0, GROUND), (15.0, GROUND), (30.0, OBSTACLE)]
)
def test_slopes_under_and_over_the_limit(degrees, expected):
    tan = math.tan(math.radians(degrees))
    pts = surface(-3, 3, -3, 3, lambda x, y: tan * x)
    labels = label(pts)
    inner = (np.abs(pts[:, 0]) < 2) & (np.abs(pts[:, 1]) < 2)
    assert share(labels, inner, expected) > 0.99


def test_slope_across_y_counts_too():
    tan = math.tan(math.radians(30.0))
    pts = surface(-3, 3, -3, 3, lambda x, y: tan * y)
    labels = label(pts)
    inner = (np.abs(pts[:, 0]) < 2) & (np.abs(pts[:, 1]) < 2)
    assert share(labels, inner, OBSTACLE) > 0.99


def test_a_step_under_the_limit_is_ground_both_sides():
    pts = surface(-3, 3, -3, 3, lambda x, y: np.where(x < 0.0, 0.0, 0.2))
    labels = label(pts)
    assert np.all(labels == GROUND)


def test_a_step_over_the_limit_is_an_obstacle_at_its_edge_only():
    pts = surface(-3, 3, -3, 3, lambda x, y: np.where(x < 0.0, 0.0, 0.5))
    labels = label(pts)
    edge = (pts[:, 0] >= 0.0) & (pts[:, 0] < 0.2)  # the upper cells beside the lower ones
    assert np.all(labels[edge] == OBSTACLE)
    low = pts[:, 0] < -0.5
    assert np.all(labels[low] == GROUND)  # standing below a ledge is fine
    high = pts[:, 0] > 1.0
    assert np.all(labels[high] == GROUND)  # so is standing on it, away from the edge


def test_a_wall_is_an_obstacle_and_the_ground_at_its_foot_is_ground():
    pts = np.concatenate([flat(), wall(1.01, -2, 2, 0.0, 2.0)])
    labels = label(pts)
    in_wall_cells = (pts[:, 0] >= 1.0) & (pts[:, 0] < 1.2) & (np.abs(pts[:, 1]) < 2)
    assert np.all(labels[in_wall_cells] == OBSTACLE)  # the wall, its foot with it
    assert np.all(labels[~in_wall_cells] == GROUND)  # right up to the cells beside it


def test_a_wall_whose_foot_is_hidden_is_an_obstacle():
    """Parked cars hide the foot of a building: the wall's cells start 1.5 m up, with no ground
    beside them to be a step from; they are still obstacles, not a ledge to stand on."""
    labels = label(wall(1.01, -2, 2, 1.5, 4.0))
    assert np.all(labels == OBSTACLE)


def test_a_tree_trunk_is_an_obstacle():
    pts = np.concatenate([flat(), trunk(1.5, 0.5, 0.15, 3.0)])
    labels = label(pts)
    tree = (np.hypot(pts[:, 0] - 1.5, pts[:, 1] - 0.5) > 0.14) & (pts[:, 2] > STEP + 0.01)
    assert np.all(labels[tree] == OBSTACLE)
    far = np.hypot(pts[:, 0] - 1.5, pts[:, 1] - 0.5) > 1.0
    assert np.all(labels[far] == GROUND)


def test_a_trunk_whose_foot_is_hidden_is_an_obstacle():
    """The LiDAR sees the trunk from 0.5 m up only: its cells' lowest points stand out of the
    ground around them by more than a step."""
    t = trunk(1.5, 0.5, 0.15, 3.0)
    pts = np.concatenate([flat(), t[t[:, 2] > 0.5]])
    labels = label(pts)
    assert np.all(labels[len(flat()) :] == OBSTACLE)


def test_a_box_lower_than_a_step_is_ground_and_a_higher_one_an_obstacle():
    def box(h):
        return surface(
            -3, 3, -3, 3, lambda x, y: np.where((np.abs(x) < 0.6) & (np.abs(y) < 0.6), h, 0)
        )

    low, high = box(0.15), box(0.6)
    assert np.all(label(low) == GROUND)
    top = (np.abs(high[:, 0]) < 0.6) & (np.abs(high[:, 1]) < 0.6)
    labels = label(high)
    assert np.all(labels[top & (np.abs(high[:, 0]) > 0.4)] == OBSTACLE)  # its rim
    assert np.all(labels[~top & (np.hypot(high[:, 0], high[:, 1]) > 1.2)] == GROUND)


def test_a_hole_is_an_obstacle_and_a_low_outlier_spoils_only_its_cell():
    pts = flat()
    outlier = np.array([[1.05, 1.05, -2.0]], np.float32)
    labels = label(np.concatenate([pts, outlier]))
    cell = (np.floor(pts[:, 0] / 0.2) == 5) & (np.floor(pts[:, 1] / 0.2) == 5)
    assert np.all(labels[:-1][~cell] == GROUND)
    assert labels[-1] == OBSTACLE


def test_sparse_points_are_unknown():
    lone = np.array([[0.1, 0.1, 0.0], [3.1, 3.1, 0.0], [3.11, 3.12, 0.01]], np.float32)
    labels = label(lone)
    assert labels[0] == UNKNOWN  # one point in its cell: fewer than min_points
    assert np.all(labels[1:] == UNKNOWN)  # a cell with no neighbour to measure a slope on


def test_far_and_nonfinite_points_are_unknown():
    pts = np.concatenate([flat(), [[np.nan, 0, 0], [0, np.inf, 0], [500.0, 0, 0], [500.1, 0, 0]]])
    labels = label_geometric(pts.astype(np.float32), [0, 0, 1.0])
    assert np.all(labels[-4:] == UNKNOWN)
    assert np.all(labels[:-4] == GROUND)


def test_the_world_frame_matters_not_the_sensor_frame():
    """Lifted and shifted, the same scene gets the same labels."""
    pts = np.concatenate([flat(), wall(1.01, -2, 2, 0.0, 2.0)])
    moved = pts + np.array([20.0, -7.0, 3.5], np.float32)
    a = label_geometric(pts, [0, 0, 1], CFG, STEP, RADIUS)
    b = label_geometric(moved, [20, -7, 4.5], CFG, STEP, RADIUS)
    assert np.mean(a == b) > 0.99  # cells split the float points slightly differently


# -- the kernel against the reference ---------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_kernel_matches_reference_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 3000))
    span = float(rng.uniform(1.0, 6.0))
    pts = np.c_[rng.uniform(-span, span, (n, 2)), rng.normal(0, 0.05, n)]
    # some rough terrain, some blocks and spikes, some duplicates on cell edges
    pts[:, 2] += 0.3 * np.sin(pts[:, 0]) + np.where(rng.random(n) < 0.1, rng.uniform(0, 2, n), 0)
    pts[: n // 10, :2] = np.round(pts[: n // 10, :2] / 0.2) * 0.2
    cfg = GeometricConfig(
        cell_m=float(rng.choice([0.1, 0.2, 0.3])),
        max_slope_deg=float(rng.uniform(5, 45)),
        min_points=int(rng.integers(1, 4)),
    )
    step = float(rng.uniform(0.05, 0.5))
    radius = float(rng.uniform(0.0, 0.8))
    pts = pts.astype(np.float32)
    got = label_geometric(pts, [0, 0, 1], cfg, step, radius)
    want = reference_labels(pts, [0, 0, 1], cfg, step, radius)
    np.testing.assert_array_equal(got, want)
    assert set(np.unique(got)) <= {UNKNOWN, GROUND, OBSTACLE}


# -- the public API ---------------------------------------------------------------------------


def test_labeller_takes_the_robot_limits_from_the_config():
    cfg = SmanaConfig.load(
        overrides=["planner.max_step_m=0.1", "navgraph.robot_radius_m=0.8", "geometric.cell_m=0.1"]
    )
    lab = GeometricLabeller.from_config(cfg)
    assert lab.max_step_m == 0.1 and lab.window_cells == 8 and lab.config.cell_m == 0.1
    pts = surface(-3, 3, -3, 3, lambda x, y: np.where(x < 0.0, 0.0, 0.2))
    labels = lab.label(pts, [0, 0, 1])
    assert np.any(labels == OBSTACLE)  # a 0.2 m step is too high for this robot


def test_empty_cloud():
    assert label_geometric(np.zeros((0, 3), np.float32), [0, 0, 0]).shape == (0,)


@pytest.mark.parametrize(
    ("points", "origin", "why"),
    [
        (np.zeros((4, 2), np.float32), [0, 0, 0], "shape"),
        (np.zeros((4, 3), np.int32), [0, 0, 0], "floats"),
        (np.zeros((4, 3), np.float32), [0, 0], "sensor_origin"),
        (np.zeros((4, 3), np.float32), [0, np.nan, 0], "sensor_origin"),
    ],
)
def test_bad_input_is_a_value_error(points, origin, why):
    with pytest.raises(ValueError, match=why):
        label_geometric(points, origin)


def test_bad_limits_are_value_errors():
    pts = flat()
    with pytest.raises(ValueError, match="max_step_m"):
        label_geometric(pts, [0, 0, 0], max_step_m=0)
    with pytest.raises(ValueError, match="robot_radius_m"):
        GeometricLabeller(GeometricConfig(), 0.3, -1)


def test_config_section_is_checked():
    with pytest.raises(ConfigError, match="geometric.max_slope_deg"):
        SmanaConfig.load(overrides=["geometric.max_slope_deg=95"])
    with pytest.raises(ConfigError, match="geometric.min_points"):
        GeometricConfig(min_points=0)
    with pytest.raises(ConfigError, match="grid 20000 cells wide"):
        GeometricConfig(cell_m=0.01)  # a grid the memory could not hold


def test_median_helper_matches_statistics_median():
    from smana.common.geometric import _median

    rng = np.random.default_rng(1)
    for _ in range(2000):
        n = int(rng.integers(1, 40))
        a = rng.normal(size=n) if rng.random() < 0.5 else rng.integers(0, 4, n).astype(float)
        assert _median(a.copy(), n) == statistics.median(a.tolist())
