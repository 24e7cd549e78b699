"""How the explorer drives to its goal (`Explorer.control`): the follower's command slowed near
obstacles, reversing out of where it got stuck, one spin on the spot where nothing was found,
giving way in a fleet; and the checks that a path is blocked or the robot stuck. Part of
`exploration.Explorer`; no wiring.

A turn on the spot sweeps the footprint's circumscribed circle (`turn_clearance_m`): a corner of
the chassis reaches obstacles the robot drove past side-on (a gap between two hedges). Where a
known obstacle node lies in that circle the robot does not turn there: the follower's turn
becomes a straight creep along the robot's axis away from the nearest obstacle node (in reverse
from one ahead, forward from one behind), while that way is clear, until the circle is free; a
look-around spin is not taken there, nor the turn to a reached view's heading (the view is taken
as it stands). Only when that way is not clear does it turn as it was told, and a goal it was
sent (a ROS 2 goal's heading) is always faced.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from smana.services.explorer import frontier as fr
from smana.services.explorer.follower import wrap_angle

BACK_OFF_S = 2.0  # stuck: reverse this long at creep speed (when clear behind) before going on
BACK_OFF_M = 0.4  # how far behind the robot must be clear of known obstacles to reverse
CREEP_CHECK_M = 0.3  # creeping instead of turning: this far ahead (or behind) must be clear
SWATH_M = 0.2  # of known obstacles, this far either side of the robot's axis (its half-width)
OBSTACLE_ONLY = fr.OBSTACLE


class Driving:
    """The part of `Explorer` that drives. It uses the state `Explorer.__init__` sets
    (`config`, `grid`, `pose`, `goal`, `follower`, `team`, `_spin`, `_progress_mark`, ...)."""

    def control(self) -> tuple[float, float]:
        """Velocity command (v m/s, w rad/s) for the current tick, as the guard lets it go out
        (guard.py: slowed or stopped before the body meets what the safety scan shows)."""
        v, w = self._command()
        return self.guard.check(v, w, self.pose, self.t_now)

    def _command(self) -> tuple[float, float]:
        """The command before the guard's check."""
        if self.done or self.pose is None:
            return 0.0, 0.0
        x, y, yaw = self.pose
        if self._spin is not None:
            turned = self._spin["turned"] + abs(wrap_angle(yaw - self._spin["last_yaw"]))
            self._spin.update(turned=turned, last_yaw=yaw)
            if turned >= 2 * math.pi - 0.2 or self.t_now - self._spin["t0"] > 30.0:
                self._spin = None
                self._empty_plans = 0
                self._t_last_plan = -math.inf
                return 0.0, 0.0
            return 0.0, self.config.follower.max_angular_radps * 0.6
        if self._back_off_until is not None:
            if self.t_now < self._back_off_until:
                p = np.array([x, y])
                behind = p - BACK_OFF_M * np.array([math.cos(yaw), math.sin(yaw)])
                # clear of known obstacles, and of fleet members: reversing is blind to them
                member = self.team is not None and self.team.ahead(x, y, yaw + math.pi, self.t_now)
                if self._segment_clear(p, behind, OBSTACLE_ONLY) and not member:
                    return -self.config.creep_speed_mps, 0.0
            self._back_off_until = None
            if self.goal is not None:  # the new path starts where the robot now is
                self._progress_mark = (self.t_now, self.follower.remaining_length_m())
        if self.goal is None:
            return self._make_way(x, y, yaw)
        cmd = self.follower.command(x, y, yaw, self._segment_clear)
        if cmd.turn_target is not None and not self._turn_clear(x, y):
            creep = self._creep_clear(x, y, yaw, np.asarray(cmd.turn_target))
            if creep is not None:
                self.n_turns_avoided += 1
                return creep
        if cmd.final_turn and not self.nav_active and not self._turn_clear(x, y):
            # a view reached where facing its heading would sweep an obstacle: seen from here
            self.n_turns_avoided += 1
            cmd = dataclasses.replace(cmd, linear_mps=0.0, angular_radps=0.0, done=True)
        if cmd.done and self.nav_active:
            self._nav_arrived()
            return 0.0, 0.0
        if cmd.done:
            self._forget(self.goal.choice.xy, seconds=self.config.dwell_s + 5.0)
            self._set_goal(None)
            self._t_arrived = self.t_now
            return 0.0, 0.0
        v, w = cmd.linear_mps, cmd.angular_radps
        if self.team is not None and v > 0:
            stop, give_way = self.team.hold(x, y, yaw, self.t_now)
            if stop:
                v = 0.0  # turning on the spot stays allowed: it may point the robot away
            self._yield |= give_way
        if self.grid is not None and v > self.config.creep_speed_mps:
            here = np.array(self.grid.cell_of((x, y)))
            if self.grid.inside(here).all() and _blocking(self.grid.flags[here[0], here[1]]):
                w *= self.config.creep_speed_mps / v  # same arc, slower
                v = self.config.creep_speed_mps
        return v, w

    def _make_way(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        """Idle in a fleet: step away from a member that comes close (team.py), slowly, and
        only onto ground known to be clear."""
        away = None if self.team is None else self.team.make_way(x, y, self.t_now)
        if away is None:
            return 0.0, 0.0
        err = wrap_angle(math.atan2(away[1], away[0]) - yaw)
        fc = self.config.follower
        w = max(-fc.max_angular_radps, min(fc.max_angular_radps, 2.0 * err))
        if abs(err) > 0.5:
            return 0.0, w
        p = np.array([x, y])
        if not self._segment_clear(p, p + 0.5 * away):
            return 0.0, 0.0
        return self.config.creep_speed_mps, w

    def _path_blocked(self) -> bool:
        g = self.grid
        rem = self.follower.remaining
        if len(rem) == 0:
            return False
        cells = g.cells_of(rem)
        cells = cells[g.inside(cells)]
        bad = _blocking(g.flags[cells[:, 0], cells[:, 1]])
        # skip the node the robot is on: leaving a safety zone it was put in must stay possible
        here = g.cell_of(self.pose[:2])
        mine = (cells[:, 0] == here[0]) & (cells[:, 1] == here[1])
        return bool((bad & ~mine).any())

    def _segment_clear(self, p: np.ndarray, q: np.ndarray, bits: int | None = None) -> bool:
        """No known obstacle or safety-zone node (or nodes with `bits`) on the segment p-q, the
        node of p excepted."""
        g = self.grid
        if g is None:
            return True
        n = max(2, int(math.ceil(np.hypot(*(q - p)) / (0.5 * g.resolution_m))) + 1)
        pts = p + (q - p) * np.linspace(0.0, 1.0, n)[:, None]
        cells = g.cells_of(pts)
        cells = cells[g.inside(cells)]
        here = np.array(g.cell_of(p))
        cells = cells[(cells != here).any(axis=1)]
        return not _blocking(g.flags[cells[:, 0], cells[:, 1]], bits).any()

    def _stuck(self) -> bool:
        if self._progress_mark is None:
            return False
        t0, rem0 = self._progress_mark
        rem = self.follower.remaining_length_m()
        if rem < rem0 - 0.1:
            self._progress_mark = (self.t_now, rem)
            return False
        return self.t_now - t0 > self.config.stuck_timeout_s

    def _obstacles_within(self, x: float, y: float, r: float) -> np.ndarray:
        """Centres (K, 2) of the known obstacle nodes whose square comes within `r` of (x, y)."""
        g = self.grid
        res = g.resolution_m
        lo = np.maximum(np.array(g.cell_of((x - r, y - r))), 0)
        hi = np.minimum(np.array(g.cell_of((x + r, y + r))) + 1, g.flags.shape)
        if (hi <= lo).any():
            return np.zeros((0, 2))
        cells = np.argwhere(g.flags[lo[0] : hi[0], lo[1] : hi[1]] & fr.OBSTACLE) + lo
        centres = g.centres(cells)
        # distance to the node's square, not its centre
        d = np.maximum(np.abs(centres - np.array([x, y])) - res / 2, 0.0)
        return centres[np.hypot(d[:, 0], d[:, 1]) < r]

    def _turn_clear(self, x: float, y: float) -> bool:
        """No known obstacle node within `turn_clearance_m` of (x, y): the robot may turn on
        the spot there."""
        r = self.config.turn_clearance_m
        if self.grid is None or r <= 0:
            return True
        return not len(self._obstacles_within(x, y, r))

    def _swath_clear(self, p: np.ndarray, q: np.ndarray) -> bool:
        """No known obstacle node within SWATH_M of the segment p-q (sampled every half
        node): the chassis can drive straight along it."""
        n = max(2, int(math.ceil(np.hypot(*(q - p)) / (0.5 * self.grid.resolution_m))) + 1)
        for c in p + (q - p) * np.linspace(0.0, 1.0, n)[:, None]:
            if len(self._obstacles_within(float(c[0]), float(c[1]), SWATH_M)):
                return False
        return True

    def _creep_clear(self, x: float, y: float, yaw: float, target: np.ndarray):
        """Instead of a turn on the spot that would sweep an obstacle: (v, 0) at creep speed,
        straight away from the nearest obstacle node along the robot's axis (forward when it
        lies behind, in reverse when ahead; towards `target` when it lies abeam), while that
        way is clear; None when it is not."""
        p = np.array([x, y])
        heading = np.array([math.cos(yaw), math.sin(yaw)])
        near = self._obstacles_within(x, y, self.config.turn_clearance_m)
        o = near[np.argmin(np.hypot(*(near - p).T))]
        along = float((p - o) @ heading)
        if abs(along) < 0.5 * self.grid.resolution_m:
            along = float((target - p) @ heading)
        sign = 1.0 if along >= 0.0 else -1.0
        if not self._swath_clear(p, p + sign * CREEP_CHECK_M * heading):
            return None
        return sign * self.config.creep_speed_mps, 0.0

    def _maybe_spin(self) -> bool:
        """Turn once on the spot where nothing was found: the camera sees 57 degrees, and what is
        behind the robot may hold a frontier. Only once per place, and never where the turn
        would sweep an obstacle (`turn_clearance_m`)."""
        x, y, yaw = self.pose
        here = np.array([x, y])
        if any(np.hypot(*(here - p)) < 1.0 for p in self._spun_at):
            return False
        if not self._turn_clear(x, y):
            return False
        self._spun_at.append(here)
        self._spin = {"t0": self.t_now, "turned": 0.0, "last_yaw": yaw}
        return True


def _blocking(flags: np.ndarray, bits: int | None = None) -> np.ndarray:
    """Known nodes the robot must not enter: obstacles and their safety zone (or `bits`)."""
    bits = fr.OBSTACLE | fr.SAFETY_ZONE if bits is None else bits
    return ((flags & fr.KNOWN) != 0) & ((flags & bits) != 0)
