"""The long-drive generator (lab/data/longdrive.py) against a slow, obvious ray cast."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.lab.data import longdrive
from smana.lab.data.synthetic import BUSH, DIRT, GRASS, TREE, terrain_height


def _obstacles_near(world, x, y, reach):
    """Every obstacle of every cell within `reach` of (x, y), by brute force."""
    c = world.cell_m
    out = []
    buf = np.empty(6)
    for i in range(math.floor((x - reach) / c), math.floor((x + reach) / c) + 1):
        for j in range(math.floor((y - reach) / c), math.floor((y + reach) / c) + 1):
            if longdrive._cell_obstacle(i, j, world.params, buf):
                out.append(buf.copy())
    return out


def _reference_ray(world, origin, d, max_range, obstacles):
    """First hit: every obstacle by a closed-form cylinder test, the ground by 1 cm steps and
    bisection (no DDA, no adaptive step)."""
    ox, oy, oz = origin
    best, lab = max_range, -1
    for cx, cy, r, z0, z1, label in obstacles:
        ts = []
        a = d[0] ** 2 + d[1] ** 2
        fx, fy = ox - cx, oy - cy
        if a > 1e-12:
            b = fx * d[0] + fy * d[1]
            disc = b * b - a * (fx * fx + fy * fy - r * r)
            if disc >= 0:
                for t in ((-b - math.sqrt(disc)) / a, (-b + math.sqrt(disc)) / a):
                    if t > 1e-6 and z0 <= oz + t * d[2] <= z1:
                        ts.append(t)
        if abs(d[2]) > 1e-12:
            t = (z1 - oz) / d[2]
            if t > 1e-6 and (fx + t * d[0]) ** 2 + (fy + t * d[1]) ** 2 <= r * r:
                ts.append(t)
        if ts and min(ts) < best:
            best, lab = min(ts), int(label)

    def below(t):
        return oz + d[2] * t - terrain_height(ox + d[0] * t, oy + d[1] * t)

    t, step = 0.05, 0.01
    while t < best:
        t2 = min(t + step, best)
        if below(t2) <= 0:
            lo, hi = t, t2
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if below(mid) > 0 else (lo, mid)
            best = hi
            lab = (
                DIRT
                if longdrive._trail_distance(ox + d[0] * hi, oy + d[1] * hi, world.params)
                <= world.trail_half_width_m
                else GRASS
            )
            break
        if d[2] >= 0 and oz + d[2] * t2 > 1.0:
            break
        t = t2
    return best, lab


def test_scan_matches_a_slow_reference_ray_cast():
    world = longdrive.DriveWorld(seed=3, side_m=200.0, lane_spacing_m=20.0, density=0.6)
    max_range = 25.0
    hits = {TREE: 0, BUSH: 0, GRASS: 0, DIRT: 0}
    for d_m in (0.0, 37.0, 230.0):  # along a lane, and on the join between two lanes
        origin, heading = longdrive.sensor_origin(world, d_m)
        dirs = longdrive.world_rays(heading, beams=8, columns=64)
        t, lab = longdrive.cast_rays(world, origin, dirs, max_range)
        obstacles = _obstacles_near(world, origin[0], origin[1], max_range + world.cell_m)
        for r in range(len(dirs)):
            t_ref, lab_ref = _reference_ray(world, origin, dirs[r], max_range, obstacles)
            if lab_ref < 0:
                assert not np.isfinite(t[r]), (d_m, r, t[r])
                continue
            assert t[r] == pytest.approx(t_ref, abs=2e-3), (d_m, r)
            assert lab[r] == lab_ref, (d_m, r)
            hits[lab_ref] += 1
    assert all(n > 0 for n in hits.values()), hits  # the case reaches every kind of surface


def test_drive_is_free_and_scans_are_os1_like():
    drive = longdrive.Drive(longdrive.DriveWorld(seed=1))
    world = drive.world
    assert drive.n_scans(1.0) == 6667  # 1 km at 1.5 m/s and 10 Hz
    for k in (0, 3000, 40000):
        x, y, _ = world.position(drive.distance_m(k))
        assert longdrive._trail_distance(x, y, world.params) < 1e-9
        # no obstacle within the clearance of the robot
        for cx, cy, r, *_ in _obstacles_near(world, x, y, 10.0):
            assert math.hypot(cx - x, cy - y) >= world.clearance_m + r - 1e-9
    pts, lab, origin = drive.scan(7)
    assert 0.4 * 131072 < len(pts) <= 131072  # the upper beams see the sky where no tree is
    assert pts.dtype == np.float32 and lab.dtype == np.uint16
    assert np.linalg.norm(pts - origin, axis=1).max() <= drive.max_range_m + 1e-3
    again = drive.scan(7)
    assert np.array_equal(again[0], pts) and np.array_equal(again[1], lab)


def test_bad_world_is_refused():
    with pytest.raises(ValueError, match="density"):
        longdrive.DriveWorld(density=2.0)
    with pytest.raises(ValueError, match="max_range_m"):
        longdrive.cast_rays(longdrive.DriveWorld(), np.zeros(3), np.array([[1.0, 0, 0]]), 0.0)
