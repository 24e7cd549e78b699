"""What entering each node of the window costs (paper eq. 1's t_f * T(l), `unknown_cost` for an
unknown node, +inf where it is closed), filled whole (`enter_costs`) or node by node after a patch
(`enter_cells`); with the grid's risk layers, a doubtful node priced from its class distribution
by the one risk pricing (`enter_costs_risk`, `enter_cells_risk`: common/risk.py's
`node_risk_cost`); and the clearance cost beside obstacles and safety zones (`add_clearance`,
`add_clearance_all`)."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import (
    FLAG_DOUBTFUL,
    FLAG_KNOWN,
    FLAG_OBSTACLE,
    FLAG_SAFETY_ZONE,
    P_SCALE,
    RISK_LAYER_NAMES,
    NavGrid,
)
from smana.common.risk import node_risk_cost


class EnterCosts(NamedTuple):
    """What the enter-cost kernels turn a node's flags and label into its cost with."""

    lut: np.ndarray  # f8 per label id: t_f * T(l), +inf where not traversable
    allow_unknown: bool  # unknown nodes (and known ones of the "unknown" class) may be entered
    unknown_cost: float  # t_f * their cost
    doubtful_cost: float  # t_f * the cost of a doubtful node (an unconfirmed obstacle class)


def enter_costs_of(scaled_lut, allow_unknown, p: PlannerConfig) -> EnterCosts:
    return EnterCosts(
        scaled_lut,
        bool(allow_unknown),
        float(p.unknown_cost * p.t_f),
        float(p.doubtful_cost * p.t_f),
    )


def clearance_of(p: PlannerConfig, resolution_m: float) -> tuple[int, float]:
    """(ring, cost): how many nodes beyond a blocked node the clearance cost reaches
    (`clearance_m` in nodes, rounded) and its t_f-scaled value beside it (0: none)."""
    ring = int(round(p.clearance_m / resolution_m))
    cost = p.clearance_cost * p.t_f if ring > 0 else 0.0
    return ring, (cost if np.isfinite(cost) else 0.0)


def with_ring(cells: np.ndarray, ring: int, shape) -> np.ndarray:
    """`cells` (K, 2) and every window cell within `ring` nodes of one, each once."""
    if ring <= 0 or len(cells) == 0:
        return cells
    r = np.arange(-ring, ring + 1, dtype=np.int32)
    off = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    out = (cells[:, None, :] + off[None]).reshape(-1, 2)
    inside = (out >= 0).all(axis=1) & (out[:, 0] < shape[0]) & (out[:, 1] < shape[1])
    return np.ascontiguousarray(np.unique(out[inside], axis=0).astype(np.int32))


@numba.njit(cache=True)
def add_clearance(flags, out, cells, ring, cost):
    """Add the clearance cost to the finite enter costs at `cells`: `cost` for a node beside a
    blocked one (obstacle or safety zone), falling linearly with the distance d (in nodes, to
    the nearest blocked node within `ring`) to 0 at d = ring + 1: cost * (ring + 1 - d) / ring."""
    nx, ny = flags.shape
    for k in range(len(cells)):
        i, j = cells[k, 0], cells[k, 1]
        if not out[i, j] < np.inf:
            continue
        best = np.inf
        for a in range(max(0, i - ring), min(nx, i + ring + 1)):
            for b in range(max(0, j - ring), min(ny, j + ring + 1)):
                if flags[a, b] & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE):
                    d = np.sqrt((a - i) ** 2 + (b - j) ** 2)
                    if d < best:
                        best = d
        if best < ring + 1:
            out[i, j] += cost * (ring + 1 - best) / ring


