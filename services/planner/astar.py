"""Weighted A* on a dense 8-connected 2.5D grid window (paper 3.3.2, eq. 1 and 2). No zenoh here.

Transition cost from node p to its neighbour n (paper eq. 1):

    c(p -> n) = d(p, n) + h_f * |h(n) - h(p)| + t_f * T(l(n))

with d the planar distance between node centres (resolution or resolution * sqrt 2), h the node
heights and T the traversability cost of n's label. The caller folds `t_f * T(l(n))` into one
per-node `enter_cost` array (+inf where n may not be entered: obstacle, safety zone, unknown). An
edge whose height step exceeds `max_step_m` is not traversable. Where a height is unknown (NaN)
the height term and the step check are skipped.

Eq. 2 as printed folds the heuristic into the accumulated cost; this is the correct A*: g(n) is the
sum of transition costs and the open set is ordered by f = g + h (ties: larger g first, which
favours nodes nearer the goal). Both heuristics below are admissible and consistent because every
transition costs at least its planar distance plus the cheapest enter cost, so the path found costs
exactly what Dijkstra finds on the same graph:

- "euclidean": h = d(n, goal), the paper's choice;
- "octile": h = octile distance + min(enter_cost) * Chebyshev steps, a tighter lower bound (every
  path needs at least that many steps and pays at least the cheapest enter cost on each), which
  expands far fewer nodes when traversability costs dominate distance.
"""

from __future__ import annotations

import math
import threading
import time
import typing
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from smana.common.config.planner import Heuristic

HEURISTICS = typing.get_args(Heuristic)
SQRT2 = math.sqrt(2.0)
# The search's state of a node, one 16-byte row: g, its heap row or _NOT_IN_HEAP / _CLOSED, its
# parent. One row, not three arrays, so a neighbour's state is one cache line (1.1x faster on
# the cluttered graphs, measured).
NODE_STATE = np.dtype([("g", np.float64), ("slot", np.int32), ("parent", np.int32)], align=True)
# A heap row: f, h (float32, ties only) and the node, 16 bytes: a sift moves one row, and four
# rows share a cache line (24-byte rows of float64 f, g, node were 10 % slower, measured). The
# popped node's g is read from its state: with decrease-key a heap row is never stale.
HEAP_ROW = np.dtype([("f", np.float64), ("h", np.float32), ("n", np.int32)], align=True)


class Query(NamedTuple):
    """One search as the kernels read it: the window's flat arrays, the goal, the cost terms."""

    enter: np.ndarray  # f8 (nx * ny,): enter cost of each node, +inf where blocked
    heights: np.ndarray  # f8 or f4 (nx * ny,): NaN where unknown
    nx: int
    ny: int
    goal: int  # flat node index
    res: float  # planar distance between neighbours along an axis, metres
    h_f: float
    max_step: float  # inf for none
    mode: int  # 0 euclidean, 1 octile
    min_enter: float  # the octile heuristic's cheapest enter cost (0.0 for euclidean)


@dataclass
class AStarResult:
    cost: float  # +inf when the goal is unreachable
    cells: np.ndarray  # (K, 2) int64 window cells from start to goal; empty when unreachable
    nodes_expanded: int
    time_ms: float

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.cost))


