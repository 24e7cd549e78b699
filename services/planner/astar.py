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
# A node whose f lies beyond the heap's band waits in a bucket: one FAR_ROW in a linked list,
# (g, node, next row). The ring has _RING buckets of `width` in f; a farther f waits in the last
# one and is sorted on when that bucket's turn comes.
FAR_ROW = np.dtype([("g", np.float64), ("n", np.int32), ("next", np.int32)], align=True)
_RING = 1 << 12
# The bucket width in units of the cheapest straight step (res + min enter cost): the heap then
# holds the open nodes of a narrow band of f (measured, see docs/benchmarks.md).
BUCKET_STEPS = 1.0


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
    inv_width: float  # 1 / the f width of a bucket of the open set; 0: one heap, no buckets


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
    enter_cost,
    heights,
    start,
    goal,
    resolution_m,
    h_f,
    max_step,
    heuristic,
    min_enter,
    t0=None,
    bucket_steps=BUCKET_STEPS,
) -> AStarResult:
    """`astar` without the input checks, for a caller that built the arrays itself and knows
    their smallest finite enter cost (the Planner caches both per graph version): C-contiguous
    arrays, enter costs float64, heights float64 or float32 (the grid's; a height difference is
    taken in float64 either way, so the cost is the same to the bit), in-window cells,
    `max_step` a float (inf for none). `bucket_steps` is the open set's bucket width in
    cheapest straight steps (0: one heap, as before the buckets; for tests and benchmarks)."""
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
        _inv_width(resolution_m, min_enter if octile else 0.0, bucket_steps),
    )
    cost, path, expanded = _astar_kernel(st, query, start[0] * ny + start[1])
    cells = np.stack([path // ny, path % ny], axis=1)
    return AStarResult(float(cost), cells, int(expanded), (time.perf_counter() - t0) * 1e3)


def _inv_width(resolution_m: float, min_enter: float, bucket_steps: float) -> float:
    """1 / the bucket width in f: `bucket_steps` cheapest straight steps (0: no buckets)."""
    step = resolution_m + min_enter
    if not bucket_steps > 0 or not step > 0 or not math.isfinite(step):
        return 0.0
    return 1.0 / (bucket_steps * step)


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
_NOT_IN_HEAP, _CLOSED, _IN_FAR = -1, -2, -3  # st[node].slot when it has no heap row
_DX = (-1, -1, -1, 0, 0, 1, 1, 1)
_DY = (-1, 0, 1, -1, 1, -1, 0, 1)


@numba.njit(cache=True, inline="always")
def _h(ax, ay, res, mode, min_enter, diag_extra):
    """The heuristic for a node `ax`, `ay` cells from the goal (one copy, so that a bucketed
    node's f is recomputed to the bit when it moves into the heap)."""
    if mode == 0:
        return res * math.sqrt(ax * ax + ay * ay)
    lo = min(ax, ay)
    hi = max(ax, ay)
    return res * (hi + diag_extra * lo) + min_enter * hi


@numba.njit(cache=True, inline="always")
def _band(f, base, inv_width):
    """The bucket of f: monotone in f (floor of monotone float operations), so a node of a
    lower bucket never has a larger f than one of a higher bucket. inv_width 0: all in bucket 0,
    a plain heap."""
    return np.int64(math.floor((f - base) * inv_width))


@numba.njit(cache=True)
def _search(query, st, heap, stack, far, heads, counts, progress):
    """The A* loop proper, for `query` from where `progress` left it. It returns (status,
    progress) when the goal is popped, the open set is empty, or an array has no room for one
    more step; the caller then grows it and calls again. Keeping the growth out of here
    matters: an array variable reassigned inside the hot loop costs numba reference counting on
    every iteration (2.4x slower when measured).

    The open set has three tiers, taken in this order:

    - `stack` (rows (g, node)): a node not in the heap whose new f <= f_min, the f of the last
      node taken from the heap. Its nodes are still minimal, so the search stays exact, and
      LIFO takes the deepest first as the heap's tie rule does; on open ground most nodes never
      go further. A stack entry is stale when its node was improved or closed since.
    - the heap, a binary heap with decrease-key (`st[node].slot` is its row: an improved node
      moves up in place instead of leaving a stale copy; 1.3x faster than stale copies on the
      cluttered graphs, measured), holding the open nodes whose f lies in the buckets up to the
      current one, `cur`;
    - the buckets beyond `cur` (`_band`), linked lists of FAR_ROW rows in a ring: pushing there
      is O(1), and a node that is improved again before its bucket's turn costs no heap work
      (its old row turns stale: slot no longer _IN_FAR or g changed). When the stack and the
      heap are empty the next non-empty bucket's live rows move into the heap.

    Every f in a later bucket is larger than every f in the heap (`_band` is monotone), so the
    heap's root is the open set's minimum in (f, h) as with one heap: the nodes expanded are
    the same, only the order of exact (f, h) ties may differ. `slot` also marks closed nodes
    (_CLOSED), so no separate closed flags. The query's fields are read into locals once."""
    enter, heights, nx, ny, goal, res, h_f, max_step, mode, min_enter, inv_width = query
    size, depth, f_min, expanded, cur, base, top, free, n_free, n_far, need = progress
    goal_x = goal // ny
    goal_y = goal - goal_x * ny
    diag = res * SQRT2
    diag_extra = SQRT2 - 1.0
    mask = _RING - 1
    # Without a height term or a step limit the heights need not be read at all.
    use_heights = h_f != 0.0 or max_step != np.inf
    cap = len(heap)
    stack_cap = stack.shape[0]
    far_cap = len(far)
    while True:
        if size + 8 > cap or depth + 8 > stack_cap or far_cap - top + n_free < 8:
            return _FULL, (size, depth, f_min, expanded, cur, base, top, free, n_free, n_far, 0)
        if depth > 0:
            depth -= 1
            gpop = stack[depth, 0]
            n = np.int64(stack[depth, 1])
            # Stale when the node was closed or improved since (then on the stack again, or
            # with a heap row or a bucket row).
            if st[n].slot != _NOT_IN_HEAP or gpop != st[n].g:
                continue
            st[n].slot = _CLOSED
        elif size > 0:
            f_min = heap[0].f
            n = np.int64(heap[0].n)
            gpop = st[n].g
            size = _pop(heap, st, size)  # closes n; a heap row is never stale
        else:
            if n_far == 0:
                break
            b = cur + 1
            while heads[b & mask] < 0:
                b += 1
            if counts[b & mask] + 8 > cap:  # the caller grows the heap for this bucket first
                out = (size, depth, f_min, expanded, cur, base, top, free, n_free, n_far)
                return _FULL, (*out, counts[b & mask] + 8)
            cur = b
            e = heads[b & mask]
            heads[b & mask] = -1
            counts[b & mask] = 0
            while e >= 0:
                nxt = far[e].next
                n = far[e].n
                g = far[e].g
                n_far -= 1
                if st[n].slot == _IN_FAR and st[n].g == g:
                    mx = n // ny
                    my = n - mx * ny
                    h = _h(abs(mx - goal_x), abs(my - goal_y), res, mode, min_enter, diag_extra)
                    f = g + h
                    k = _band(f, base, inv_width)
                    if k <= cur:
                        _sift_up(heap, st, size, f, np.float32(h), n)
                        size += 1
                        e_free = True
                    else:  # beyond the ring when it was pushed: on to its own bucket
                        k = min(k, cur + _RING - 1)
                        far[e].next = heads[k & mask]
                        heads[k & mask] = e
                        counts[k & mask] += 1
                        n_far += 1
                        e_free = False
                else:
                    e_free = True  # stale
                if e_free:
                    far[e].next = free
                    free = e
                    n_free += 1
                e = nxt
            continue
        if n == goal:
            return _FOUND, (size, depth, f_min, expanded, cur, base, top, free, n_free, n_far, 0)
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
                h = _h(abs(mx - goal_x), abs(my - goal_y), res, mode, min_enter, diag_extra)
                f = ng + h
                if sm >= 0:
                    _sift_up(heap, st, sm, f, np.float32(h), m)  # decrease-key
                elif f <= f_min:
                    st[m].slot = _NOT_IN_HEAP  # a bucket row it had turns stale
                    stack[depth, 0] = ng
                    stack[depth, 1] = m
                    depth += 1
                else:
                    b = _band(f, base, inv_width)
                    if b <= cur:
                        _sift_up(heap, st, size, f, np.float32(h), m)
                        size += 1
                    else:
                        b = min(b, cur + _RING - 1)
                        if free >= 0:
                            e = free
                            free = far[e].next
                            n_free -= 1
                        else:
                            e = top
                            top += 1
                        far[e].g = ng
                        far[e].n = m
                        far[e].next = heads[b & mask]
                        heads[b & mask] = e
                        counts[b & mask] += 1
                        n_far += 1
                        st[m].slot = _IN_FAR
    return _EXHAUSTED, (size, depth, f_min, expanded, cur, base, top, free, n_free, n_far, 0)


@numba.njit(cache=True)
def _grown(a, used):
    b = np.empty((2 * a.shape[0], a.shape[1]), a.dtype)
    b[:used] = a[:used]
    return b


@numba.njit(cache=True)
def _astar_kernel(st, query, start):
    """`st` is a NODE_STATE work array of nx * ny rows, set here (parent needs none)."""
    goal = query.goal
    ny = query.ny
    for i in range(len(st)):
        st[i].g = np.inf
        st[i].slot = _NOT_IN_HEAP
    heap = np.empty(1 << 14, HEAP_ROW)
    stack = np.empty((1 << 12, 2), np.float64)
    far = np.empty(1 << 14, FAR_ROW)
    heads = np.full(_RING, -1, np.int32)
    counts = np.zeros(_RING, np.int64)
    st[start].g = 0.0
    _sift_up(heap, st, 0, 0.0, np.float32(0.0), start)
    # Buckets count from the start's f, the smallest f of the search (the heuristic is
    # consistent), so that the first ones are used.
    ax = abs(start // ny - goal // ny)
    ay = abs(start % ny - goal % ny)
    base = _h(ax, ay, query.res, query.mode, query.min_enter, SQRT2 - 1.0)
    # heap size, stack depth, f_min, nodes expanded, current bucket, bucket origin, far rows
    # used, free far row, free rows, far rows in buckets, heap rows needed
    progress = (1, 0, 0.0, 0, np.int64(0), base, 0, -1, 0, 0, 0)
    while True:
        state, progress = _search(query, st, heap, stack, far, heads, counts, progress)
        size, depth, _, expanded, _, _, top, _, n_free, _, need = progress
        if state != _FULL:
            break
        if size + 8 > len(heap) or need > len(heap):
            heap2 = np.empty(max(2 * len(heap), 2 * need), HEAP_ROW)
            heap2[:size] = heap[:size]
            heap = heap2
        if depth + 8 > stack.shape[0]:
            stack = _grown(stack, depth)
        if len(far) - top + n_free < 8:
            far2 = np.empty(2 * len(far), FAR_ROW)
            far2[:top] = far[:top]
            far = far2
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
