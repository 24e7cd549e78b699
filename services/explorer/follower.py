"""Path following for a differential-drive robot: pure pursuit with turn-in-place.

Pure pursuit steers toward the point one lookahead distance further along the path, with the
curvature of the circle through the robot and that point (kappa = 2 sin(alpha) / L). Two changes
suit a cluttered garden: when the lookahead point is far off the heading the robot turns in place
instead of sweeping a wide arc (the planner's path keeps clear of obstacles, a wide arc does not),
and speed falls with the heading error so corners are taken slowly. The lookahead point is
searched only ahead of the progress made so far, so a path that doubles back is not short-cut.

Its parameters are the config section [explorer.follower] (`FollowerConfig`), received as it is.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from smana.common.config.explorer import FollowerConfig


def wrap_angle(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class FollowCommand:
    linear_mps: float
    angular_radps: float
    done: bool
    progress_index: int
    cross_track_m: float
    # the point a turn on the spot turns towards (None for any other command): the explorer
    # creeps towards it instead where the turn would sweep an obstacle
    turn_target: tuple[float, float] | None = None
    final_turn: bool = False  # turning on the spot to the path's final heading


@dataclass
class PurePursuit:
    """Follows one path; `set_path` starts a new one; `command(x, y, yaw)` each control tick."""

    config: FollowerConfig = field(default_factory=FollowerConfig)
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    final_yaw: float | None = None
    tolerance_m: float | None = None  # this path's goal tolerance (None: config.goal_tolerance_m)
    _progress: int = 0
    _cum: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _arrived: bool = False

    def set_path(
        self, path_xy: np.ndarray, final_yaw: float | None = None, tolerance_m: float | None = None
    ) -> None:
        path = np.asarray(path_xy, np.float64)
        if path.ndim != 2 or path.shape[1] < 2 or len(path) == 0:
            raise ValueError(f"path must be (K, 2|3) with K >= 1, got shape {path.shape}")
        if not np.isfinite(path[:, :2]).all():
            raise ValueError("path has non-finite points")
        self.path = path[:, :2].copy()
        seg = np.hypot(*np.diff(self.path, axis=0).T) if len(path) > 1 else np.zeros(0)
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._progress = 0
        self._arrived = False
        self.final_yaw = final_yaw
        self.tolerance_m = tolerance_m

    def skip_to_nearest(self, x: float, y: float) -> None:
        """Go on from the path point nearest (x, y), wherever it is (a path resumed by a process
        that took over, the robot further along than the window `command` searches)."""
        if self.active:
            d = np.hypot(*(self.path - np.array([x, y], np.float64)).T)
            self._progress = int(np.argmin(d))

    @property
    def active(self) -> bool:
        return len(self.path) > 0

    @property
    def remaining(self) -> np.ndarray:
        """Path points not passed yet (for blocked-path checks)."""
        return self.path[self._progress :]

    def remaining_length_m(self) -> float:
        if not self.active:
            return 0.0
        return float(self._cum[-1] - self._cum[self._progress])

    def _nearest_ahead(self, p: np.ndarray) -> tuple[int, float]:
        # search a window ahead of the progress so that a loop in the path is not skipped
        lo = self._progress
        window_end = self._cum[lo] + 2.0 * self.config.lookahead_m + 0.5
        hi = min(len(self.path), lo + 1 + int(np.searchsorted(self._cum[lo:], window_end)))
        d = np.hypot(*(self.path[lo:hi] - p).T)
        k = int(np.argmin(d))
        return lo + k, float(d[k])

    def command(
        self, x: float, y: float, yaw: float, is_clear: Callable | None = None
    ) -> FollowCommand:
        """`is_clear(p, q)`, when given, says whether the straight line between two points keeps
        off obstacles; the lookahead point is pulled back along the path until it does, so that
        corners of the path are not cut through a safety zone."""
        cfg = self.config
        if not self.active:
            return FollowCommand(0.0, 0.0, True, 0, 0.0)
        p = np.array([x, y], np.float64)
        self._progress, cross = self._nearest_ahead(p)
        goal = self.path[-1]
        to_goal = float(np.hypot(*(goal - p)))
        tol = cfg.goal_tolerance_m if self.tolerance_m is None else self.tolerance_m
        if self._arrived or to_goal <= tol:
            self._arrived = True
            self._progress = len(self.path) - 1
            if self.final_yaw is None:
                return FollowCommand(0.0, 0.0, True, self._progress, cross)
            err = wrap_angle(self.final_yaw - yaw)
            if abs(err) <= cfg.final_yaw_tolerance_rad:
                return FollowCommand(0.0, 0.0, True, self._progress, cross)
            w = math.copysign(min(cfg.max_angular_radps, max(0.3, 2.0 * abs(err))), err)
            return FollowCommand(0.0, w, False, self._progress, cross, final_turn=True)

        # lookahead point: the first path point at least L along the path from the nearest point,
        # and at least L away from the robot (otherwise a robot off the path chases its own foot)
        target_s = self._cum[self._progress] + cfg.lookahead_m
        j = int(np.searchsorted(self._cum, target_s))
        j = min(max(j, self._progress), len(self.path) - 1)
        while j < len(self.path) - 1 and np.hypot(*(self.path[j] - p)) < cfg.lookahead_m:
            j += 1
        if is_clear is not None:
            while j > self._progress + 1 and not is_clear(p, self.path[j]):
                j -= 1
        target = self.path[j]
        dx, dy = target - p
        dist = math.hypot(dx, dy)
        alpha = wrap_angle(math.atan2(dy, dx) - yaw)
        if abs(alpha) > cfg.turn_in_place_rad:
            w = math.copysign(cfg.max_angular_radps, alpha)
            turn_target = (float(target[0]), float(target[1]))
            return FollowCommand(0.0, w, False, self._progress, cross, turn_target)
        taper = max(0.0, 1.0 - abs(alpha) / cfg.slow_down_rad)
        # slow down on the last metre so the goal is not overshot at full speed
        v = cfg.max_linear_mps * taper * min(1.0, 0.3 + to_goal)
        v = min(v, cfg.max_linear_mps)
        kappa = 2.0 * math.sin(alpha) / max(dist, 1e-6)
        w = v * kappa
        if abs(w) > cfg.max_angular_radps:
            # keep the arc: scale both speeds down together
            v *= cfg.max_angular_radps / abs(w)
            w = math.copysign(cfg.max_angular_radps, w)
        return FollowCommand(v, w, False, self._progress, cross)
