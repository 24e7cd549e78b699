"""Path queries on a navigation grid: checks, the dense search window, A*, and the answer (path in
world coordinates, its cost broken down, label shares) or a clear error. No zenoh here.

The planner searches a dense window: the bounding box of the grid's allocated tiles, grown to
include start and goal (and by one tile more when unknown nodes may be crossed, so that a path to
a frontier can go round the known area). The window's dense arrays are cached until the grid
changes. A node can be entered when it is known and traversable (cost t_f * T(l)); an obstacle or
safety-zone node never; an unknown node only when the request allows it, at `unknown_cost`.

When the graph has the risk layers (a node's second most likely class and the probabilities of
both), a known node's enter cost is taken from its class distribution as `risk` says (expected
cost, CVaR, or a chance constraint; docs/risk.md); a node whose label is certain, or a graph
without the layers, costs t_f * T(l) in every mode, exactly as without risk.

Its parameters are the [planner] config section as it is (`PlannerConfig`): the defaults of every
query, which a request may override one by one (h_f, t_f, max_step_m, unknown_cost, heuristic).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from smana.common.classes import ClassTable
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import (
    FLAG_KNOWN,
    FLAG_OBSTACLE,
    FLAG_SAFETY_ZONE,
    NavGrid,
)
from smana.common.risk import RISK_MODES, risk_model, risk_prices
from smana.services.planner.astar import HEURISTICS, path_costs, reserve, search
from smana.services.planner.enter_costs import (
    RiskPools,
    add_clearance,
    add_clearance_all,
    clearance_of,
    enter_cells,
    enter_cells_risk,
    enter_costs,
    enter_costs_of,
    enter_costs_risk,
    with_ring,
)
from smana.services.planner.window import TilePools, Window, gather_cells, gather_window

# Error codes of PathReply.error
OUT_OF_BOUNDS = "out_of_bounds"
START_BLOCKED = "start_blocked"
GOAL_BLOCKED = "goal_blocked"
UNREACHABLE = "unreachable"
NO_GRAPH = "no_graph"
MALFORMED = "malformed"
# A start on a node not seen yet leaves from the nearest known free node this near (without
# allow_unknown; with it, the unknown node is entered like any other)
SNAP_START_M = 1.0


@dataclass
class PlanResult:
    ok: bool
    error: str = ""
    message: str = ""
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    cost_total: float = 0.0
    cost_distance: float = 0.0
    cost_height: float = 0.0
    cost_traversability: float = 0.0
    label_share: dict[str, float] = field(default_factory=dict)
    nodes_expanded: int = 0
    time_ms: float = 0.0
    nearest_free: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))


class PlanError(Exception):
    def __init__(self, code: str, message: str, nearest_free=None):
        super().__init__(message)
        self.code = code
        self.nearest_free = nearest_free


class Planner:
    """Weighted A* path queries on a NavGrid (navgraph's, or the planner service's copy)."""

    def __init__(self, grid: NavGrid, classes: ClassTable, config: PlannerConfig | None = None):
        """`config` is the [planner] section as it is (its defaults when None): the defaults of
        every query, which a query may override one by one."""
        self.grid = grid
        self.classes = classes
        self.config = PlannerConfig() if config is None else config
        self._cache_key = None
        self._cache = None
        self._enter_key = None
        self._enter_cache = None
        names = ["unknown"] * classes.size
        for cid, c in classes.classes.items():
            names[cid] = c.name
        self._names = names
        # The last query's costs and ends (the defaults and none before any): what `prepare`
        # builds for. Its ends keep the window the query had, so that a patch is refreshed in
        # place instead of the window flipping between two boxes.
        self._last = (classes.costs({}), self.config, False, [])
        self.prepare()

    def prepare(self) -> float:
        """Build ahead what a query builds on a new graph version: the dense window of the
        known area and the last query's ends, its enter costs under that query's costs, and
        this thread's search work array. The constructor calls it, and the service on its tick
        after graph patches, so that the first query after a change costs what a repeat query
        does (a later patch refreshes only its nodes). Nothing to do on an empty grid. Returns
        the seconds taken."""
        t0 = time.perf_counter()
        if self.grid.n_tiles:
            lut, p, allow_unknown, ends = self._last
            box = self._window(ends, allow_unknown)
            labels, flags, _ = self._dense(box)
            self._enter(box, flags, labels, lut, p, allow_unknown)
            reserve((box[2] - box[0]) * (box[3] - box[1]))
        return time.perf_counter() - t0

    # -- the query -----------------------------------------------------------------------------

    def plan_request(self, req, avoid=None, avoid_radius_m: float = 0.0) -> PlanResult:
        """Answer a PathRequest (or anything with its attributes); `avoid` as in `plan`."""
        return self.plan(
            req.start,
            req.goal,
            h_f=req.h_f,
            t_f=req.t_f,
            class_costs=req.class_costs,
            allow_unknown=req.allow_unknown,
            unknown_cost=req.unknown_cost,
            max_step_m=req.max_step_m,
            avoid=avoid,
            avoid_radius_m=avoid_radius_m,
        )

    def plan(
        self,
        start,
        goal,
        *,
        h_f: float | None = None,
        t_f: float | None = None,
        class_costs: dict[int, float] | None = None,
        allow_unknown: bool = False,
        unknown_cost: float | None = None,
        max_step_m: float | None = None,
        heuristic: str | None = None,
        avoid=None,
        avoid_radius_m: float = 0.0,
        risk: str | None = None,
    ) -> PlanResult:
        """`avoid`: positions (K, 2) of moving obstacles (other fleet members): nodes within
        `avoid_radius_m` of one are not entered, except by a path moving away from it (a robot
        already that close may still leave). `risk`: this query's risk mode (the config's when
        None)."""
        t0 = time.perf_counter()
        try:
            result = self._plan(
                start,
                goal,
                h_f,
                t_f,
                class_costs,
                allow_unknown,
                unknown_cost,
                max_step_m,
                heuristic,
                avoid,
                avoid_radius_m,
                risk,
            )
        except PlanError as exc:
            nf = np.zeros(0) if exc.nearest_free is None else np.asarray(exc.nearest_free, float)
            result = PlanResult(False, exc.code, str(exc), nearest_free=nf)
        result.time_ms = (time.perf_counter() - t0) * 1e3
        return result

    def _params(self, h_f, t_f, class_costs, unknown_cost, max_step_m, heuristic, risk=None):
        """The config with this query's overrides, checked by the section's own limits."""
        given = {
            "h_f": h_f,
            "t_f": t_f,
            "max_step_m": max_step_m,
            "unknown_cost": unknown_cost,
            "heuristic": heuristic,
            "risk": risk,
        }
        # a PathRequest always carries unknown_cost: values equal to the config's need no check
        overrides = {
            k: v for k, v in given.items() if v is not None and v != getattr(self.config, k)
        }
        try:
            p = dataclasses.replace(self.config, **overrides) if overrides else self.config
            lut = self.classes.costs(class_costs or {})
        except (ValueError, TypeError) as exc:  # ConfigError is a ValueError
            raise PlanError(MALFORMED, str(exc)) from None
        return p, lut

    def _point(self, name, v) -> np.ndarray:
        try:
            a = np.asarray(v, np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise PlanError(MALFORMED, f"{name} must be 2 or 3 numbers, got {v!r}") from None
        if a.shape not in ((2,), (3,)) or not np.isfinite(a).all():
            raise PlanError(MALFORMED, f"{name} must be 2 or 3 finite numbers, got {v!r}")
        return a[:2]

    def _plan(
        self,
        start,
        goal,
        h_f,
        t_f,
        class_costs,
        allow_unknown,
        unknown_cost,
        max_step_m,
        heuristic,
        avoid=None,
        avoid_radius_m=0.0,
        risk=None,
    ) -> PlanResult:
        p, lut = self._params(h_f, t_f, class_costs, unknown_cost, max_step_m, heuristic, risk)
        s_xy, g_xy = self._point("start", start), self._point("goal", goal)
        g = self.grid
        if g.n_tiles == 0 and not allow_unknown:
            # through the unknown, an empty graph is all unknown ground: planned across, as
            # Nav2's planners plan across an empty costmap (allow_unknown)
            raise PlanError(NO_GRAPH, "no navigation graph yet (no patch received)")
        cells = []
        for name, xy in (("start", s_xy), ("goal", g_xy)):
            ix, iy, ok = g.world_to_cell(xy)
            if not ok:
                lo = g.origin_xy
                hi = lo + np.array(g.shape) * g.resolution_m
                raise PlanError(
                    OUT_OF_BOUNDS,
                    f"{name} ({xy[0]:.2f}, {xy[1]:.2f}) is outside the graph bounds "
                    f"[{lo[0]:.2f}, {hi[0]:.2f}] x [{lo[1]:.2f}, {hi[1]:.2f}]",
                )
            cells.append((int(ix), int(iy)))
        box = self._window(cells, bool(allow_unknown))
        self._last = (lut, p, bool(allow_unknown), cells)
        labels, flags, known_h = self._dense(box)
        enter, min_enter = self._enter(box, flags, labels, lut, p, bool(allow_unknown))
        (sx, sy), (gx, gy) = ((c[0] - box[0], c[1] - box[1]) for c in cells)
        self._check_end("start", sx, sy, flags, enter, box, s_xy, allow_unknown=True)
        snapped = None
        if not allow_unknown and not flags[sx, sy] & FLAG_KNOWN:
            # a robot on a node not seen yet (the ground under it, at start) leaves from the
            # nearest known free node, if one is within SNAP_START_M; the path begins at the
            # start itself
            nf = _nearest_free(enter, sx, sy)
            if nf is not None and math.dist(nf, (sx, sy)) * g.resolution_m <= SNAP_START_M:
                snapped, (sx, sy) = (sx, sy), nf
        goal_cost = lut[labels[gx, gy]] if labels[gx, gy] < len(lut) else np.inf
        self._check_end("goal", gx, gy, flags, enter, box, g_xy, allow_unknown, goal_cost)
        step = float(p.max_step_m)
        # Moving obstacles block nodes for this query only: the cached enter costs are put back
        # after the search. Raising costs keeps min_enter a lower bound: still exact.
        blocked = self._blocked(box, s_xy, g_xy, (gx, gy), avoid, avoid_radius_m)
        saved = enter[blocked] if blocked is not None else None
        try:
            if blocked is not None:
                enter[blocked] = np.inf
            res = search(
                enter,
                known_h,
                (sx, sy),
                (gx, gy),
                g.resolution_m,
                float(p.h_f),
                step,
                p.heuristic,
                min_enter,
            )
        finally:
            if blocked is not None:
                enter[blocked] = saved
        if not res.found:
            raise PlanError(
                UNREACHABLE,
                f"goal ({g_xy[0]:.2f}, {g_xy[1]:.2f}) cannot be reached from start "
                f"({s_xy[0]:.2f}, {s_xy[1]:.2f}) ({res.nodes_expanded} nodes searched"
                + ("" if allow_unknown else "; unknown nodes not allowed")
                + ")",
            )
        if snapped is not None:
            res.cells = np.vstack([np.array([snapped], res.cells.dtype), res.cells])
            res.cost += sum(path_costs(res.cells[:2], enter, known_h, g.resolution_m, p.h_f))
        d, hgt, trav = path_costs(res.cells, enter, known_h, g.resolution_m, p.h_f)
        gcells = res.cells + np.array([box[0], box[1]])
        xy = g.cell_centre(gcells[:, 0], gcells[:, 1])
        z = _fill_heights(known_h[res.cells[:, 0], res.cells[:, 1]])
        path = np.column_stack([xy, z]).astype(np.float32)
        on_path = labels[res.cells[:, 0], res.cells[:, 1]]
        is_known = (flags[res.cells[:, 0], res.cells[:, 1]] & FLAG_KNOWN) != 0
        names = [
            self._names[lab] if k and lab < len(self._names) else "unknown"
            for lab, k in zip(on_path.tolist(), is_known.tolist(), strict=True)
        ]
        counts: dict[str, int] = {}
        for n in names:
            counts[n] = counts.get(n, 0) + 1
        share = {n: c / len(names) for n, c in counts.items()}
        return PlanResult(
            ok=True,
            message=f"{len(path)} nodes, {d:.2f} m",
            path=path,
            cells=gcells,
            cost_total=res.cost,
            cost_distance=d,
            cost_height=hgt,
            cost_traversability=trav,
            label_share=share,
            nodes_expanded=res.nodes_expanded,
        )

    def _blocked(self, box, s_xy, g_xy, goal_cell, avoid, radius_m):
        """Window indices (rows, cols) of the nodes the moving obstacles `avoid` close for this
        query (see `plan`), or None when there are none; a goal among them is refused. Only the
        discs' bounding boxes are visited: the window may be a thousand nodes a side."""
        if avoid is None or radius_m <= 0:
            return None
        avoid = np.asarray(avoid, np.float64).reshape(-1, 2)
        if len(avoid) == 0:
            return None
        g = self.grid
        x0, y0, x1, y1 = box
        cx = g.origin_xy[0] + (np.arange(x0, x1) + 0.5) * g.resolution_m
        cy = g.origin_xy[1] + (np.arange(y0, y1) + 0.5) * g.resolution_m
        rows, cols = [], []
        for ox, oy in avoid:
            d_start = math.hypot(s_xy[0] - ox, s_xy[1] - oy)
            limit = min(radius_m, d_start)  # nearer than the start: only moving away is allowed
            i = np.flatnonzero(np.abs(cx - ox) < limit)
            j = np.flatnonzero(np.abs(cy - oy) < limit)
            inside = np.zeros((0, 2), np.int64)
            if len(i) and len(j):
                d2 = (cx[i, None] - ox) ** 2 + (cy[None, j] - oy) ** 2
                inside = np.argwhere(d2 < limit * limit) + (i[0], j[0])
                rows.append(inside[:, 0])
                cols.append(inside[:, 1])
            if math.hypot(g_xy[0] - ox, g_xy[1] - oy) < limit or (inside == goal_cell).all(1).any():
                raise PlanError(
                    GOAL_BLOCKED,
                    f"goal ({g_xy[0]:.2f}, {g_xy[1]:.2f}) is within {radius_m:g} m of another "
                    f"robot at ({ox:.2f}, {oy:.2f})",
                )
        if not rows or not sum(len(r) for r in rows):
            return None
        return np.concatenate(rows), np.concatenate(cols)

    def _check_end(self, name, ix, iy, flags, enter, box, xy, allow_unknown, cost=np.inf) -> None:
        """Refuse an end in an obstacle or safety zone, or a goal that cannot be entered; `cost`
        is T of the goal's label (finite for a node the risk closed)."""
        f = int(flags[ix, iy])
        code = START_BLOCKED if name == "start" else GOAL_BLOCKED
        if f & FLAG_OBSTACLE:
            why = "in an obstacle"
        elif f & FLAG_SAFETY_ZONE:
            why = "in the safety zone (within the robot radius of an obstacle)"
        elif name == "goal" and not np.isfinite(enter[ix, iy]):
            if f & FLAG_KNOWN and np.isfinite(cost):
                why = "on a node too likely of a forbidden class (max_risk)"
            elif f & FLAG_KNOWN:
                why = "on a node whose class is not traversable"
            else:
                why = "in unknown space (allow_unknown is off)"
        else:
            return
        free = _nearest_free(enter, ix, iy)
        where = ""
        nf = None
        if free is not None:
            nf = self.grid.cell_centre(free[0] + box[0], free[1] + box[1])
            where = f"; nearest free node at ({nf[0]:.2f}, {nf[1]:.2f})"
        raise PlanError(code, f"{name} ({xy[0]:.2f}, {xy[1]:.2f}) is {why}{where}", nf)

    # -- the window ----------------------------------------------------------------------------

    def _window(self, cells, allow_unknown: bool) -> tuple[int, int, int, int]:
        g = self.grid
        known = g.known_box()
        if known is None:  # an empty graph (planned through only as unknown)
            known = (cells[0][0], cells[0][1], cells[0][0] + 1, cells[0][1] + 1)
        x0, y0, x1, y1 = known
        for ix, iy in cells:
            x0, y0, x1, y1 = min(x0, ix), min(y0, iy), max(x1, ix + 1), max(y1, iy + 1)
        if allow_unknown:
            m = g.tile_size
            x0, y0, x1, y1 = x0 - m, y0 - m, x1 + m, y1 + m
        return max(0, x0), max(0, y0), min(g.shape[0], x1), min(g.shape[1], y1)

    def _enter(self, box, flags, labels, lut, p: PlannerConfig, allow_unknown: bool):
        """Per-node enter costs t_f * T(l) of the window (from the class distribution when the
        grid has risk layers) and their finite minimum, cached until the grid or the costs change
        (an explorer asks many paths on one graph version)."""
        # "label", or a grid without the layers: as without risk
        pools = None if p.risk == "label" else RiskPools.of(self.grid)
        model = None if pools is None else risk_model(p)
        key = (self.grid.version, box, lut.tobytes(), p.t_f, p.unknown_cost, p.doubtful_cost)
        ring, clearance = clearance_of(p, self.grid.resolution_m)
        key += (allow_unknown, model, ring, clearance)
        if self._enter_key != key:
            # Scale the finite costs only: inf * 0 would be NaN when t_f = 0.
            scaled = np.where(np.isfinite(lut), lut * p.t_f, np.inf)
            prices = None if pools is None else risk_prices(model, scaled)
            window = self._cache
            cells = self._changed_in(box, self._enter_key, key)
            if cells is not None:
                # Only the patched nodes: their enter costs, and a minimum that can only fall
                # (a minimum that is too low keeps the heuristic a lower bound: still exact).
                out, lowest = self._enter_cache
                costs = enter_costs_of(scaled, allow_unknown, p)
                # a changed node changes the clearance cost of the nodes round it too
                cells = with_ring(cells, ring, labels.shape)
                if pools is None:
                    low = enter_cells(labels, flags, costs, cells, out)
                else:
                    gcells = cells + np.array(box[:2], np.int32)
                    low = enter_cells_risk(window, pools, gcells, cells, costs, prices, out)
                if clearance > 0:
                    add_clearance(flags, out, cells, ring, clearance)
                self._enter_cache = (out, min(lowest, low))
                self._enter_key = key
                return self._enter_cache
            old = self._enter_cache
            out = old[0] if old is not None and old[0].shape == labels.shape else None
            out = np.empty(labels.shape) if out is None else out  # refilled: no page faults
            costs = enter_costs_of(scaled, allow_unknown, p)
            if pools is None:
                lowest = enter_costs(labels, flags, costs, out)
            else:
                lowest = enter_costs_risk(window, pools, box[0], box[1], costs, prices, out)
            if clearance > 0:
                # the clearance cost only adds: the minimum stays a lower bound (exact A*)
                add_clearance_all(flags, out, ring, clearance)
            self._enter_cache = (out, lowest)
            self._enter_key = key
        return self._enter_cache

    def _changed_in(self, box, old_key, new_key) -> np.ndarray | None:
        """Window-local cells (K, 2) that changed between a cache built for `old_key` (graph
        version first, then the window and the rest) and `new_key`; None when the cache must be
        rebuilt whole: another window or cost set, a change the grid cannot list, or a change so
        large that a whole pass is as cheap."""
        if old_key is None or old_key[1:] != new_key[1:]:
            return None
        cells = self.grid.changes_since(old_key[0])
        if cells is None:
            return None
        x0, y0, x1, y1 = box
        if len(cells) > (x1 - x0) * (y1 - y0) // 8:
            return None
        inside = (cells[:, 0] >= x0) & (cells[:, 0] < x1) & (cells[:, 1] >= y0) & (cells[:, 1] < y1)
        return np.ascontiguousarray(cells[inside] - np.array([x0, y0], np.int32))

    def _dense(self, box):
        """labels, flags and known heights (NaN where unknown) of the window, cached until the
        grid changes. Read straight from the grid's tile pools in one pass: `NavGrid.box` and a
        `np.where` took 13 ms at 1000 x 1000 (five full-size temporaries). After a graph change
        the window's arrays are refilled in place when its size did not change: fresh ones cost
        page faults, about 1 ms per 1 MB (measured on the A* work arrays)."""
        g = self.grid
        key = (g.version, box)
        if self._cache_key != key:
            x0, y0, x1, y1 = box
            cells = self._changed_in(box, self._cache_key, key)
            if cells is not None:  # a patch since: refresh its nodes only
                gcells = cells + np.array([x0, y0], np.int32)
                gather_cells(TilePools.of(g), gcells, cells, self._cache)
                self._cache_key = key
                return self._cache
            shape = (x1 - x0, y1 - y0)
            if self._cache is None or self._cache[0].shape != shape:
                self._cache = Window(
                    np.empty(shape, np.uint16),
                    np.empty(shape, np.uint8),
                    np.empty(shape, np.float32),  # the grid's own heights: half the bytes
                )
            gather_window(TilePools.of(g), x0, y0, self._cache)
            self._cache_key = key
        return self._cache


