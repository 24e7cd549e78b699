"""The last check of every velocity command: will the robot's body come too close to what its
safety scan shows?

The explorer plans and steers on its map, placed by its pose. When the pose drifts (odometry
without loop closure: 0.4 to 0.6 m after five minutes at the experiments' drift) the map's
obstacles are no longer where the robot meets them, and a path that keeps the safety zone on the
map puts the chassis on a hedge. A field robot carries a sensor for this that needs neither map
nor pose: a safety scanner whose points are in the robot's own frame (Nav2's collision monitor
reads one; services/sim gives the simulated robot one, `[sim.safety_scan]`).

`Guard.check` follows a command (v, w) for `horizon_s` as a unicycle, in steps, and measures the
clearance between the footprint (rectangles in the base frame) and the scan's points at each
step (signed: a point inside the footprint counts by its depth). The command passes when that
clearance stays at least `margin_m` or never falls below the clearance the robot has now (it
drives away, or along, what is close). Otherwise the same arc is tried at 1/2, 1/4 and 1/10 of
the speed: the robot slows as it nears an obstacle and stops at the margin (Nav2's "approach"
model). When none passes it stops; the explorer's own checks then see no progress and back out
or give the goal up.

The scanner's low beams start outside the robot's body, so a scan alone is blind to a low
object beside the robot: each scan's points are kept for `memory_s`, placed in the frame of the
pose the explorer steers by (filtered: services/explorer/pose_filter.py), whose drift over a
second or two is small. Parameters: `[explorer.guard]` (`GuardConfig`).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from smana.common.config.explorer import GuardConfig

SCALES = (1.0, 0.5, 0.25, 0.1)  # the command's arc at these fractions of its speed
STEPS = 10  # clearance checked at this many points along the horizon (and now)
EPS_M = 1e-3  # "not closer than now", to the millimetre
CELL_M = 0.03  # a scan's points are thinned to one per cell of this side


def clearance(points: np.ndarray, poses: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """Per pose (K, 3: x, y, yaw), the signed distance from the footprint (rectangles R x 4:
    centre x, centre y, half x, half y in the base frame) to the nearest of `points` (N, 2):
    negative for a point inside, by its depth (so that going deeper reads as coming closer).
    inf when there are no points."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    if len(points) == 0:
        return np.full(len(poses), np.inf)
    d = points[None, :, :] - poses[:, None, :2]  # K, N, 2
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    lx = c * d[..., 0] + s * d[..., 1]
    ly = -s * d[..., 0] + c * d[..., 1]
    qx = np.abs(lx[..., None] - rects[:, 0]) - rects[:, 2]  # K, N, R: > 0 outside in x
    qy = np.abs(ly[..., None] - rects[:, 1]) - rects[:, 3]
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    inside = np.minimum(np.maximum(qx, qy), 0.0)  # minus the depth, 0 outside
    return (outside + inside).min(axis=(1, 2))


