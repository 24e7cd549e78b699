"""What one fleet member's explorer knows of the others, and the rules it explores by with them.

A member's explorer chooses its next-best view itself, on the fleet's shared graph, and then claims
it from the coordinator (services/coordinator). This module holds the other members' last poses
(their `robot/pose`, stamped on the same clock as ours: one simulator, or hosts kept in time by
NTP) and goals (the coordinator's `claims`), and turns them into the three rules of issue 17:

- views are chosen apart: a candidate within `fleet.goal_separation_m` of another member's goal is
  not considered (the coordinator refuses it anyway), and unknown area within
  `fleet.claim_radius_m` of another member's goal counts for nothing in a view's gain (that member
  will see it): views near another's goal are discounted by what that member will map;
- other members are moving obstacles: the follower stops while one is within
  `fleet.stop_distance_m` ahead (the planner, for its part, does not route through them);
- a member with nothing to do moves out of the way of a member that comes within
  `fleet.stop_distance_m` (an idle robot parked in a narrow path would hold it up);
- a member blocked by another for long re-plans: the one later in `fleet.robots` first (it yields),
  the earlier one only after three times as long, so two members facing each other do not both
  turn away.
"""

from __future__ import annotations

import math

import numpy as np

from smana.common.config.fleet import FleetConfig

AHEAD_HALF_ANGLE_RAD = math.radians(60.0)  # "ahead": within 60 degrees of the heading
YIELD_AFTER_S = 3.0  # blocked this long by a member with priority: give way (re-plan)


class Team:
    def __init__(self, config: FleetConfig, me: str):
        if me not in config.robots:
            raise ValueError(f"{me!r} is not a member of the fleet {config.robots}")
        self.config = config
        self.me = me
        self.rank = config.robots.index(me)  # 0 has the right of way over everyone
        self.positions: dict[str, tuple[float, float, float]] = {}  # name -> (x, y, stamp)
        self.goals: dict[str, np.ndarray] = {}  # name -> xy, from the coordinator
        self.blocked_by: str | None = None
        self.blocked_since: float | None = None
        self.n_stops = 0  # control ticks the robot was held for another member

    # -- inputs -------------------------------------------------------------------------------

    def update_position(self, name: str, x: float, y: float, stamp_s: float) -> None:
        if name != self.me and name in self.config.robots:
            self.positions[name] = (float(x), float(y), float(stamp_s))

    def update_goals(self, claims: dict) -> None:
        """The coordinator's claims ({member: [x, y]}); ours is left out."""
        goals = {}
        for name, xy in claims.items():
            if name != self.me and name in self.config.robots:
                a = np.asarray(xy, float).reshape(-1)[:2]
                if a.shape == (2,) and np.isfinite(a).all():
                    goals[name] = a
        self.goals = goals

    def add_goal(self, name: str, xy) -> None:
        """A goal we learnt of from a refused claim, before the next claims message."""
        if name != self.me and name in self.config.robots and xy is not None:
            self.goals[name] = np.asarray(xy, float)[:2]

    # -- what they mean ---------------------------------------------------------------------------

    def others_xy(self, t_now: float) -> np.ndarray:
        """Positions (K, 2) of the members heard of within `pose_timeout_s` of `t_now`."""
        fresh = [
            (x, y)
            for x, y, t in self.positions.values()
            if abs(t_now - t) <= self.config.pose_timeout_s
        ]
        return np.array(fresh, float).reshape(-1, 2)

    def goals_xy(self) -> np.ndarray:
        return np.array(list(self.goals.values()), float).reshape(-1, 2)

    def apart(self, xy: np.ndarray) -> np.ndarray:
        """Which candidate positions (N, 2) keep `goal_separation_m` from every other goal."""
        goals = self.goals_xy()
        keep = np.ones(len(xy), bool)
        for g in goals:
            keep &= np.hypot(*(xy - g).T) >= self.config.goal_separation_m
        return keep

    def claimed(self, origin_xy, resolution_m: float, shape) -> np.ndarray:
        """Cells (of a grid box) within `claim_radius_m` of another member's goal."""
        out = np.zeros(shape, bool)
        r = self.config.claim_radius_m
        if r <= 0:
            return out
        cx = origin_xy[0] + (np.arange(shape[0]) + 0.5) * resolution_m
        cy = origin_xy[1] + (np.arange(shape[1]) + 0.5) * resolution_m
        for gx, gy in self.goals_xy():
            i = np.flatnonzero(np.abs(cx - gx) <= r)
            j = np.flatnonzero(np.abs(cy - gy) <= r)
            if len(i) and len(j):
                d2 = (cx[i, None] - gx) ** 2 + (cy[None, j] - gy) ** 2
                out[i[0] : i[-1] + 1, j[0] : j[-1] + 1] |= d2 <= r * r
        return out

    def ahead(self, x: float, y: float, yaw: float, t_now: float) -> str | None:
        """The nearest member within `stop_distance_m` ahead of the robot, or None."""
        best, best_d = None, math.inf
        for name, (ox, oy, t) in self.positions.items():
            if abs(t_now - t) > self.config.pose_timeout_s:
                continue
            d = math.hypot(ox - x, oy - y)
            if d > self.config.stop_distance_m or d >= best_d:
                continue
            bearing = math.atan2(oy - y, ox - x) - yaw
            bearing = math.atan2(math.sin(bearing), math.cos(bearing))
            if abs(bearing) <= AHEAD_HALF_ANGLE_RAD:
                best, best_d = name, d
        return best

    def make_way(self, x: float, y: float, t_now: float) -> np.ndarray | None:
        """For a member with nothing to do: the direction (unit xy) away from the nearest member
        within `stop_distance_m`, or None. An idle robot parked in a path would hold up a member
        that must pass it (on a 1.4 m garden path the planner cannot go round)."""
        near = self.others_xy(t_now)
        if len(near) == 0:
            return None
        d = np.hypot(*(near - (x, y)).T)
        k = int(np.argmin(d))
        if d[k] > self.config.stop_distance_m or d[k] < 1e-6:
            return None
        return (np.array([x, y]) - near[k]) / d[k]

    def hold(self, x: float, y: float, yaw: float, t_now: float) -> tuple[bool, bool]:
        """(stop now, give the goal up and re-plan): a member ahead stops us; held by it for
        `YIELD_AFTER_S` (three times that by a member that yields to us) we re-plan."""
        other = self.ahead(x, y, yaw, t_now)
        if other is None:
            self.blocked_by = self.blocked_since = None
            return False, False
        if other != self.blocked_by:
            self.blocked_by, self.blocked_since = other, t_now
        self.n_stops += 1
        patience = YIELD_AFTER_S * (1 if self.config.robots.index(other) < self.rank else 3)
        if t_now - self.blocked_since >= patience:
            self.blocked_since = t_now  # once per patience, not every tick
            return True, True
        return True, False