@numba.njit(cache=True)
def add_clearance_all(flags, out, ring, cost):
    """`add_clearance` over the whole window, the other way round: each blocked node on the
    edge of a blocked area (one with an open 8-neighbour; an inner one is never the nearest)
    lowers the distance of the nodes within `ring` of it, then every finite cost gets its
    share. The same distances and sums as `add_clearance`, without a list of every node."""
    nx, ny = flags.shape
    blocked = FLAG_OBSTACLE | FLAG_SAFETY_ZONE
    near = np.full((nx, ny), np.inf)
    for i in range(nx):
        for j in range(ny):
            if not flags[i, j] & blocked:
                continue
            edge = False
            for a in range(max(0, i - 1), min(nx, i + 2)):
                for b in range(max(0, j - 1), min(ny, j + 2)):
                    if not flags[a, b] & blocked:
                        edge = True
            if not edge:
                continue
            for a in range(max(0, i - ring), min(nx, i + ring + 1)):
                for b in range(max(0, j - ring), min(ny, j + ring + 1)):
                    d = np.sqrt((a - i) ** 2 + (b - j) ** 2)
                    if d < near[a, b]:
                        near[a, b] = d
    for i in range(nx):
        for j in range(ny):
            if out[i, j] < np.inf and near[i, j] < ring + 1:
                out[i, j] += cost * (ring + 1 - near[i, j]) / ring


@numba.njit(cache=True)
def _enter_cost(f, lab, lut, n_lut, allow_unknown, unknown_cost, doubtful_cost):
    if f & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE):
        return np.inf
    if f & FLAG_DOUBTFUL:
        return doubtful_cost  # dear but passable: the graph has not confirmed the obstacle
    if f & FLAG_KNOWN:
        c = lut[lab] if lab < n_lut else np.inf
        if c == np.inf and lab == 0 and allow_unknown:
            c = unknown_cost  # a known node of the "unknown" class
        return c
    return unknown_cost if allow_unknown else np.inf


class RiskPools(NamedTuple):
    """The grid's risk layers as the risk kernels read them: pools of (slot, T, T). The kernels
    read them in place: no dense copy of the window is kept (unallocated tiles: certain)."""

    tile_map: np.ndarray
    alt: np.ndarray  # u2: second most likely class, 0 = none
    p_label: np.ndarray  # u1: P(label) x 255
    p_alt: np.ndarray  # u1: P(alt) x 255
    tile_size: int

    @classmethod
    def of(cls, g: NavGrid) -> RiskPools | None:
        """The pools, or None when the grid has no risk layers (every label certain)."""
        if not g.has_risk():
            return None
        return cls(g.tile_map, *(g.layer(name) for name in RISK_LAYER_NAMES), g.tile_size)


