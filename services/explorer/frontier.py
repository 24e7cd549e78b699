"""Next-best-view frontier exploration on the 2.5D navigation grid (paper 4.3, after Achat 2022).

The explorer works on a box of the navigation graph exported as dense arrays indexed `[ix, iy]`
at the graph resolution: `labels` (class ids), `flags` (bit 1 KNOWN, 2 OBSTACLE, 4 SAFETY_ZONE,
8 DOUBTFUL).
Three steps, each usable alone:

1. `traversable_mask` / `reachable_mask` / `frontier_cells`: candidate views are known, free,
   reachable nodes that touch unknown space (the border of the explored traversable area);
   `sample_candidates` thins them to one per `spacing` block so scoring stays cheap.
2. `view_gains`: for each candidate and each of `n_yaw` headings, the unknown area (m^2) inside
   the camera's field-of-view mask (a sector of `fov_deg` and `max_range_m`: [explorer.view]),
   optionally cut by line of sight through obstacle nodes. The best heading is the view's yaw.
3. `select_view`: score = gain / A_view - weight * cost / (c_flat * max_range) (`ViewScore`: the
   share of a full view that is unknown, minus the path cost counted in view ranges driven on the
   cheapest flat ground). Path costs come from a callable (the planner over Zenoh in the service, a
   local search in tests); the candidates are queried in order of an optimistic bound so that
   only a few paths are requested (branch and bound).

The nearest-frontier baseline (Yamauchi 1997) needs `travel_distance_m`: metres over free nodes
from the robot, 8-connected (a numba Dijkstra, `kernels.travel_distance_kernel`).

The numba kernels live in kernels.py, imported on first use: the explorer service imports this
module before it is live, and numba's import alone is a quarter of a second of CPU.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from smana.common.config.explorer import ViewConfig
from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE

# the navigation graph's node flags, under the short names this module has always used
KNOWN, OBSTACLE, SAFETY_ZONE, DOUBTFUL = FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, FLAG_DOUBTFUL

EIGHT_CONNECTED = np.ones((3, 3), bool)  # the planner's graph: what is reachable here is there


# -- which nodes are free, reachable, on the frontier -----------------------------------------


def _check_grid(labels: np.ndarray, flags: np.ndarray) -> None:
    if labels.ndim != 2 or flags.shape != labels.shape:
        raise ValueError(
            f"labels and flags must be 2-D arrays of one shape, got {labels.shape} {flags.shape}"
        )


def traversable_mask(
    labels: np.ndarray, flags: np.ndarray, traversable_lut: np.ndarray
) -> np.ndarray:
    """Known nodes the robot may stand on: a traversable class, or a doubtful node (an obstacle
    class the graph has not confirmed: the planner's paths may cross it, dearly); no obstacle,
    not in the safety zone.

    Labels outside the lookup table count as not traversable (a corrupt id must never open a
    way through an obstacle).
    """
    labels = np.asarray(labels)
    flags = np.asarray(flags)
    _check_grid(labels, flags)
    lut = np.asarray(traversable_lut, bool)
    inside = labels < lut.size
    trav = np.zeros(labels.shape, bool)
    trav[inside] = lut[labels[inside]]
    free = (flags & KNOWN).astype(bool) & ~(flags & (OBSTACLE | SAFETY_ZONE)).astype(bool)
    return (trav | ((flags & DOUBTFUL) != 0)) & free


def reachable_mask(free: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Nodes of `free` 8-connected to `start`; all False when `start` is not free.

    8-connectivity matches the planner's graph, so what is reachable here is reachable there.
    """
    ix, iy = start
    if not (0 <= ix < free.shape[0] and 0 <= iy < free.shape[1]) or not free[ix, iy]:
        return np.zeros(free.shape, bool)
    from scipy import ndimage  # here, not at import: half a second off the explorer's start

    comp, _ = ndimage.label(free, structure=EIGHT_CONNECTED)
    return comp == comp[ix, iy]


def step_components(free: np.ndarray, heights: np.ndarray | None, max_step_m: float) -> np.ndarray:
    """Components of `free` (int32 labels, 0 off it) as the planner joins nodes: 8-connected,
    and only across a height step of at most `max_step_m` (the planner's `max_step_m`; a NaN
    height joins any neighbour). A doubtful hedge top 1 m up is then apart from the lawn beside
    it, as no path climbs to it. No heights, or an infinite step: scipy's 8-connected labels."""
    free = np.ascontiguousarray(free, dtype=np.bool_)
    if heights is None or not math.isfinite(max_step_m):
        from scipy import ndimage  # here, not at import: off the explorer's start

        return ndimage.label(free, structure=EIGHT_CONNECTED)[0].astype(np.int32)
    heights = np.ascontiguousarray(heights, dtype=np.float32)
    if heights.shape != free.shape:
        raise ValueError(f"heights {heights.shape} and free {free.shape} differ")
    from smana.services.explorer.kernels import step_components_kernel

    labels = np.zeros(free.shape, np.int32)
    step_components_kernel(free, heights, np.float64(max_step_m), labels)
    return labels


def unknown_mask(flags: np.ndarray) -> np.ndarray:
    return (np.asarray(flags) & KNOWN) == 0


def opaque_mask(flags: np.ndarray) -> np.ndarray:
    """Known obstacle nodes: what hides the view behind it (`view_gains`' `opaque`)."""
    flags = np.asarray(flags)
    return ((flags & KNOWN) != 0) & ((flags & OBSTACLE) != 0)


def frontier_cells(reachable: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """Reachable nodes with at least one unknown 8-neighbour, as an (F, 2) array of (ix, iy).

    Space outside the grid box is not unknown: the graph has fixed bounds and nothing outside them
    can ever be mapped, so a border node is a frontier only if it touches unknown nodes inside.
    """
    from scipy import ndimage

    near_unknown = ndimage.binary_dilation(unknown, structure=EIGHT_CONNECTED, border_value=0)
    return np.argwhere(reachable & near_unknown)


def sample_candidates(cells: np.ndarray, spacing: int) -> np.ndarray:
    """One frontier node per `spacing` x `spacing` block: the one nearest the block's centre.

    Deterministic (ties broken by cell order) and vectorised; keeps candidates spread along every
    frontier while bounding their number by the frontier's extent rather than its node count.
    """
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    if spacing < 1:
        raise ValueError(f"spacing must be >= 1 node, got {spacing}")
    if spacing == 1 or len(cells) == 0:
        return cells
    block = cells // spacing
    centre = block * spacing + (spacing - 1) / 2.0
    d2 = ((cells - centre) ** 2).sum(axis=1)
    key = block[:, 0] * (1 << 32) + block[:, 1]
    order = np.lexsort((d2, key))
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return cells[np.sort(order[first])]


# -- field-of-view gain -----------------------------------------------------------------------


@dataclass(frozen=True)
class FovModel:
    """The camera's footprint on the grid: cell offsets inside `view.max_range_m`, and per heading
    the offsets that fall inside the horizontal field of view.

    `in_sector[k, o]` is True when offset `o` lies within +-fov/2 of heading `yaws[k]`. Offsets
    closer than `view.min_range_m` are left out: a camera a few decimetres above the ground does
    not see the ground right under its lens.
    """

    resolution_m: float
    view: ViewConfig
    yaws: np.ndarray  # (K,) radians
    offsets: np.ndarray  # (O, 2) int64 cell offsets
    in_sector: np.ndarray  # (K, O) bool

    @classmethod
    def build(cls, resolution_m: float, view: ViewConfig) -> FovModel:
        """The footprint of `view` (the [explorer.view] section, already checked) on a grid of
        `resolution_m`."""
        if not resolution_m > 0:
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        fov_deg, max_range_m, min_range_m = view.fov_deg, view.max_range_m, view.min_range_m
        r = int(math.ceil(max_range_m / resolution_m))
        dx, dy = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
        dist = np.hypot(dx, dy) * resolution_m
        keep = (dist <= max_range_m) & (dist >= min_range_m) & ((dx != 0) | (dy != 0))
        offsets = np.stack([dx[keep], dy[keep]], axis=1).astype(np.int64)
        bearing = np.arctan2(offsets[:, 1], offsets[:, 0])
        yaws = np.arange(view.n_yaw) * (2 * np.pi / view.n_yaw)
        diff = np.angle(np.exp(1j * (bearing[None, :] - yaws[:, None])))
        # a small epsilon so that offsets exactly on the sector edge count the same on every side
        in_sector = np.abs(diff) <= math.radians(fov_deg) / 2 + 1e-9
        return cls(float(resolution_m), view, yaws, offsets, in_sector)

    @property
    def view_area_m2(self) -> float:
        """The area of one full view: the largest gain any candidate can have (all unknown)."""
        return float(self.in_sector.sum(axis=1).max()) * self.resolution_m**2


def view_gains(
    unknown: np.ndarray,
    opaque: np.ndarray | None,
    candidates: np.ndarray,
    fov: FovModel,
    samples_per_cell: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Unknown area (m^2) each candidate would see per heading: (gains (C, K), best yaw (C,)).

    `opaque` marks nodes that block the view (obstacles); None disables occlusion, which is the
    paper's plain mask intersection. Unknown nodes never block: what is unknown is assumed open,
    the optimistic choice that keeps exploration going into unseen space.
    """
    unknown = np.ascontiguousarray(unknown, dtype=np.bool_)
    if unknown.ndim != 2:
        raise ValueError(f"unknown must be 2-D, got shape {unknown.shape}")
    occlusion = opaque is not None
    opaque_arr = (
        np.ascontiguousarray(opaque, dtype=np.bool_) if occlusion else np.zeros((1, 1), np.bool_)
    )
    if occlusion and opaque_arr.shape != unknown.shape:
        raise ValueError(f"opaque shape {opaque_arr.shape} != unknown shape {unknown.shape}")
    cand = np.ascontiguousarray(np.asarray(candidates, np.int64).reshape(-1, 2))
    if len(cand) and (
        cand.min() < 0
        or cand[:, 0].max() >= unknown.shape[0]
        or cand[:, 1].max() >= unknown.shape[1]
    ):
        raise ValueError("candidate cells outside the grid")
    if samples_per_cell < 1:
        raise ValueError(f"samples_per_cell must be >= 1, got {samples_per_cell}")
    if len(cand) == 0:
        return np.zeros((0, len(fov.yaws))), np.zeros(0)
    from .kernels import visible_unknown_kernel  # numba: imported on first use (kernels.py)

    vis = visible_unknown_kernel(
        unknown, opaque_arr, cand, fov.offsets, occlusion, int(samples_per_cell)
    )
    counts = vis.astype(np.float32) @ fov.in_sector.T.astype(np.float32)
    gains = counts.astype(np.float64) * fov.resolution_m**2
    best = fov.yaws[np.argmax(gains, axis=1)]
    return gains, best


# -- choosing the view ------------------------------------------------------------------------


def path_cost_scale(
    t_f: float, class_costs: np.ndarray, resolution_m: float
) -> tuple[float, float]:
    """(cost per metre on the cheapest flat ground, a lower bound on cost per straight-line metre)
    for the planner's cost c = d + h_f |dh| + t_f T(l) per step (paper eq. 1).

    Along a grid axis a metre is 1/res steps of cost res + t_f T_min: 1 + t_f T_min / res (5 with
    the defaults t_f 0.8, T(terrain) 1, res 0.2). No path can do better than diagonal steps on the
    cheapest class (res sqrt 2 per step), nor beat the straight line: 1 + t_f T_min / (res sqrt 2)
    per metre of straight-line distance bounds every path from below (`select_view`'s bound).
    """
    if not resolution_m > 0 or not t_f >= 0:
        raise ValueError(f"need resolution_m > 0 and t_f >= 0, got {resolution_m}, {t_f}")
    costs = np.asarray(class_costs, np.float64)
    finite = costs[np.isfinite(costs)]
    t_min = float(finite.min()) if len(finite) else 0.0
    return 1.0 + t_f * t_min / resolution_m, 1.0 + t_f * t_min / (resolution_m * math.sqrt(2.0))


@dataclass(frozen=True)
class ViewScore:
    """score = gain_m2 / view_area_m2 - weight * cost / cost_per_view_range.

    Both terms are dimensionless, so `weight` (`explorer.path_cost_weight`) reads as the share of
    a full view worth driving one view range (`view.max_range_m`) on the cheapest flat ground:
    gain and cost trade on one scale whatever the sensor's footprint or the planner's t_f.
    """

    view_area_m2: float  # `FovModel.view_area_m2`: the gain of a view into all-unknown space
    cost_per_view_range: float  # planner cost of max_range_m on the cheapest flat ground
    weight: float

    def __post_init__(self):
        if not (self.view_area_m2 > 0 and self.cost_per_view_range > 0 and self.weight >= 0):
            raise ValueError(
                f"need view_area_m2 > 0, cost_per_view_range > 0, weight >= 0, got {self}"
            )

    def __call__(self, gain_m2, cost):
        return gain_m2 / self.view_area_m2 - self.weight * cost / self.cost_per_view_range


PathCostFn = Callable[[np.ndarray], "tuple[float, object] | None"]


@dataclass
class ViewChoice:
    cell: np.ndarray  # (2,) node index
    xy: np.ndarray  # (2,) metres
    yaw: float
    gain_m2: float
    path_cost: float
    score: float  # nbv: `ViewScore`; nearest_frontier: minus the travel distance (m)
    path: object  # whatever the cost function returned with the cost (the planner's reply)
    n_queries: int
    n_candidates: int


def select_view(
    candidates_xy: np.ndarray,
    cells: np.ndarray,
    gains_m2: np.ndarray,
    yaws: np.ndarray,
    robot_xy: np.ndarray,
    path_cost: PathCostFn,
    score: ViewScore,
    min_gain_m2: float,
    cost_per_m_lower_bound: float = 1.0,
    *,
    max_queries: int,
) -> ViewChoice | None:
    """Best view by `score(gain, path cost)`, asking `path_cost` as few times as it can.

    `path_cost(goal_xy)` returns (cost, path) or None when the goal is unreachable. Every path
    costs at least `cost_per_m_lower_bound` times the straight-line distance and the score falls
    as the cost grows, so `score(gain, bound * distance)` is an upper bound on a candidate's
    score: candidates are queried in order of that bound and the search stops as soon as no
    remaining bound can beat the best score found (exact), or after `max_queries` (a latency cap;
    then the best found so far wins).
    Candidates with a gain below `min_gain_m2` are not worth a trip; None when none is left.
    """
    if cost_per_m_lower_bound < 0:
        raise ValueError("cost_per_m_lower_bound must be >= 0")
    candidates_xy = np.asarray(candidates_xy, np.float64).reshape(-1, 2)
    gains_m2 = np.asarray(gains_m2, np.float64).reshape(-1)
    worth = np.flatnonzero(gains_m2 >= min_gain_m2)
    if len(worth) == 0:
        return None
    dist = np.hypot(*(candidates_xy[worth] - np.asarray(robot_xy, np.float64)[:2]).T)
    bound = score(gains_m2[worth], cost_per_m_lower_bound * dist)
    order = worth[np.argsort(-bound, kind="stable")]
    bound_sorted = np.sort(bound)[::-1]
    best: ViewChoice | None = None
    n_queries = 0
    for rank, i in enumerate(order):
        if best is not None and bound_sorted[rank] <= best.score:
            break
        if n_queries >= max_queries:
            break
        n_queries += 1
        reply = path_cost(candidates_xy[i])
        if reply is None:
            continue
        cost, path = reply
        if not math.isfinite(cost):
            continue
        s = float(score(gains_m2[i], cost))
        if best is None or s > best.score:
            best = ViewChoice(
                np.asarray(cells[i]),
                candidates_xy[i].copy(),
                float(yaws[i]),
                float(gains_m2[i]),
                float(cost),
                s,
                path,
                0,
                len(worth),
            )
    if best is not None:
        best.n_queries = n_queries
    return best


# -- the nearest-frontier baseline ------------------------------------------------------------


def travel_distance_m(
    free: np.ndarray, starts: np.ndarray, start_dist_m: np.ndarray, resolution_m: float
) -> np.ndarray:
    """Metres of travel from the nearest start to every node over `free` nodes (8-connected,
    diagonal res * sqrt 2, class costs ignored: Yamauchi's nearest frontier is by distance);
    inf where no start reaches. Each start (ix, iy) must be free and begins at `start_dist_m`
    (the hop from the robot to it)."""
    free = np.ascontiguousarray(free, dtype=np.bool_)
    if free.ndim != 2:
        raise ValueError(f"free must be 2-D, got shape {free.shape}")
    src = np.ascontiguousarray(np.asarray(starts, np.int64).reshape(-1, 2))
    src_d = np.ascontiguousarray(np.asarray(start_dist_m, np.float64).reshape(-1))
    if len(src_d) != len(src):
        raise ValueError(f"{len(src)} starts but {len(src_d)} start distances")
    if not resolution_m > 0:
        raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
    if len(src) == 0:
        return np.full(free.shape, np.inf)
    if (src < 0).any() or (src[:, 0] >= free.shape[0]).any() or (src[:, 1] >= free.shape[1]).any():
        raise ValueError("start nodes outside the grid")
    if not free[src[:, 0], src[:, 1]].all():
        raise ValueError("start nodes must be free")
    if not (np.isfinite(src_d).all() and (src_d >= 0).all()):
        raise ValueError("start distances must be finite and >= 0")
    from .kernels import travel_distance_kernel

    return travel_distance_kernel(free, src, src_d, float(resolution_m))
