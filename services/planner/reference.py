"""The slow, obvious reference for the A* kernel: the same 8-connected graph with the same edge
costs, built as a scipy sparse matrix and solved with `scipy.sparse.csgraph.dijkstra`.

Used by the tests (A* cost must equal this optimum) and by `smana bench planner`. Beside it, the
enter costs of the risk modes node by node in plain Python (`risk_enter_costs`), the reference of
the planner's risk kernels.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

OFFSETS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def build_graph(enter_cost, heights, resolution_m, h_f, max_step_m=None) -> sparse.csr_matrix:
    """Directed edges p -> n for every pair of 8-neighbours where n can be entered and the height
    step is allowed, weighted d + h_f * |dh| + enter_cost[n] (paper eq. 1)."""
    enter_cost = np.asarray(enter_cost, np.float64)
    heights = np.asarray(heights, np.float64)
    nx, ny = enter_cost.shape
    idx = np.arange(nx * ny).reshape(nx, ny)
    step = np.inf if max_step_m is None else max_step_m
    rows, cols, weights = [], [], []
    for dx, dy in OFFSETS:
        src = (slice(max(0, -dx), nx - max(0, dx)), slice(max(0, -dy), ny - max(0, dy)))
        dst = (slice(max(0, dx), nx + min(0, dx)), slice(max(0, dy), ny + min(0, dy)))
        dh = np.abs(heights[dst] - heights[src])
        unknown = np.isnan(dh)
        dh = np.where(unknown, 0.0, dh)
        ok = np.isfinite(enter_cost[dst]) & (unknown | (dh <= step))
        w = resolution_m * math.hypot(dx, dy) + h_f * dh + enter_cost[dst]
        rows.append(idx[src][ok])
        cols.append(idx[dst][ok])
        weights.append(w[ok])
    return sparse.csr_matrix(
        (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
        shape=(nx * ny, nx * ny),
    )


def dijkstra_cost(
    enter_cost, heights, start, goal, resolution_m, h_f, max_step_m=None, graph=None
) -> float:
    """Optimal cost from start to goal (cells), +inf if unreachable."""
    nx, ny = np.asarray(enter_cost).shape
    if graph is None:
        graph = build_graph(enter_cost, heights, resolution_m, h_f, max_step_m)
    dist = csgraph.dijkstra(graph, directed=True, indices=start[0] * ny + start[1])
    return float(dist[goal[0] * ny + goal[1]])


def cvar(atoms, alpha) -> float:
    """CVaR at level alpha of a discrete cost distribution [(cost, probability), ...] summing to
    1: the mean cost of the worst alpha of the probability mass."""
    left, total = alpha, 0.0
    for cost, prob in sorted(atoms, key=lambda a: -a[0]):
        take = min(prob, left)
        if take > 0:
            total += take * cost
            left -= take
    return total / alpha


def risk_enter_costs(
    labels, flags, alt, p_label, p_alt, classes, config, allow_unknown=False, resolution_m=0.2
):
    """Enter cost of every node of dense windows (labels, flags and the risk layers) under
    `config` (a PlannerConfig), one node at a time: the definitions of docs/risk.md as written,
    plus the clearance cost (`add_clearance`) for nodes of `resolution_m`."""
    from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE

    t_f = config.t_f
    out = np.full(np.shape(labels), np.inf)
    for (i, j), lab in np.ndenumerate(labels):
        f = int(flags[i, j])
        if f & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE):
            continue
        if f & FLAG_DOUBTFUL:  # an unconfirmed obstacle class: dear, whatever the risk mode
            out[i, j] = t_f * config.doubtful_cost
            continue
        if not f & FLAG_KNOWN:
            out[i, j] = config.unknown_cost * t_f if allow_unknown else np.inf
            continue
        lab = int(lab)
        T = classes.cost_lut[lab] if lab < classes.size else np.inf
        if lab == 0 and allow_unknown:
            T = config.unknown_cost
        if not np.isfinite(T):
            continue  # a label that cannot be entered: closed in every mode
        if config.risk == "label":
            out[i, j] = t_f * T
            continue
        dist = {lab: int(p_label[i, j]) / 255}
        a = int(alt[i, j])
        if 0 < a < classes.size and int(p_label[i, j]) < 255:
            dist[a] = dist.get(a, 0.0) + min(int(p_alt[i, j]), 255 - int(p_label[i, j])) / 255
        other = 1.0 - sum(dist.values())
        cost = {lab: T}
        p_forbidden = 0.0
        for c in dist:
            if c != lab:
                cost[c] = classes.cost_lut[c]
                if not np.isfinite(cost[c]):
                    p_forbidden += dist[c]
                    cost[c] = config.risk_forbidden_cost
        atoms = [(t_f * cost[c], dist[c]) for c in dist] + [(t_f * config.unknown_cost, other)]
        expected = sum(c * p for c, p in atoms)
        if config.risk == "cvar":
            out[i, j] = cvar(atoms, config.risk_alpha)
        elif config.risk == "chance":
            p_forbidden += other * config.risk_other_forbidden
            out[i, j] = np.inf if p_forbidden > config.max_risk else expected
        else:
            out[i, j] = expected
    return add_clearance(out, flags, config, resolution_m)


def add_clearance(enter, flags, config, resolution_m):
    """The clearance cost added to finite enter costs, node by node: t_f * clearance_cost at a
    blocked node's side, falling linearly to 0 at (ring + 1) nodes from the nearest one (ring =
    clearance_m in nodes, rounded)."""
    from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE

    ring = int(round(config.clearance_m / resolution_m))
    if ring <= 0 or config.clearance_cost == 0:
        return enter
    out = np.array(enter, float)
    blocked = np.argwhere((np.asarray(flags) & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0)
    for (i, j), c in np.ndenumerate(out):
        if not np.isfinite(c) or len(blocked) == 0:
            continue
        near = np.abs(blocked - (i, j)).max(axis=1) <= ring  # within the ring's square
        if near.any():
            d = float(np.hypot(*(blocked[near] - (i, j)).T).min())
            if d < ring + 1:
                out[i, j] = c + config.t_f * config.clearance_cost * (ring + 1 - d) / ring
    return out