@numba.njit(cache=True)
def enter_cells_risk(window, pools, grid_cells, cells, costs, prices, out):
    """`enter_cells` with the nodes' class distributions, read from the grid's risk `pools` at
    `grid_cells` (`cells` in the window)."""
    labels, flags, _ = window
    tile_map, alt_pool, pl_pool, pa_pool, t = pools
    lut, allow_unknown, unknown_cost, doubtful_cost = costs
    model, alt_cost, alt_forbidden = prices
    n_lut = len(lut)
    lowest = np.inf
    for k in range(len(cells)):
        i, j = cells[k, 0], cells[k, 1]
        f = flags[i, j]
        c = _enter_cost(f, labels[i, j], lut, n_lut, allow_unknown, unknown_cost, doubtful_cost)
        gx, gy = grid_cells[k, 0], grid_cells[k, 1]
        slot = tile_map[gx // t, gy // t]
        # Obstacles, safety zones, unknown and doubtful nodes, a label that cannot be entered and
        # a certain label: as without risk.
        if slot >= 0 and c < np.inf and (f & (FLAG_KNOWN | FLAG_DOUBTFUL)) == FLAG_KNOWN:
            lx, ly = gx % t, gy % t
            pl = pl_pool[slot, lx, ly]
            if pl < P_SCALE:
                a = alt_pool[slot, lx, ly]
                a = a if a < n_lut else 0  # outside the table: no class named
                pa = min(pa_pool[slot, lx, ly], P_SCALE - pl) if a > 0 else 0
                c = node_risk_cost(c, alt_cost[a], alt_forbidden[a], pl, pa, model)
        out[i, j] = c
        if c < lowest:
            lowest = c
    return lowest


@numba.njit(cache=True)
def enter_costs_risk(window, pools, ix0, iy0, costs, prices, out):
    """`enter_costs` with the nodes' class distributions, read from the grid's risk `pools`
    (the window's node (0, 0) is the grid's (ix0, iy0)): the costs without risk (a loop LLVM
    vectorises), then tile run by tile run the doubtful nodes, listed first without a branch
    (half the nodes doubtful at random defeats the branch predictor), then the minimum."""
    labels, flags, _ = window
    tile_map, alt_pool, pl_pool, pa_pool, t = pools
    model, alt_cost, alt_forbidden = prices
    n_lut = len(alt_cost)
    enter_costs(labels, flags, costs, out)
    w, h = labels.shape
    doubtful = np.empty(t, np.int64)
    run_alt = np.empty(t, alt_pool.dtype)
    run_pl = np.empty(t, pl_pool.dtype)
    run_pa = np.empty(t, pa_pool.dtype)
    for i in range(w):
        gx = ix0 + i
        tx = gx // t
        lx = gx - tx * t
        j = 0
        while j < h:
            gy = iy0 + j
            ty = gy // t
            ly0 = gy - ty * t
            run = min(t - ly0, h - j)
            slot = tile_map[tx, ty]
            if slot >= 0:  # an unallocated tile reads as certain
                # The run's three layers copied whole first: loads that depend on nothing, so
                # their cache misses overlap (read only at the doubtful nodes, each missed on
                # its own: 5.5 against 3.2 ms with 5 % of the nodes doubtful).
                for k in range(run):
                    run_pl[k] = pl_pool[slot, lx, ly0 + k]
                    run_alt[k] = alt_pool[slot, lx, ly0 + k]
                    run_pa[k] = pa_pool[slot, lx, ly0 + k]
                m = 0
                for k in range(run):
                    doubtful[m] = k
                    m += run_pl[k] < P_SCALE
                for q in range(m):
                    k = doubtful[q]
                    c = out[i, j + k]
                    # obstacles, safety zones, unknown and doubtful nodes and closed labels: as
                    # without risk
                    if (
                        c < np.inf
                        and (flags[i, j + k] & (FLAG_KNOWN | FLAG_DOUBTFUL)) == FLAG_KNOWN
                    ):
                        pl = run_pl[k]
                        a = run_alt[k]
                        a = a if a < n_lut else 0  # outside the table: no class named
                        pa = min(run_pa[k], P_SCALE - pl) if a > 0 else 0
                        out[i, j + k] = node_risk_cost(
                            c, alt_cost[a], alt_forbidden[a], pl, pa, model
                        )
            j += run
    lowest = np.inf
    for i in range(w):
        for j in range(h):
            lowest = min(lowest, out[i, j])
    return lowest if lowest < np.inf else 0.0


@numba.njit(cache=True)
def enter_cells(labels, flags, costs, cells, out):
    """`enter_costs` for a list of window cells; returns their smallest finite cost (+inf
    when none is finite, so that it leaves the cached minimum as it was)."""
    lut, allow_unknown, unknown_cost, doubtful_cost = costs
    lowest = np.inf
    n_lut = len(lut)
    for k in range(len(cells)):
        i, j = cells[k, 0], cells[k, 1]
        c = _enter_cost(
            flags[i, j], labels[i, j], lut, n_lut, allow_unknown, unknown_cost, doubtful_cost
        )
        out[i, j] = c
        if c < lowest:
            lowest = c
    return lowest


@numba.njit(cache=True)
def enter_costs(labels, flags, costs, out):
    """Fill `out` with t_f * T(l) per node (`EnterCosts`); +inf for obstacles, safety zones,
    non-traversable classes, and unknown nodes unless allowed. Returns the smallest finite cost
    (0 when none is finite)."""
    lut, allow_unknown, unknown_cost, doubtful_cost = costs
    nx, ny = labels.shape
    lowest = np.inf
    n_lut = len(lut)
    for i in range(nx):
        for j in range(ny):
            out[i, j] = _enter_cost(
                flags[i, j], labels[i, j], lut, n_lut, allow_unknown, unknown_cost, doubtful_cost
            )
            if out[i, j] < lowest:
                lowest = out[i, j]
    return lowest if lowest < np.inf else 0.0