def warm_up(classes: ClassTable) -> float:
    """Compile (or load from numba's cache) the planner's kernels on a tiny grid, so the first
    real query is not slow. Returns the seconds it took."""
    t0 = time.perf_counter()
    grid = NavGrid((0.0, 0.0), (8, 8), 0.2, tile_size=4)
    cells = np.argwhere(np.ones((8, 8), bool))
    trav = [c for c in classes.classes.values() if c.traversable]
    lab = trav[0].id if trav else 0
    grid.apply_patch(cells, np.full(64, lab), np.zeros(64), np.full(64, FLAG_KNOWN, np.uint8))
    planner = Planner(grid, classes)
    for heuristic in HEURISTICS:
        planner.plan((0.1, 0.1), (1.5, 1.5), heuristic=heuristic)
    planner.plan((0.1, 0.1), (9.0, 9.0))  # an error path too
    # the risk kernels: a doubtful label on every node, each mode
    risk = (np.zeros(64, np.uint16), np.full(64, 200, np.uint8), np.zeros(64, np.uint8))
    grid.apply_patch(cells, *grid.read_cells(cells), risk=risk)
    for mode in RISK_MODES:
        planner.plan((0.1, 0.1), (1.5, 1.5), risk=mode)
    grid.apply_patch(cells[:1], *grid.read_cells(cells[:1]), risk=[r[:1] for r in risk])
    planner.plan((0.1, 0.1), (1.5, 1.5))  # the patched nodes only
    return time.perf_counter() - t0


