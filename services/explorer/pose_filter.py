"""The pose the explorer steers by: its localisation's poses, filtered with the twist it commanded.

A localisation source is noisy: the paper adds white noise to every pose (0.1 m and 0.02 rad at
its high setting), and a robot that steers by each raw pose swerves from side to side of its path
and can put its body on an obstacle its planner kept it clear of. A robot's controller steers by
a filtered pose (ROS: robot_localization's EKF fuses odometry and the localisation's poses).
smana's robot publishes no odometry, but the explorer knows the twist it commanded, and that is
the motion model here: a Kalman filter per coordinate (x, y), predicted with the commanded
forward speed along the measured heading, corrected by each pose. The yaw passes as it comes:
its noise is small beside what a turn does (0.02 rad is a degree), while a skid-steered robot's
turn rate strays far from the commanded one, so a filtered yaw would lag every turn.

The filter needs the localisation's noise, and a smana pose carries no covariance: it is
estimated from the innovations (Mehra 1970: the innovation's variance is the predicted variance
plus the measurement's), averaged over `window_s`. Noise-free poses give a variance near zero,
so the filter follows them (its gain goes to 1); noisy ones a larger one, so it averages them.
The process noise (`motion_sd_mps`) is how far the robot's motion strays from the command per
second (acceleration limits, wheel slip, a robot held by an obstacle).

A pose further from the prediction than `reset_m` (a localisation jump, a respawned robot) or
after a gap of `max_gap_s` resets the filter to it. Its parameters are [explorer.pose_filter]
(`PoseFilterConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from smana.common.config.explorer import PoseFilterConfig
from smana.services.explorer.follower import wrap_angle

# the smallest and largest measurement variance the estimate may take (standard deviations of
# 1 mm and 0.5 m): the floor keeps the gain below 1 by a hair, the ceiling keeps a robot held by
# an obstacle (innovations the command cannot explain) from freezing the estimate
R_MIN, R_MAX = 1e-6, 0.25


@dataclass
class PoseFilter:
    """`set_speed(v)` after each command sent; `update(x, y, yaw, t)` with each pose, which
    returns the filtered (x, y, yaw); `forget()` when the robot reappeared elsewhere."""

    config: PoseFilterConfig = field(default_factory=PoseFilterConfig)
    state: np.ndarray | None = None  # x, y
    var: np.ndarray = field(default_factory=lambda: np.zeros(2))  # of the state, per coordinate
    meas_var: np.ndarray = field(default_factory=lambda: np.full(2, R_MIN))  # the estimated R
    t: float | None = None
    speed: float = 0.0  # the forward speed last commanded, m/s
    n_resets: int = 0
    _yaw: float = 0.0

    def set_speed(self, linear_mps: float) -> None:
        self.speed = float(linear_mps)

    def forget(self) -> None:
        """Start afresh from the next pose."""
        self.state = None

    def reset(self, x: float, y: float, yaw: float, t: float) -> None:
        self.state = np.array([x, y], np.float64)
        self.var = self.meas_var.copy()
        self.t = t
        self._yaw = yaw
        self.n_resets += 1

    def update(self, x: float, y: float, yaw: float, t: float) -> tuple[float, float, float]:
        c = self.config
        if not c.enabled:
            return x, y, yaw
        if self.state is None or self.t is None or not (0.0 <= t - self.t <= c.max_gap_s):
            self.reset(x, y, yaw, t)
            return x, y, yaw
        dt = t - self.t
        self.t = t
        # predict with the commanded speed along the heading at mid-step
        mid = self._yaw + 0.5 * wrap_angle(yaw - self._yaw)
        self._yaw = yaw
        pred = self.state + self.speed * dt * np.array([math.cos(mid), math.sin(mid)])
        p_pred = self.var + (c.motion_sd_mps * dt) ** 2
        nu = np.array([x, y]) - pred
        if math.hypot(nu[0], nu[1]) > c.reset_m:
            self.reset(x, y, yaw, t)
            return x, y, yaw
        # the measurement's variance from the innovations: E[nu^2] = P_pred + R
        a = min(1.0, dt / c.window_s)
        r_obs = np.clip(nu * nu - p_pred, R_MIN, R_MAX)
        self.meas_var = (1.0 - a) * self.meas_var + a * r_obs
        gain = p_pred / (p_pred + self.meas_var)
        self.state = pred + gain * nu
        self.var = (1.0 - gain) * p_pred
        return float(self.state[0]), float(self.state[1]), yaw

    @property
    def noise_sd_m(self) -> float:
        """The estimated noise of the poses' x and y (standard deviation, m)."""
        return float(math.sqrt(self.meas_var.mean()))
