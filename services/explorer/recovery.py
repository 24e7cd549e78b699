"""What the explorer does when no view is left but its map may be wrong (`Explorer.plan` calls
these): go and look again before giving up, and tell a robot its own map closed in from one that
has seen all it can reach. Part of `exploration.Explorer`; no wiring.

A perception-driven map can close a robot in: wrong labels confirmed into obstacles, safety zones
round them, ground seen beyond them that no path reaches. Nav2's navigator answers a planner that
fails with recovery behaviours (clear the costmap, spin, back up, wait) before it aborts; here the
map clears itself when the camera sees the same ground again (navgraph's evidence), so recovery
means looking again: drive to the reachable node nearest the free ground seen beyond the blockage,
face it (the camera looks ahead and down), and plan again. Each look goes to a new place
(`recovery_spacing_m` from the earlier ones), at most `recoveries` times while no view is found.

It looks again when the robot seems closed in: the free ground it has seen but cannot reach is
larger than the ground it can reach (and at least `closed_in_min_m2`), or the part of it that
borders unknown ground (a frontier beyond the blockage: more to explore there) is at least a
quarter of what it can reach (and `closed_in_min_m2`). A robot that explored its part of the
world, where a few beds or pockets behind hedges stay out of reach, seen whole, ends as before
without a detour. Closed in still with its looks spent (the first test), the run ends
`closed_in`, which the run's report calls a failure.
"""

from __future__ import annotations

import math

import numpy as np

from smana.services.explorer import frontier as fr

# a frontier beyond the reach is worth a look when the free ground round it is at least this
# share of the ground within reach (and `closed_in_min_m2`)
BEYOND_SHARE = 0.25


class Recovering:
    """The part of `Explorer` that looks again. It uses the state `Explorer.__init__` sets
    (`config`, `grid`, `pose`, `_looked_at`, `n_recoveries`, ...) and `_set_goal`."""

    def _seen_beyond(self, free: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """Free nodes the robot cannot reach, in pieces of at least `closed_in_min_m2` / 4 (a
        pocket of a node or two inside a bed is no way on)."""
        from scipy import ndimage  # here, not at import: off the explorer's start

        others = free & ~reach
        if not others.any():
            return others
        comp, n = ndimage.label(others, structure=fr.EIGHT_CONNECTED)
        size = np.bincount(comp.ravel(), minlength=n + 1)
        cell_m2 = self.grid.resolution_m**2
        big = size * cell_m2 >= self.config.closed_in_min_m2 / 4
        big[0] = False
        return big[comp]

    def _closed_in(self, beyond: np.ndarray, reach: np.ndarray) -> bool:
        """More free ground seen `beyond` the reach (`_seen_beyond`) than within it."""
        beyond_m2 = float(beyond.sum()) * self.grid.resolution_m**2
        reach_m2 = float(reach.sum()) * self.grid.resolution_m**2
        return beyond_m2 >= self.config.closed_in_min_m2 and beyond_m2 > reach_m2

    def _unexplored_beyond(
        self, beyond: np.ndarray, unknown: np.ndarray, reach: np.ndarray
    ) -> bool:
        """Whether the pieces of free ground `beyond` the reach that border unknown ground (a
        frontier the robot cannot reach) add up to `closed_in_min_m2` and to `BEYOND_SHARE` of
        the reach: the inside of a hedge is unknown too, so a finished run's pockets behind
        hedges border unknown ground, but they are a small part of what it reaches."""
        from scipy import ndimage

        if not beyond.any():
            return False
        comp, n = ndimage.label(beyond, structure=fr.EIGHT_CONNECTED)
        near_unknown = ndimage.binary_dilation(unknown, structure=fr.EIGHT_CONNECTED)
        open_ids = np.unique(comp[beyond & near_unknown])
        cell_m2 = self.grid.resolution_m**2
        area = float(np.isin(comp, open_ids[open_ids > 0]).sum()) * cell_m2
        reach_m2 = float(reach.sum()) * cell_m2
        return area >= max(self.config.closed_in_min_m2, BEYOND_SHARE * reach_m2)

    def _maybe_look_again(self, beyond: np.ndarray, reach: np.ndarray, goal_cost) -> bool:
        """Drive to look again at what cuts a closed-in robot off from the free ground it has
        seen `beyond` its reach; False when there is no new place to look from or the looks are
        spent."""
        if self.n_recoveries >= self.config.recoveries or not reach.any():
            return False
        g = self.grid
        far = np.argwhere(beyond)
        near = np.argwhere(reach)
        far_xy, near_xy = g.centres(far), g.centres(near)
        from scipy.spatial import cKDTree

        # each reachable node's distance to the nearest free node beyond the blockage
        d, k = cKDTree(far_xy).query(near_xy)
        x, y, _ = self.pose
        spacing = self.config.recovery_spacing_m
        for i in np.argsort(d, kind="stable")[:50]:
            xy = near_xy[i]
            if any(math.hypot(*(xy - p)) < spacing for p in self._looked_at):
                continue
            toward = far_xy[k[i]] - xy
            yaw = math.atan2(toward[1], toward[0])
            reply = goal_cost(xy) if math.hypot(xy[0] - x, xy[1] - y) > 0.05 else (0.0, None)
            if reply is None:
                continue
            cost, path = reply
            self._looked_at.append(xy.copy())
            self.n_recoveries += 1
            choice = fr.ViewChoice(near[i], xy, yaw, 0.0, float(cost), 0.0, path, 0, 0)
            self._set_goal(choice, count=False, tolerance_m=0.15)
            self._looking = True
            return True
        return False
