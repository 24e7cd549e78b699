"""The explorer's pose filter (services/explorer/pose_filter.py) on a simulated unicycle: the
truth moves as a rate-limited robot follows its commands, the localisation adds white noise (and
optionally a slow drift), and the filtered pose must be closer to the truth than the raw one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config.explorer import PoseFilterConfig
from smana.services.explorer.follower import wrap_angle as wrap
from smana.services.explorer.pose_filter import PoseFilter


def _drive(sd_xy, sd_yaw, seed=0, seconds=60.0, hz=20.0, stall=None, config=None):
    """Truth, raw and filtered poses of a robot driving curves; the applied twist lags the
    command (acceleration limits); during `stall` (t0, t1) the robot is held where it is."""
    rng = np.random.default_rng(seed)
    f = PoseFilter(config or PoseFilterConfig())
    x = y = yaw = 0.0
    v = w = 0.0
    dt = 1.0 / hz
    truth, raw, filt = [], [], []
    for k in range(int(seconds * hz)):
        t = k * dt
        cmd = (0.4 if (t // 7) % 3 else 0.0, 0.6 * math.sin(0.3 * t))
        f.set_speed(cmd[0])
        v += float(np.clip(cmd[0] - v, -1.5 * dt, 1.5 * dt))
        w += float(np.clip(cmd[1] - w, -4.0 * dt, 4.0 * dt))
        held = stall is not None and stall[0] <= t < stall[1]
        if not held:
            x += v * dt * math.cos(yaw)
            y += v * dt * math.sin(yaw)
            yaw = wrap(yaw + w * dt)
        z = (x + rng.normal(0, sd_xy), y + rng.normal(0, sd_xy), wrap(yaw + rng.normal(0, sd_yaw)))
        truth.append((x, y, yaw))
        raw.append(z)
        filt.append(f.update(*z, t))
    return np.array(truth), np.array(raw), np.array(filt), f


def _err(a, b, skip=40):
    d = np.hypot(a[skip:, 0] - b[skip:, 0], a[skip:, 1] - b[skip:, 1])
    return float(np.sqrt(np.mean(d * d)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_poses_are_averaged(seed):
    truth, raw, filt, f = _drive(0.1, 0.02, seed)
    assert _err(truth, raw) == pytest.approx(0.1 * math.sqrt(2), rel=0.1)
    assert _err(truth, filt) < 0.45 * _err(truth, raw)
    assert np.array_equal(filt[:, 2], raw[:, 2])  # the yaw passes as it comes
    assert f.noise_sd_m == pytest.approx(0.1, rel=0.35)  # it has found the noise it was given
    assert f.n_resets == 1  # the first pose only


def test_noise_free_poses_pass_through():
    truth, raw, filt, _ = _drive(0.0, 0.0)
    assert np.abs(filt[40:, :2] - truth[40:, :2]).max() < 0.01


def test_disabled_is_the_raw_pose():
    _, raw, filt, _ = _drive(0.1, 0.02, config=PoseFilterConfig(enabled=False))
    assert np.array_equal(raw, filt)


def test_a_held_robot_is_followed_not_lost():
    # commanded forward, held for 4 s: the filter must come back to the truth, not run away
    truth, raw, filt, _ = _drive(0.1, 0.02, stall=(20.0, 24.0))
    d = np.hypot(*(filt[:, :2] - truth[:, :2]).T)
    k = int(24.0 * 20)
    assert d[k - 20 : k].max() < 0.5  # held: it lags the truth but stays near it
    assert d[k + 100 :].max() < 0.2  # 5 s later it has caught up


def test_a_jump_resets_the_filter():
    f = PoseFilter()
    for k in range(20):
        f.update(0.0, 0.0, 0.0, k * 0.05)
    assert f.update(5.0, 0.0, 1.0, 1.0) == (5.0, 0.0, 1.0)
    assert f.n_resets == 2
    # so does a gap in the poses, and a pose from the past
    assert f.update(5.1, 0.0, 1.0, 3.0) == (5.1, 0.0, 1.0)
    assert f.update(5.2, 0.0, 1.0, 2.0) == (5.2, 0.0, 1.0)
    assert f.n_resets == 4
