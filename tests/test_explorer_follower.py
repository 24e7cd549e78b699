"""Pure pursuit on a unicycle: reaches the goal, stays near the path, turns in place when needed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config.explorer import FollowerConfig
from smana.services.explorer.follower import PurePursuit, wrap_angle

# the follower's own defaults when these tests were written ([explorer.follower] has the product's)
OLD = {"max_linear_mps": 0.5, "max_angular_radps": 1.2, "goal_tolerance_m": 0.15}


def _drive(pp: PurePursuit, x, y, yaw, dt=0.05, t_max=60.0):
    trace = []
    for _ in range(int(t_max / dt)):
        cmd = pp.command(x, y, yaw)
        trace.append((x, y, yaw, cmd.linear_mps, cmd.angular_radps))
        if cmd.done:
            return x, y, yaw, np.array(trace), True
        x += cmd.linear_mps * math.cos(yaw) * dt
        y += cmd.linear_mps * math.sin(yaw) * dt
        yaw = wrap_angle(yaw + cmd.angular_radps * dt)
    return x, y, yaw, np.array(trace), False


def _dist_to_polyline(p, path):
    best = math.inf
    for a, b in zip(path[:-1], path[1:], strict=True):
        ab = b - a
        t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
        best = min(best, float(np.hypot(*(a + t * ab - p))))
    return best


def _dense(corners, step=0.1):
    pts = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / step)))
        pts += [a + (b - a) * k / n for k in range(1, n + 1)]
    return np.array(pts)


def test_follows_an_l_shaped_path_closely_and_stops_at_the_goal_with_its_yaw():
    path = _dense(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [1.0, 2.0]]))
    cfg = FollowerConfig(**{**OLD, "lookahead_m": 0.3})
    pp = PurePursuit(cfg)
    pp.set_path(path, final_yaw=math.pi / 2)
    x, y, yaw, trace, done = _drive(pp, 0.0, 0.0, 0.0)
    assert done
    assert math.hypot(x - 1.0, y - 2.0) <= cfg.goal_tolerance_m + 0.03
    assert abs(wrap_angle(yaw - math.pi / 2)) <= cfg.final_yaw_tolerance_rad + 0.05
    # corners are cut by less than the lookahead distance
    worst = max(_dist_to_polyline(np.array(p[:2]), path) for p in trace)
    assert worst < 0.2
    assert np.abs(trace[:, 3]).max() <= cfg.max_linear_mps + 1e-9
    assert np.abs(trace[:, 4]).max() <= cfg.max_angular_radps + 1e-9


def test_turns_in_place_when_the_path_is_behind():
    pp = PurePursuit(FollowerConfig(**OLD))
    pp.set_path(_dense(np.array([[0.0, 0.0], [-2.0, 0.0]])))
    cmd = pp.command(0.0, 0.0, 0.0)
    assert cmd.linear_mps == 0.0 and abs(cmd.angular_radps) > 0
    x, y, _, trace, done = _drive(pp, 0.0, 0.0, 0.0)
    assert done and math.hypot(x + 2, y) < 0.2
    # while turning it never backed away from the path
    assert trace[:, 3].min() >= 0.0


def test_a_path_that_doubles_back_is_not_short_cut():
    # out 2 m and back 1.6 m, 0.2 m apart: nearest-point search over the whole path would jump
    path = _dense(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 0.2], [0.4, 0.2]]))
    pp = PurePursuit(FollowerConfig(**OLD, lookahead_m=0.25))
    pp.set_path(path)
    _, _, _, trace, done = _drive(pp, 0.0, 0.0, 0.0)
    assert done
    assert trace[:, 0].max() > 1.8  # went all the way out before coming back


def test_single_point_path_and_bad_paths():
    pp = PurePursuit()
    pp.set_path(np.array([[0.05, 0.0]]))
    assert pp.command(0.0, 0.0, 0.0).done
    with pytest.raises(ValueError):
        pp.set_path(np.zeros((0, 2)))
    with pytest.raises(ValueError):
        pp.set_path(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError):
        FollowerConfig(lookahead_m=0)
    assert PurePursuit().command(0, 0, 0).done  # no path: stand still
