"""The slow, obvious reference for the A* kernel: the same 8-connected graph with the same edge
costs, built as a scipy sparse matrix and solved with `scipy.sparse.csgraph.dijkstra`.

Used by the tests (A* cost must equal this optimum) and by `smana bench planner`. The enter
costs' reference (the risk pricing and the clearance node by node) is the tests' own:
tests/support/enter_cost_reference.py.
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