def _fill_heights(z: np.ndarray) -> np.ndarray:
    """Path heights with unknown nodes given the last known height before them (or after, at
    the start), 0 when the whole path is unknown."""
    z = np.asarray(z, np.float64).copy()
    known = ~np.isnan(z)
    if not known.any():
        return np.zeros_like(z)
    idx = np.where(known, np.arange(len(z)), 0)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(known))
    idx[:first] = first
    return z[idx]


@numba.njit(cache=True)
def _nearest_free_kernel(enter, ix, iy, radius):
    nx, ny = enter.shape
    best = -1.0
    bx = -1
    by = -1
    for i in range(max(0, ix - radius), min(nx, ix + radius + 1)):
        for j in range(max(0, iy - radius), min(ny, iy + radius + 1)):
            if enter[i, j] < np.inf:
                d = (i - ix) ** 2 + (j - iy) ** 2
                if best < 0 or d < best:
                    best = d
                    bx = i
                    by = j
    return bx, by, best


def _nearest_free(enter: np.ndarray, ix: int, iy: int):
    """The enterable node nearest to (ix, iy) in the window, or None."""
    r = 8
    limit = max(enter.shape)
    while True:
        bx, by, d2 = _nearest_free_kernel(enter, ix, iy, r)
        # A node found within the square is the nearest only if no closer one lies outside it.
        if bx >= 0 and d2 <= r * r:
            return bx, by
        if r >= limit:
            return (bx, by) if bx >= 0 else None
        r *= 2
