"""How the explorer chooses its next view (`Explorer.plan` calls these): where paths may start,
the paper's next-best view or Yamauchi's nearest frontier, the goals it forgets for a while, and
what the current goal is still worth. Part of `exploration.Explorer`; no wiring.
"""

from __future__ import annotations

import math

import numpy as np

from smana.services.explorer import frontier as fr
from smana.services.explorer.driving import OBSTACLE_ONLY


class Choosing:
    """The part of `Explorer` that chooses views. It uses the state `Explorer.__init__` sets
    (`config`, `grid`, `goal`, `follower`, `team`, `score`, `_fov`, `_blacklist`, ...)."""

    def _keeps(self, keep_goal: bool, choice: fr.ViewChoice) -> bool:
        """A periodic plan keeps the current goal unless the new view is better by the margin."""
        return keep_goal and choice.score <= self._current_score() + self.config.switch_margin_share

    def _next_best_view(self, cells, unknown, opaque, xy, goal_cost):
        """The paper's choice among candidate cells: (cells kept, their best gains, the choice or
        None). In a fleet, views near another member's goal are left out and the unknown area
        around it counts for nothing (that member will see it)."""
        g = self.grid
        gain_unknown = unknown
        if self.team is not None:
            if len(cells):
                cells = cells[self.team.apart(g.centres(cells))]
            claimed = self.team.claimed(g.origin_xy, g.resolution_m, unknown.shape)
            gain_unknown = unknown & ~claimed
        gains, yaws = fr.view_gains(gain_unknown, opaque, cells, self._fov)
        best_gain = gains.max(axis=1) if len(cells) else np.zeros(0)
        choice = fr.select_view(
            g.centres(cells) if len(cells) else np.zeros((0, 2)),
            cells,
            best_gain,
            yaws,
            np.asarray(xy, float),
            goal_cost,
            self.score,
            self.config.min_gain_m2,
            self.cost_per_m_lower_bound,
            max_queries=self.config.max_queries,
        )
        return cells, best_gain, choice

    def _starts(self, free: np.ndarray, xy) -> tuple[np.ndarray, np.ndarray, dict]:
        """Where paths may start: for every component of free nodes that comes within
        `start_search_radius_m` of the robot, its node nearest the robot (the robot's own node when
        free). Returns (component labels, reachable mask, {component id: start node}).

        The nodes right around the robot are often unseen (the camera does not look straight
        down) or became safety zone, so the robot's own node can be cut off from all it has seen;
        it then drives a short straight hop to the start node first. Paths never cross unknown
        space beyond that hop: an unseen obstacle may stand beside the robot, out of view. A hop
        must not cross an obstacle node: a robot caught in a safety zone that just appeared
        around it backs out on the open side, not through the obstacle to a nearer node."""
        g = self.grid
        # joined as the planner joins nodes: across height steps up to its max_step_m
        comp = fr.step_components(free, g.heights, self.max_step_m)
        cell = np.array(g.cell_of(xy))
        r = int(math.ceil(self.config.start_search_radius_m / g.resolution_m))
        lo = np.maximum(cell - r, 0)
        hi = np.minimum(cell + r + 1, g.shape)
        starts: dict[int, tuple[int, int]] = {}
        if (hi > lo).all():
            sub = np.argwhere(free[lo[0] : hi[0], lo[1] : hi[1]]) + lo
            d = np.hypot(*(sub - cell).T) if len(sub) else np.zeros(0)
            p = np.asarray(xy, float)[:2]
            for k in np.argsort(d, kind="stable"):
                if d[k] > r:
                    break
                cid = int(comp[sub[k, 0], sub[k, 1]])
                if cid in starts:
                    continue
                if d[k] > 0 and not self._segment_clear(p, g.centres(sub[k]), OBSTACLE_ONLY):
                    continue
                starts[cid] = (int(sub[k, 0]), int(sub[k, 1]))
        reach = np.isin(comp, list(starts)) if starts else np.zeros(g.shape, bool)
        return comp, reach, starts

    def _goal_exhausted(self) -> bool:
        return self._goal_gain() < self.config.min_gain_m2

    def _goal_gain(self) -> float:
        g = self.grid
        cell = self.goal.choice.cell.reshape(1, 2)
        opaque = fr.opaque_mask(g.flags)
        gains, _ = fr.view_gains(
            fr.unknown_mask(g.flags),
            opaque if self.config.view.occlusion else None,
            cell,
            self._fov,
        )
        return float(gains.max()) if gains.size else 0.0

    def _current_score(self) -> float:
        # the cost left is the planned cost scaled by the share of the path still ahead
        total = max(self.goal.path_length_m, 1e-6)
        left = self.goal.choice.path_cost * self.follower.remaining_length_m() / total
        return float(self.score(self._goal_gain(), left))

    def _nearest_frontier(self, free, front, starts, xy, unknown, opaque, goal_cost):
        """Yamauchi's choice: the frontier node nearest by travel (metres over free nodes from the
        robot, class costs ignored) among those whose view is worth a look (`min_gain_m2`, the
        same test the next-best view applies, so both strategies stop on the same criterion),
        facing its most unknown heading. Returns (cells whose gain was computed, their gains,
        the choice or None). Gains are computed in growing batches in distance order: the
        nearest worthy node is usually among the first few."""
        g = self.grid
        cells = self._drop_blacklisted(front)
        src = np.array(list(starts.values()), np.int64).reshape(-1, 2)
        hop = np.hypot(*(g.centres(src) - np.asarray(xy, float)).T) if len(src) else np.zeros(0)
        dist = fr.travel_distance_m(free, src, hop, g.resolution_m)
        d = dist[cells[:, 0], cells[:, 1]] if len(cells) else np.zeros(0)
        order = np.argsort(d, kind="stable")
        order = order[np.isfinite(d[order])]
        seen_cells, seen_gains = [], []
        n_queries, lo, batch = 0, 0, 16
        while lo < len(order) and n_queries < self.config.max_queries:
            idx = order[lo : lo + batch]
            gains, yaws = fr.view_gains(unknown, opaque, cells[idx], self._fov)
            best = gains.max(axis=1)
            seen_cells.append(cells[idx])
            seen_gains.append(best)
            for k in np.flatnonzero(best >= self.config.min_gain_m2):
                if n_queries >= self.config.max_queries:
                    break
                n_queries += 1
                goal_xy = g.centres(cells[idx[k]])
                reply = goal_cost(goal_xy)
                if reply is None or not math.isfinite(reply[0]):
                    continue
                choice = fr.ViewChoice(
                    cells[idx[k]].copy(),
                    goal_xy,
                    float(yaws[k]),
                    float(best[k]),
                    float(reply[0]),
                    -float(d[idx[k]]),  # nearer is better
                    reply[1],
                    n_queries,
                    len(order),
                )
                return np.concatenate(seen_cells), np.concatenate(seen_gains), choice
            lo += batch
            batch *= 2
        if not seen_cells:
            return np.zeros((0, 2), np.int64), np.zeros(0), None
        return np.concatenate(seen_cells), np.concatenate(seen_gains), None

    def _forget(self, xy, seconds: float | None = None) -> None:
        until = self.t_now + (self.config.blacklist_s if seconds is None else seconds)
        self._blacklist.append((np.asarray(xy, float).copy(), until))

    def _drop_blacklisted(self, cells: np.ndarray) -> np.ndarray:
        self._blacklist = [(c, until) for c, until in self._blacklist if until > self.t_now]
        if not self._blacklist or len(cells) == 0:
            return cells
        xy = self.grid.centres(cells)
        keep = np.ones(len(cells), bool)
        for c, _ in self._blacklist:
            keep &= np.hypot(*(xy - c).T) > self.config.blacklist_radius_m
        return cells[keep]
