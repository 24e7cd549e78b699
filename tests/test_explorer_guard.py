"""The guard (services/explorer/guard.py): the footprint's clearance against a slow reference,
and what it lets out of a command near what the safety scan shows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config.explorer import GuardConfig
from smana.services.explorer.guard import Guard, clearance, rollout

RECTS = np.array(GuardConfig().footprint, float)


def slow_clearance(points, pose, rects) -> float:
    """The distance from the footprint to the nearest point, one point and rectangle at a time;
    a point inside a rectangle counts as minus its distance to that rectangle's nearest side."""
    x, y, yaw = pose
    best = math.inf
    for px, py in points:
        # the point in the base frame
        dx, dy = px - x, py - y
        lx = math.cos(yaw) * dx + math.sin(yaw) * dy
        ly = -math.sin(yaw) * dx + math.cos(yaw) * dy
        for cx, cy, hx, hy in rects:
            if abs(lx - cx) <= hx and abs(ly - cy) <= hy:
                best = min(best, -min(hx - abs(lx - cx), hy - abs(ly - cy)))
            else:
                ex = max(abs(lx - cx) - hx, 0.0)
                ey = max(abs(ly - cy) - hy, 0.0)
                best = min(best, math.hypot(ex, ey))
    return best


def test_clearance_matches_a_slow_reference():
    rng = np.random.default_rng(7)
    for _ in range(30):
        pts = rng.uniform(-1.5, 1.5, (rng.integers(1, 40), 2))
        poses = np.column_stack([rng.uniform(-0.5, 0.5, (5, 2)), rng.uniform(-4, 4, 5)])
        got = clearance(pts, poses, RECTS)
        want = [slow_clearance(pts, p, RECTS) for p in poses]
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert clearance(np.zeros((0, 2)), np.zeros((1, 3)), RECTS)[0] == math.inf


def test_rollout_follows_the_arc():
    p = rollout(1.0, 2.0, 0.3, 0.5, 0.0, 1.0)
    assert p.shape == (11, 3) and np.allclose(p[0], [1.0, 2.0, 0.3])
    assert np.allclose(p[-1, :2], [1.0 + 0.5 * math.cos(0.3), 2.0 + 0.5 * math.sin(0.3)])
    # a quarter turn of radius 1 m
    q = rollout(0.0, 0.0, 0.0, math.pi / 2, math.pi / 2, 1.0)
    assert np.allclose(q[-1], [1.0, 1.0, math.pi / 2], atol=1e-9)
    # an Euler integration of the same command lands on it
    x = y = th = 0.0
    for _ in range(10000):
        x += math.pi / 2 * 1e-4 * math.cos(th)
        y += math.pi / 2 * 1e-4 * math.sin(th)
        th += math.pi / 2 * 1e-4
    assert np.allclose(q[-1], [x, y, th], atol=1e-3)


def wall_scan(distance_m: float) -> np.ndarray:
    """Base-frame points of a wall across the robot's way, `distance_m` ahead of its centre."""
    ys = np.arange(-1.0, 1.0, 0.02)
    return np.column_stack([np.full_like(ys, distance_m), ys, np.zeros_like(ys)])


def drive(guard: Guard, v: float, w: float, pose, t: float, seconds: float, dt: float = 0.1):
    """Follow what the guard lets out of (v, w) for `seconds`; the final pose."""
    x, y, yaw = pose
    for _ in range(int(seconds / dt)):
        cv, cw = guard.check(v, w, (x, y, yaw), t)
        x += cv * dt * math.cos(yaw)
        y += cv * dt * math.sin(yaw)
        yaw += cw * dt
    return x, y, yaw


def test_the_robot_slows_and_stops_at_the_margin_of_a_wall():
    g = Guard()
    g.add(wall_scan(2.0), (0.0, 0.0, 0.0), t=0.0)  # wall at x = 2 in the world
    x, _, _ = drive(g, 0.8, 0.0, (0.0, 0.0, 0.0), t=0.1, seconds=8.0)
    gap = 2.0 - (x + 0.28)  # from the chassis' front to the wall
    assert g.config.margin_m - 0.01 <= gap <= 0.2
    assert g.slowed > 0 and g.stopped > 0
    # reversing away passes, and so does a command when the scan has gone stale (it says so)
    assert g.check(-0.15, 0.0, (x, 0.0, 0.0), t=0.2) == (-0.15, 0.0)
    assert g.check(0.5, 0.0, (x, 0.0, 0.0), t=5.0) == (0.5, 0.0) and g.unguarded == 1


def test_a_turn_that_sweeps_a_corner_into_a_post_is_stopped_one_away_is_not():
    g = Guard()
    # 0.32 m from the centre, 40 degrees right: beside the chassis' right side, just behind the
    # front right corner (31 degrees, 0.33 m out), which a clockwise turn sweeps over it
    post = np.array([[0.32 * math.cos(-0.70), 0.32 * math.sin(-0.70), 0.0]])
    g.add(post, (0.0, 0.0, 0.0), t=0.0)
    assert g.check(0.0, -1.0, (0.0, 0.0, 0.0), t=0.0) == (0.0, 0.0)  # swings the corner into it
    # swings the corner away (slowed: a second of it would bring the wheel, further back, close)
    v, w = g.check(0.0, 1.0, (0.0, 0.0, 0.0), t=0.0)
    assert v == 0.0 and w > 0.0
    assert g.check(-0.15, 0.0, (0.0, 0.0, 0.0), t=0.0) == (-0.15, 0.0)  # backs off
    assert g.stopped == 1


