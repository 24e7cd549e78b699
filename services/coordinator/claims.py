"""The claim book: every fleet member's current goal, and the rule that keeps goals apart.

The coordinator's core, without zenoh. Each member's explorer chooses its next-best view itself
(from the shared graph, with the views near other members' goals discounted) and then claims it:
the book grants a goal unless another member's goal lies within `goal_separation_m` of it, so no
two members head for the same frontier. Claims are answered one at a time, in arrival order (the
service's main loop), which settles two members choosing the same place at the same moment: the
first one wins, the second one is told who holds it and plans again.

A claim ends when its member claims something else, releases it (goal reached, nothing worth a
trip, done), or falls silent for `ttl_s` (its explorer stopped, or its link to the base dropped:
the place is free for the others). A claim whose member has not moved `STALL_M` in `stall_s`
(wedged somewhere, or held up) is stalled: it stays in the book but holds nobody back (it is left
out of `snapshot()` and of the separation test) until the member moves again, so one stuck robot
cannot keep the others waiting for the views it will not reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

STALL_M = 1.0  # a member that moved less than this in `stall_s` is stalled (a back-off is 0.3 m)


@dataclass
class Claim:
    xy: tuple[float, float]
    t: float  # when it was claimed or last confirmed (the book's clock)


@dataclass
class Progress:
    distance_m: float  # the member's odometer when it last moved STALL_M
    t: float  # when that was


class ClaimBook:
    """`bounds`: ((xmin, ymin), (xmax, ymax)), the fleet's area (the navigation graph's bounds); a
    goal outside it is refused like a non-finite one."""

    def __init__(
        self,
        members: list[str],
        goal_separation_m: float,
        ttl_s: float,
        stall_s: float = 20.0,
        bounds=None,
    ):
        if goal_separation_m < 0 or ttl_s <= 0:
            raise ValueError("need goal_separation_m >= 0 and ttl_s > 0")
        self.bounds = None if bounds is None else tuple(tuple(map(float, b)) for b in bounds)
        self.members = list(members)
        self.separation_m = float(goal_separation_m)
        self.ttl_s = float(ttl_s)
        self.stall_s = float(stall_s)
        self.progress: dict[str, Progress] = {}
        self.claims: dict[str, Claim] = {}
        self.heard: dict[str, float] = {}  # when each member was last heard of
        self.granted = 0
        self.refused = 0
        self.released = 0
        self.expired = 0
        self.version = 0  # bumped on every change, for the service to publish

    def check_member(self, robot: str) -> None:
        if robot not in self.members:
            raise ValueError(f"{robot!r} is not a member of the fleet ({', '.join(self.members)})")

    def claim(self, robot: str, xy, t: float) -> tuple[bool, str | None]:
        """Claim `xy` for `robot`: (True, None) when granted, else (False, the member whose goal
        is too near). Granting replaces the member's earlier claim."""
        self.check_member(robot)
        x, y = (float(v) for v in xy)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"goal must be finite, got {xy!r}")
        if self.bounds is not None:
            (x0, y0), (x1, y1) = self.bounds
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                raise ValueError(f"goal {xy!r} is outside the fleet's area {self.bounds}")
        self.heard[robot] = t
        for other, c in sorted(self.claims.items()):
            if other == robot or self.stalled(other, t):
                continue
            if math.hypot(x - c.xy[0], y - c.xy[1]) < self.separation_m:
                self.refused += 1
                return False, other
        self.claims[robot] = Claim((x, y), t)
        self.granted += 1
        self.version += 1
        return True, None

    def release(self, robot: str, t: float) -> bool:
        self.check_member(robot)
        self.heard[robot] = t
        if self.claims.pop(robot, None) is None:
            return False
        self.released += 1
        self.version += 1
        return True

    def stalled(self, robot: str, t: float) -> bool:
        p = self.progress.get(robot)
        return p is not None and t - p.t > self.stall_s

    def confirm(self, robot: str, goal_xy, t: float, distance_m: float | None = None) -> None:
        """What a member's own state says (it goes to `goal_xy`, or to nothing; its odometer): a
        claim is kept alive by it, and ends when the member says it has no goal."""
        self.check_member(robot)
        self.heard[robot] = t
        if distance_m is not None:
            p = self.progress.get(robot)
            if p is None or distance_m - p.distance_m >= STALL_M or distance_m < p.distance_m:
                if p is not None and self.stalled(robot, t):
                    self.version += 1  # its claim holds the others back again
                self.progress[robot] = Progress(float(distance_m), t)
        c = self.claims.get(robot)
        if goal_xy is None:
            if c is not None:
                self.release(robot, t)
        elif c is not None and math.hypot(goal_xy[0] - c.xy[0], goal_xy[1] - c.xy[1]) < 1e-3:
            c.t = t

    def expire(self, t: float) -> list[str]:
        """Forget the claims of members not heard of for `ttl_s`."""
        gone = [r for r in self.claims if t - self.heard.get(r, -math.inf) > self.ttl_s]
        for r in gone:
            del self.claims[r]
            self.expired += 1
        if gone:
            self.version += 1
        return gone

    def snapshot(self, t: float | None = None) -> dict[str, list[float]]:
        """The claims that hold the others back at time `t` (every claim without `t`)."""
        return {
            r: [c.xy[0], c.xy[1]]
            for r, c in sorted(self.claims.items())
            if t is None or not self.stalled(r, t)
        }

    def stalled_members(self, t: float) -> list[str]:
        return sorted(r for r in self.claims if self.stalled(r, t))

    def stats(self) -> dict:
        return {
            "claims": self.snapshot(),
            "granted": self.granted,
            "refused": self.refused,
            "released": self.released,
            "expired": self.expired,
        }
