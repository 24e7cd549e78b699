"""The explorer's numba kernels, behind frontier.py's checked functions (`view_gains`,
`travel_distance_m`), which import this module on first use: numba stays out of the explorer
service's imports until its kernels are loaded, after it is live."""

from __future__ import annotations

import heapq
import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def visible_unknown_kernel(
    unknown: np.ndarray,
    opaque: np.ndarray,
    cand: np.ndarray,
    offsets: np.ndarray,
    occlusion: bool,
    samples_per_cell: int,
) -> np.ndarray:
    """vis[c, o] = 1 when node cand[c] + offsets[o] is inside the grid, unknown, and (with
    occlusion) the straight segment between the two node centres crosses no opaque node."""
    nx, ny = unknown.shape
    n_c, n_o = cand.shape[0], offsets.shape[0]
    vis = np.zeros((n_c, n_o), np.uint8)
    for c in range(n_c):
        cx, cy = cand[c, 0], cand[c, 1]
        for o in range(n_o):
            tx, ty = cx + offsets[o, 0], cy + offsets[o, 1]
            if tx < 0 or ty < 0 or tx >= nx or ty >= ny or not unknown[tx, ty]:
                continue
            if occlusion:
                length = math.sqrt(float(offsets[o, 0] ** 2 + offsets[o, 1] ** 2))
                n = int(math.ceil(length * samples_per_cell))
                blocked = False
                for s in range(1, n):
                    t = s / n
                    # node (i, j) spans [i - 0.5, i + 0.5) in node units around its centre
                    sx = int(math.floor(cx + t * offsets[o, 0] + 0.5))
                    sy = int(math.floor(cy + t * offsets[o, 1] + 0.5))
                    if (sx != tx or sy != ty) and opaque[sx, sy]:
                        blocked = True
                        break
                if blocked:
                    continue
            vis[c, o] = 1
    return vis


@numba.njit(cache=True, nogil=True)
def travel_distance_kernel(
    free: np.ndarray, src: np.ndarray, src_d: np.ndarray, resolution_m: float
) -> np.ndarray:
    """Multi-source Dijkstra over `free` nodes, 8-connected, steps res and res * sqrt 2."""
    nx, ny = free.shape
    dist = np.full((nx, ny), np.inf)
    diag = resolution_m * math.sqrt(2.0)
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for k in range(src.shape[0]):
        i, j = src[k, 0], src[k, 1]
        if src_d[k] < dist[i, j]:
            dist[i, j] = src_d[k]
            heapq.heappush(heap, (src_d[k], np.int64(i * ny + j)))
    while len(heap) > 0:
        d, n = heapq.heappop(heap)
        i, j = n // ny, n % ny
        if d > dist[i, j]:
            continue  # a stale entry: the node was settled through a shorter way
        for a in range(-1, 2):
            for b in range(-1, 2):
                if a == 0 and b == 0:
                    continue
                p, q = i + a, j + b
                if p < 0 or q < 0 or p >= nx or q >= ny or not free[p, q]:
                    continue
                nd = d + (diag if a != 0 and b != 0 else resolution_m)
                if nd < dist[p, q]:
                    dist[p, q] = nd
                    heapq.heappush(heap, (nd, np.int64(p * ny + q)))
    return dist


@numba.njit(cache=True, nogil=True)
def step_components_kernel(free, heights, max_step, labels):
    """Label the components of `free` (8-connected) whose neighbours differ in height by at most
    `max_step` (a NaN height joins any neighbour): 1, 2, ... in order of first node (row-major),
    0 off `free`. Returns the number of components."""
    nx, ny = free.shape
    stack = np.empty(nx * ny, np.int64)
    n = 0
    for i0 in range(nx):
        for j0 in range(ny):
            if not free[i0, j0] or labels[i0, j0] != 0:
                continue
            n += 1
            labels[i0, j0] = n
            top = 0
            stack[top] = i0 * ny + j0
            top += 1
            while top > 0:
                top -= 1
                k = stack[top]
                i = k // ny
                j = k - i * ny
                h = heights[i, j]
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        a = i + di
                        b = j + dj
                        if (di == 0 and dj == 0) or a < 0 or b < 0 or a >= nx or b >= ny:
                            continue
                        if not free[a, b] or labels[a, b] != 0:
                            continue
                        # the planner's test (float32 step, float64 limit); False with a NaN
                        if abs(heights[a, b] - h) > max_step:
                            continue
                        labels[a, b] = n
                        stack[top] = a * ny + b
                        top += 1
    return n