def test_a_point_inside_the_footprint_lets_the_robot_out_not_deeper():
    g = Guard()
    g.add(np.array([[0.25, 0.0, 0.0]]), (0.0, 0.0, 0.0), t=0.0)  # 3 cm inside the front
    assert g.check(0.3, 0.0, (0.0, 0.0, 0.0), t=0.0) == (0.0, 0.0)
    assert g.check(-0.15, 0.0, (0.0, 0.0, 0.0), t=0.0) == (-0.15, 0.0)


def test_driving_along_a_wall_close_by_goes_on():
    g = Guard()
    xs = np.arange(-2.0, 3.0, 0.02)
    g.add(np.column_stack([xs, np.full_like(xs, 0.34), np.zeros_like(xs)]), (0, 0, 0), t=0.0)
    assert g.check(0.5, 0.0, (0.0, 0.0, 0.0), t=0.0) == (0.5, 0.0)  # 0.03 m clear, parallel


def test_points_the_guard_ignores():
    g = Guard(GuardConfig(memory_s=1.0))
    ground = np.array([[0.4, 0.0, -0.15]])  # the ground ahead
    overhead = np.array([[0.4, 0.0, 0.4]])  # a branch it passes under
    far = np.array([[3.0, 0.0, 0.0]])
    g.add(np.concatenate([ground, overhead, far]), (0.0, 0.0, 0.0), t=0.0)
    assert len(g.points_near(0.0, 0.0)) == 0
    assert g.check(0.5, 0.0, (0.0, 0.0, 0.0), t=0.0) == (0.5, 0.0)
    # a scan is kept memory_s in the frame of the pose it came with, then dropped
    g.add(np.array([[0.5, 0.0, 0.0]]), (1.0, 1.0, math.pi / 2), t=0.5)
    assert np.allclose(g.points_near(1.0, 1.5), [[1.0, 1.5]], atol=0.02)
    g.add(np.zeros((0, 3)), (1.0, 1.0, 0.0), t=2.0)
    assert len(g.points_near(1.0, 1.5)) == 0
    off = Guard(GuardConfig(enabled=False))
    off.add(wall_scan(0.3), (0.0, 0.0, 0.0), t=0.0)
    assert off.check(1.0, 0.0, (0.0, 0.0, 0.0), t=0.0) == (1.0, 0.0)


@pytest.mark.parametrize(
    "bad",
    [{"footprint": [[0.0, 0.0, 0.3]]}, {"footprint": []}, {"z_min_m": 0.2, "z_max_m": 0.1}],
)
def test_a_guard_config_that_cannot_be_is_refused(bad):
    from smana.common.config.section import ConfigError

    with pytest.raises(ConfigError, match="explorer.guard"):
        GuardConfig(**bad)


def test_the_report_counts_what_the_guard_did():
    """The Exploration table's row: commands slowed and stopped, or that there was no scan."""
    from smana.deploy.report.render import render_markdown

    config = {
        "backend": "octree-max",
        "map_resolution_m": 0.1,
        "graph_resolution_m": 0.2,
        "world": "garden",
        "seed": 3,
        "label_noise": "off",
        "pose_noise_xy_m": 0.0,
        "pose_noise_yaw_rad": 0.0,
        "class_costs": [],
        "time_budget_s": 60.0,
    }
    guard = {"scans": 120, "slowed": 7, "stopped": 3, "unguarded": 0, "min_clearance_m": 0.05}
    m = {"run_dir": "runs/x", "config": config, "explorer": {"guard": guard}}
    row = "| the guard (safety scan): commands slowed / stopped | 7 / 3 (120 scans) |"
    assert row in render_markdown(m).splitlines()
    m["explorer"]["guard"] = dict(guard, scans=0, slowed=0, stopped=0, unguarded=50)
    assert "no safety scan: not guarded" in render_markdown(m)


def test_cells_match_a_unique_of_rows_and_scans_kept_together_count_once():
    from smana.services.explorer.guard import CELL_M, cells

    rng = np.random.default_rng(3)
    for scale in (1e-3, 1.0, 1e3, 1e6):
        xy = rng.uniform(-1, 1, (400, 2)) * scale
        want = np.unique(np.round(xy / CELL_M), axis=0) * CELL_M
        got = cells(xy)
        order = np.lexsort((got[:, 1], got[:, 0]))
        np.testing.assert_allclose(got[order], want, atol=1e-9)
    g = Guard()
    for k in range(10):  # the same wall in ten scans
        g.add(wall_scan(1.0), (0.0, 0.0, 0.0), t=0.1 * k)
    assert len(g.points_near(0.0, 0.0)) == len(cells(wall_scan(1.0)[:, :2]))
    # only what the footprint can reach within the horizon is asked for
    assert len(g.points_near(0.0, 0.0, 0.5)) == 0