def cells(xy: np.ndarray) -> np.ndarray:
    """One point (K, 2) per occupied cell of CELL_M, at the cell's centre: the points' cells as
    one integer key each, made unique (a lexicographic unique of rows costs ten times more).
    Cells within 2**30 of the origin an axis (32,000 km at 3 cm)."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    ij = np.round(np.asarray(xy, float) / CELL_M).astype(np.int64) + 2**30
    keys = np.unique((ij[:, 0] << 31) | ij[:, 1])
    i, j = (keys >> 31) - 2**30, (keys & (2**31 - 1)) - 2**30
    return np.column_stack([i, j]).astype(float) * CELL_M


def rollout(x: float, y: float, yaw: float, v: float, w: float, horizon_s: float) -> np.ndarray:
    """Poses (STEPS + 1, 3) of a unicycle following (v, w) from (x, y, yaw), now included."""
    t = np.linspace(0.0, horizon_s, STEPS + 1)
    th = yaw + w * t
    if abs(w) < 1e-6:
        px = x + v * t * math.cos(yaw)
        py = y + v * t * math.sin(yaw)
    else:  # the exact arc
        px = x + v / w * (np.sin(th) - math.sin(yaw))
        py = y - v / w * (np.cos(th) - math.cos(yaw))
    return np.stack([px, py, th], axis=1)


class Guard:
    """The safety scan's recent points and the check of a command against them."""

    def __init__(self, config: GuardConfig | None = None):
        self.config = config or GuardConfig()
        self.rects = np.asarray(self.config.footprint, float).reshape(-1, 4)
        self._scans: collections.deque[tuple[float, np.ndarray]] = collections.deque()
        self.t_scan = -math.inf  # robot time of the newest scan
        self.scans = 0
        self.slowed = 0  # commands that went out slower
        self.stopped = 0  # commands that became a stop
        self.unguarded = 0  # commands that went out with no fresh scan to check them against
        self.min_clearance_m = math.inf  # the least clearance the robot had while moving
        # no point farther than this from the base frame's origin touches the footprint
        self._reach_m = float(np.max(np.hypot(*(np.abs(self.rects[:, :2]) + self.rects[:, 2:]).T)))

    # -- the scan ------------------------------------------------------------------------------

    def add(self, points_base: np.ndarray, pose: tuple[float, float, float], t: float) -> None:
        """A safety scan's points (N, 3, base frame), taken at robot time `t` where the robot
        steered by `pose`: those at the heights that count, within range, kept in the pose's
        frame."""
        cfg = self.config
        p = np.asarray(points_base, float).reshape(-1, 3)
        keep = (p[:, 2] >= cfg.z_min_m) & (p[:, 2] <= cfg.z_max_m)
        # past range_m by what a robot at 1 m/s closes in the horizon: a point kept now may be
        # within range of a later check
        keep &= np.hypot(p[:, 0], p[:, 1]) <= cfg.range_m + cfg.horizon_s * 1.0
        xy = cells(p[keep, :2])
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        world = np.column_stack([x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]])
        self._scans.append((t, world))
        self.t_scan = max(self.t_scan, t)
        self.scans += 1
        while self._scans and self._scans[0][0] < self.t_scan - cfg.memory_s:
            self._scans.popleft()

    def points_near(self, x: float, y: float, radius_m: float | None = None) -> np.ndarray:
        """The kept points (K, 2) within `radius_m` (default `range_m`) of (x, y), one per cell
        of CELL_M: a wall seen by fifteen scans is one wall."""
        if not self._scans:
            return np.zeros((0, 2))
        r = self.config.range_m if radius_m is None else min(radius_m, self.config.range_m)
        near = [w[np.hypot(w[:, 0] - x, w[:, 1] - y) <= r] for _, w in self._scans]
        return cells(np.concatenate(near))

    def fresh(self, t: float) -> bool:
        return t - self.t_scan <= self.config.stale_s

    # -- the check -----------------------------------------------------------------------------

    def check(
        self, v: float, w: float, pose: tuple[float, float, float] | None, t: float
    ) -> tuple[float, float]:
        """The command (v, w) as it may go out at robot time `t`: as it is, slower along the
        same arc, or (0, 0). Unchecked when the guard is off, the robot stands still, or no
        fresh scan is there (counted in `unguarded`)."""
        cfg = self.config
        if not cfg.enabled or (v == 0.0 and w == 0.0) or pose is None:
            return v, w
        if not self.fresh(t):
            self.unguarded += 1
            return v, w
        x, y, yaw = pose
        # only points the footprint can come within the margin of in the horizon count: with
        # none, the command passes whatever is farther
        reach = self._reach_m + abs(v) * cfg.horizon_s + cfg.margin_m + CELL_M
        pts = self.points_near(x, y, reach)
        if len(pts) == 0:
            return v, w
        now = float(clearance(pts, np.array([[x, y, yaw]]), self.rects)[0])
        self.min_clearance_m = min(self.min_clearance_m, now)
        for k, s in enumerate(SCALES):
            ahead = clearance(pts, rollout(x, y, yaw, v * s, w * s, cfg.horizon_s), self.rects)
            worst = float(ahead[1:].min())
            if worst >= cfg.margin_m or worst >= now - EPS_M:
                self.slowed += k > 0
                return v * s, w * s
        self.stopped += 1
        return 0.0, 0.0

    def summary(self) -> dict:
        """What the guard did, for the explorer's state and its run record."""
        return {
            "scans": self.scans,
            "slowed": self.slowed,
            "stopped": self.stopped,
            "unguarded": self.unguarded,
            "min_clearance_m": None
            if math.isinf(self.min_clearance_m)
            else round(self.min_clearance_m, 3),
        }