def astar(
    enter_cost: np.ndarray,
    heights: np.ndarray,
    start: tuple[int, int],
    goal: tuple[int, int],
    resolution_m: float,
    h_f: float = 0.1,
    max_step_m: float | None = None,
    heuristic: str = "euclidean",
) -> AStarResult:
    """Least-cost 8-connected path from `start` to `goal` (cells of the window arrays).

    `enter_cost[ix, iy]` >= 0 is the cost of entering a node (t_f * T(l)), +inf if it cannot be
    entered; `heights[ix, iy]` in metres, NaN where unknown. The start node is never entered, so its
    own enter cost does not matter (the robot is already there).
    """
    t0 = time.perf_counter()
    enter_cost = np.ascontiguousarray(enter_cost, np.float64)
    heights = np.ascontiguousarray(heights, np.float64)
    if enter_cost.ndim != 2 or heights.shape != enter_cost.shape:
        raise ValueError(
            f"enter_cost and heights must be 2-D arrays of one shape, got "
            f"{enter_cost.shape} and {heights.shape}"
        )
    nx, ny = enter_cost.shape
    if nx * ny == 0 or nx * ny >= 2**31 - 1:
        raise ValueError(f"window of {nx} x {ny} nodes is empty or too large")
    if np.isnan(enter_cost).any() or (enter_cost < 0).any():
        raise ValueError("enter_cost must be >= 0 (+inf for blocked nodes), without NaN")
    if not (np.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
    if not (np.isfinite(h_f) and h_f >= 0):
        raise ValueError(f"h_f must be >= 0, got {h_f}")
    step = np.inf if max_step_m is None else float(max_step_m)
    if not step > 0:
        raise ValueError(f"max_step_m must be > 0, got {max_step_m}")
    if heuristic not in HEURISTICS:
        raise ValueError(f"heuristic must be one of {HEURISTICS}, got {heuristic!r}")
    sx, sy = (int(v) for v in start)
    gx, gy = (int(v) for v in goal)
    for name, (x, y) in (("start", (sx, sy)), ("goal", (gx, gy))):
        if not (0 <= x < nx and 0 <= y < ny):
            raise ValueError(f"{name} cell ({x}, {y}) outside the {nx} x {ny} window")
    finite = enter_cost[np.isfinite(enter_cost)]
    min_enter = float(finite.min()) if finite.size else 0.0
    return search(
        enter_cost,
        heights,
        (sx, sy),
        (gx, gy),
        float(resolution_m),
        float(h_f),
        step,
        heuristic,
        min_enter,
        t0,
    )


def search(
    enter_cost, heights, start, goal, resolution_m, h_f, max_step, heuristic, min_enter, t0=None
) -> AStarResult:
    """`astar` without the input checks, for a caller that built the arrays itself and knows
    their smallest finite enter cost (the Planner caches both per graph version): C-contiguous
    arrays, enter costs float64, heights float64 or float32 (the grid's; a height difference is
    taken in float64 either way, so the cost is the same to the bit), in-window cells,
    `max_step` a float (inf for none)."""
    t0 = time.perf_counter() if t0 is None else t0
    nx, ny = enter_cost.shape
    st = _work_arrays(nx * ny)
    octile = heuristic == "octile"
    query = Query(
        enter_cost.reshape(-1),
        heights.reshape(-1),
        nx,
        ny,
        goal[0] * ny + goal[1],
        resolution_m,
        h_f,
        max_step,
        1 if octile else 0,
        min_enter if octile else 0.0,
    )
    cost, path, expanded = _astar_kernel(st, query, start[0] * ny + start[1])
    cells = np.stack([path // ny, path % ny], axis=1)
    return AStarResult(float(cost), cells, int(expanded), (time.perf_counter() - t0) * 1e3)


_work = threading.local()


def _work_arrays(n_nodes: int):
    """The kernel's per-node work array (NODE_STATE rows), kept between the queries of one
    thread and grown when a window is larger: fresh arrays cost 10 ms of page faults per query
    at 1000 x 1000 (measured), a quarter of a search; a reused one costs a fill."""
    arrays = getattr(_work, "arrays", None)
    if arrays is None or len(arrays) < n_nodes:
        arrays = np.empty(n_nodes, NODE_STATE)
        _work.arrays = arrays
    return arrays[:n_nodes]


def reserve(n_nodes: int) -> None:
    """Grow this thread's work array to `n_nodes` and touch its pages now, so that a search of
    a window that size pays no page faults (the Planner calls it when it builds a window ahead
    of the queries)."""
    if n_nodes <= 0:
        return
    arrays = getattr(_work, "arrays", None)
    if arrays is not None and len(arrays) >= n_nodes:
        return
    _work_arrays(n_nodes)["g"] = np.inf  # np.empty maps the pages; a write faults them in


@numba.njit(cache=True, inline="always")
def _before(fa, ha, fb, hb):
    """Heap order: smaller f first; on equal f the smaller h (the larger g, nearer the goal),
    which matters with a tight heuristic, where every node of an optimal path has the same f.
    Bitwise, not `or` / `and`: the branch-free form is 25 % faster on graphs full of equal f
    (measured). h is float32 in the heap: it only breaks ties, f decides exactly."""
    return (fa < fb) | ((fa == fb) & (ha < hb))


@numba.njit(cache=True, inline="always")
def _sift_up(heap, st, i, f, h, n):
    """Place (f, h, n) at heap row i and move it up, keeping `st[node].slot` = its row. Inlined: a
    call that returned the heap would pay numba's reference counting on every push."""
    while i > 0:
        p = (i - 1) >> 1
        if _before(f, h, heap[p].f, heap[p].h):
            heap[i] = heap[p]
            st[heap[i].n].slot = i
            i = p
        else:
            break
    heap[i].f = f
    heap[i].h = h
    heap[i].n = n
    st[n].slot = i


@numba.njit(cache=True, inline="always")
def _pop(heap, st, size):
    """Remove the root, which the caller read before and now closes; returns the new size."""
    st[heap[0].n].slot = _CLOSED
    size -= 1
    if size == 0:
        return 0
    lf = heap[size].f
    lh = heap[size].h
    ln = heap[size].n
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and _before(heap[c + 1].f, heap[c + 1].h, heap[c].f, heap[c].h):
            c += 1
        if _before(heap[c].f, heap[c].h, lf, lh):
            heap[i] = heap[c]
            st[heap[i].n].slot = i
            i = c
        else:
            break
    heap[i].f = lf
    heap[i].h = lh
    heap[i].n = ln
    st[ln].slot = i
    return size


_FOUND, _EXHAUSTED, _FULL = 0, 1, 2
_NOT_IN_HEAP, _CLOSED = -1, -2  # st[node].slot when it has no heap row
_DX = (-1, -1, -1, 0, 0, 1, 1, 1)
_DY = (-1, 0, 1, -1, 1, -1, 0, 1)


@numba.njit(cache=True)
def _search(query, st, heap, stack, progress):
    """The A* loop proper, for `query` from where `progress` (heap size, stack depth, f_min,
    nodes expanded) left it. It returns (status, progress) when the goal is popped, the open
    set is empty, or the heap or the stack has no room for one more expansion; the caller then
    grows them and calls again. Keeping the growth out of here matters: an array variable
    reassigned inside the hot loop costs numba reference counting on every iteration (2.4x
    slower when measured).

    The open set is two-tier. The heap holds each open node once: `st[node].slot` is its row, so
    an improved node moves up in place (decrease-key) instead of leaving a stale copy behind;
    on the cluttered benchmark graphs half the pops were such copies, and decrease-key made
    the search 1.3x faster (measured). `f_min` is the f of the last node taken from the heap;
    every heap entry has f >= f_min. A node not in the heap whose new f <= f_min goes on
    `stack` (rows (g, node)) instead, and the stack is emptied before the heap is touched
    again: its nodes are still minimal, so the search stays exact, and LIFO takes the deepest
    first as the heap's tie rule does. A stack entry is stale when its node was improved or
    closed since. `slot` also marks closed nodes (_CLOSED), so no separate closed flags.

    The query's fields are read into locals once, before the loop."""
    enter, heights, nx, ny, goal, res, h_f, max_step, mode, min_enter = query
    size, depth, f_min, expanded = progress
    goal_x = goal // ny
    goal_y = goal - goal_x * ny
    diag = res * SQRT2
    diag_extra = SQRT2 - 1.0
    # Without a height term or a step limit the heights need not be read at all.
    use_heights = h_f != 0.0 or max_step != np.inf
    cap = len(heap)
    stack_cap = stack.shape[0]
    while size > 0 or depth > 0:
        if size + 8 > cap or depth + 8 > stack_cap:
            return _FULL, (size, depth, f_min, expanded)
        if depth > 0:
            depth -= 1
            gpop = stack[depth, 0]
            n = np.int64(stack[depth, 1])
            # Stale when the node was closed or improved since (then on the stack again, or
            # with a heap row).
            if st[n].slot != _NOT_IN_HEAP or gpop != st[n].g:
                continue
            st[n].slot = _CLOSED
        else:
            f_min = heap[0].f
            n = np.int64(heap[0].n)
            gpop = st[n].g
            size = _pop(heap, st, size)  # closes n; a heap row is never stale
        if n == goal:
            return _FOUND, (size, depth, f_min, expanded)
        expanded += 1
        x = n // ny
        y = n - x * ny
        h_n = heights[n] if use_heights else 0.0
        for k in range(8):
            dx = _DX[k]
            dy = _DY[k]
            mx = x + dx
            my = y + dy
            if mx < 0 or my < 0 or mx >= nx or my >= ny:
                continue
            m = mx * ny + my
            sm = st[m].slot
            if sm == _CLOSED:
                continue  # cheaper than reading the costs: most neighbours inside are closed
            ec = enter[m]
            if ec == np.inf:
                continue
            ng = gpop + ec + (diag if dx != 0 and dy != 0 else res)
            if use_heights:
                dh = abs(heights[m] - h_n)
                if dh > max_step:
                    continue
                if dh == dh:  # NaN when a height is unknown: no height term, no step check
                    ng += h_f * dh
            if ng < st[m].g:
                st[m].g = ng
                st[m].parent = n
                ax = abs(mx - goal_x)
                ay = abs(my - goal_y)
                if mode == 0:
                    h = res * math.sqrt(ax * ax + ay * ay)
                else:
                    lo = min(ax, ay)
                    hi = max(ax, ay)
                    h = res * (hi + diag_extra * lo) + min_enter * hi
                f = ng + h
                if sm >= 0:
                    _sift_up(heap, st, sm, f, np.float32(h), m)  # decrease-key
                elif f <= f_min:
                    stack[depth, 0] = ng
                    stack[depth, 1] = m
                    depth += 1
                else:
                    _sift_up(heap, st, size, f, np.float32(h), m)
                    size += 1
    return _EXHAUSTED, (size, depth, f_min, expanded)


@numba.njit(cache=True)
def _grown(a, used):
    b = np.empty((2 * a.shape[0], a.shape[1]), a.dtype)
    b[:used] = a[:used]
    return b


@numba.njit(cache=True)
def _astar_kernel(st, query, start):
    """`st` is a NODE_STATE work array of nx * ny rows, set here (parent needs none)."""
    goal = query.goal
    for i in range(len(st)):
        st[i].g = np.inf
        st[i].slot = _NOT_IN_HEAP
    # A binary heap with decrease-key (see _search).
    heap = np.empty(1 << 14, HEAP_ROW)
    stack = np.empty((1 << 12, 2), np.float64)
    st[start].g = 0.0
    _sift_up(heap, st, 0, 0.0, np.float32(0.0), start)
    progress = (1, 0, 0.0, 0)  # heap size, stack depth, f_min, nodes expanded
    while True:
        state, progress = _search(query, st, heap, stack, progress)
        size, depth, _, expanded = progress
        if state != _FULL:
            break
        if size + 8 > len(heap):
            heap2 = np.empty(2 * len(heap), HEAP_ROW)
            heap2[:size] = heap[:size]
            heap = heap2
        if depth + 8 > stack.shape[0]:
            stack = _grown(stack, depth)
    if state != _FOUND:
        return np.inf, np.empty(0, np.int64), expanded
    k = 1
    n = goal
    while n != start:
        n = st[n].parent
        k += 1
    path = np.empty(k, np.int64)
    n = goal
    for i in range(k - 1, -1, -1):
        path[i] = n
        n = st[n].parent
    return st[goal].g, path, expanded


def path_costs(
    cells: np.ndarray,
    enter_cost: np.ndarray,
    heights: np.ndarray,
    resolution_m: float,
    h_f: float,
) -> tuple[float, float, float]:
    """(distance, height, traversability) parts of a path's cost, recomputed edge by edge."""
    cells = np.asarray(cells, np.int64)
    if len(cells) < 2:
        return 0.0, 0.0, 0.0
    step = np.diff(cells, axis=0)
    d = resolution_m * np.hypot(step[:, 0], step[:, 1])
    # Index, then convert: converting the whole window first (the planner's heights are float32)
    # made a window-sized float64 copy per query (8 MB at 1000 x 1000).
    h = np.asarray(heights)[cells[:, 0], cells[:, 1]].astype(np.float64)
    dh = np.abs(np.diff(h))
    dh = np.where(np.isnan(dh), 0.0, dh)
    trav = np.asarray(enter_cost)[cells[1:, 0], cells[1:, 1]].astype(np.float64)
    return float(d.sum()), float(h_f * dh.sum()), float(trav.sum())
