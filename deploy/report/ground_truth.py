"""A finished run measured against the simulator's ground truth, as the paper measures it
(4.2.2 and 4.3): what the run report (`write_report`) and `smana eval` compute.

Map precision: for every point of the produced map, the nearest ground-truth point (a k-d tree
over the GT cloud). The reconstruction error is the distance to it (mean and standard deviation)
and the classification ratio the share of map points whose label equals its label; both overall
and per class, where "class" is either the label the map gave (`per_class`: how right is what
the map calls hedge) or the true label of the nearest GT point (`per_true_class`: how much of
the true hedge came out as hedge).

Accuracy alone rewards a map that holds only what it is sure of, so every map is also scored
the other way round, as Tanks and Temples scores a reconstruction (Knapitsch et al. 2017):
`precision` is the share of map points within `threshold_m` (5 cm) of a true surface point,
`completeness` the share of true surface points within `threshold_m` of a map point, and
`f_score` their harmonic mean. The ground truth is the whole world's surface, seen or not, so a
map of part of the world is that incomplete; compare maps of the same views.

Exploration: the share of the reachable traversable area that the final navigation graph knows as
traversable (usable coverage), beside the reachable area it calls an obstacle (false obstacle) and
the obstacles it calls traversable (false free); the labels of the graph nodes the robot
travelled over (terrain vs grass, paper 4.3), and the robot's clearance from obstacles along its
trajectory.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE

# -- map precision ------------------------------------------------------------------------------


def _check_cloud(name: str, points, labels) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points, np.float64)
    labels = np.asarray(labels).astype(np.int64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} points must be (N, 3), got {points.shape}")
    if len(labels) != len(points):
        raise ValueError(f"{name}: {len(points)} points but {len(labels)} labels")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} points contain NaN or inf")
    return points, labels


def nearest_gt(map_points, gt_points, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index) of the nearest ground-truth point for every map point (`tree`: a
    cKDTree of `gt_points` built earlier, reused across maps)."""
    tree = tree if tree is not None else cKDTree(np.asarray(gt_points, np.float64))
    dist, idx = tree.query(np.asarray(map_points, np.float64), k=1)
    return dist, idx


def _summary(err: np.ndarray, ok: np.ndarray) -> dict:
    n = int(len(err))
    if n == 0:
        return {
            "n_points": 0,
            "error_mean_m": None,
            "error_std_m": None,
            "error_median_m": None,
            "classification_ratio": None,
        }
    return {
        "n_points": n,
        "error_mean_m": float(err.mean()),
        "error_std_m": float(err.std()),
        "error_median_m": float(np.median(err)),
        "classification_ratio": float(ok.mean()),
    }


def surface_completeness(map_points, gt_points, threshold_m: float = 0.05) -> float:
    """Share of ground-truth points with a map point within `threshold_m` (0 for an empty map)."""
    mp = np.asarray(map_points, np.float64).reshape(-1, 3)
    gp = np.asarray(gt_points, np.float64).reshape(-1, 3)
    if len(gp) == 0:
        raise ValueError("the ground-truth cloud is empty")
    if len(mp) == 0:
        return 0.0
    dist, _ = cKDTree(mp).query(gp, k=1, distance_upper_bound=threshold_m * (1 + 1e-9))
    return float((dist <= threshold_m).mean())


def evaluate_map(
    map_points,
    map_labels,
    gt_points,
    gt_labels,
    class_names: dict[int, str] | None = None,
    gt_tree=None,
    threshold_m: float = 0.05,
) -> dict:
    """Reconstruction error and classification ratio of a labelled map against a labelled GT cloud.

    Returns a dict: `n_points`, `reconstruction_error_mean_m`, `reconstruction_error_std_m`,
    `reconstruction_error_median_m`, `reconstruction_error_p95_m`, `classification_ratio`,
    `precision`, `completeness`, `f_score` (at `threshold_m`, see the module docstring),
    `threshold_m`, and `per_class` / `per_true_class` (name -> n_points, error_mean_m,
    error_std_m, error_median_m, classification_ratio).
    """
    if not (math.isfinite(threshold_m) and threshold_m > 0):
        raise ValueError(f"threshold_m must be > 0, got {threshold_m}")
    mp, ml = _check_cloud("map", map_points, map_labels)
    gp, gl = _check_cloud("ground truth", gt_points, gt_labels)
    if len(gp) == 0:
        raise ValueError("the ground-truth cloud is empty")
    names = class_names or {}
    if len(mp) == 0:
        return {
            "n_points": 0,
            "reconstruction_error_mean_m": None,
            "reconstruction_error_std_m": None,
            "reconstruction_error_median_m": None,
            "reconstruction_error_p95_m": None,
            "classification_ratio": None,
            "precision": None,
            "completeness": 0.0,
            "f_score": None,
            "threshold_m": threshold_m,
            "per_class": {},
            "per_true_class": {},
        }
    dist, idx = nearest_gt(mp, gp, gt_tree)
    precision = float((dist <= threshold_m).mean())
    completeness = surface_completeness(mp, gp, threshold_m)
    pr = precision + completeness
    f_score = 2 * precision * completeness / pr if pr > 0 else 0.0
    true = gl[idx]
    ok = ml == true
    out = {
        "n_points": int(len(mp)),
        "reconstruction_error_mean_m": float(dist.mean()),
        "reconstruction_error_std_m": float(dist.std()),
        "reconstruction_error_median_m": float(np.median(dist)),
        "reconstruction_error_p95_m": float(np.percentile(dist, 95)),
        "classification_ratio": float(ok.mean()),
        "precision": precision,
        "completeness": completeness,
        "f_score": f_score,
        "threshold_m": threshold_m,
        "per_class": {},
        "per_true_class": {},
    }
    for key, lab in (("per_class", ml), ("per_true_class", true)):
        for c in np.unique(lab):
            sel = lab == c
            out[key][names.get(int(c), str(int(c)))] = _summary(dist[sel], ok[sel])
    return out


# -- exploration --------------------------------------------------------------------------------


def sample_grid(grid: dict, xy: np.ndarray, layer: str = "flags") -> np.ndarray:
    """Values of a saved navigation-grid box at world points; 0 outside the box.

    `grid` holds `origin_xy`, `resolution_m` and dense layers indexed [ix, iy]; node (ix, iy)
    covers [origin + i * res, origin + (i + 1) * res)."""
    data = np.asarray(grid[layer])
    ij = np.floor(
        (np.asarray(xy, float) - np.asarray(grid["origin_xy"], float)) / float(grid["resolution_m"])
    ).astype(np.int64)
    inside = (ij >= 0).all(axis=-1) & (ij[..., 0] < data.shape[0]) & (ij[..., 1] < data.shape[1])
    out = np.zeros(ij.shape[:-1], data.dtype)
    out[inside] = data[ij[inside, 0], ij[inside, 1]]
    return out


def reachable_traversable(trav: np.ndarray, start_ij: tuple[int, int]) -> np.ndarray:
    """Cells of the boolean raster `trav` 8-connected to `start_ij` (empty if it is blocked)."""
    comp, _ = ndimage.label(trav, structure=np.ones((3, 3), bool))
    c = comp[start_ij]
    return comp == c if c > 0 else np.zeros(trav.shape, bool)


def passable_nodes(grid: dict, traversable_lut: np.ndarray) -> np.ndarray:
    """The nodes of a saved navigation-grid box the planner may enter: known, neither obstacle
    nor safety zone, and of a traversable class or doubtful (`graph_layers`'s usable, per node)."""
    flags = np.asarray(grid["flags"])
    labels = np.asarray(grid["labels"]).astype(np.int64)
    lut = np.asarray(traversable_lut, bool)
    inside = (labels >= 0) & (labels < len(lut))
    traversable = np.zeros(labels.shape, bool)
    traversable[inside] = lut[labels[inside]]
    known = (flags & FLAG_KNOWN) != 0
    blocked = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0
    return known & ~blocked & (traversable | ((flags & FLAG_DOUBTFUL) != 0))


# the 8 neighbours of a node, as the planner connects them
_NEIGHBOURS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]


def drivable_nodes(
    grid: dict,
    traversable_lut: np.ndarray,
    drove_xy: np.ndarray,
    max_step_m: float,
    start_radius_m: float = 0.0,
) -> np.ndarray:
    """The passable nodes (`passable_nodes`) the robot could drive to from where it drove: the
    passable ones under `drove_xy` (its trajectory; when none is, a robot that never left an
    unseen node, those within `start_radius_m` of it, as the explorer starts its paths from a
    node that near) and every passable node joined to them through 8-neighbours whose heights
    differ by at most `max_step_m` (the planner's step rule). A passable island behind false
    obstacles, or the top of a hedge whose label the map doubts, is known but not drivable.
    Grown one ring of neighbours at a time (vectorised)."""
    passable = passable_nodes(grid, traversable_lut)
    heights = np.asarray(grid["heights"], np.float64)
    nx, ny = passable.shape
    ij = np.floor(
        (np.asarray(drove_xy, float).reshape(-1, 2) - np.asarray(grid["origin_xy"], float))
        / float(grid["resolution_m"])
    ).astype(np.int64)
    ok = (ij >= 0).all(axis=1) & (ij[:, 0] < nx) & (ij[:, 1] < ny)
    under = np.zeros(passable.shape, bool)
    under[ij[ok, 0], ij[ok, 1]] = True
    seen = under & passable
    r = int(start_radius_m / float(grid["resolution_m"]))
    if not seen.any() and r > 0:
        ax = np.arange(-r, r + 1)
        disc = ax[:, None] ** 2 + ax[None, :] ** 2 <= r * r
        seen = ndimage.binary_dilation(under, structure=disc) & passable
    # per direction, whether the edge from a node to its neighbour may be taken
    edges = []
    for di, dj in _NEIGHBOURS:
        src = (slice(max(0, -di), nx - max(0, di)), slice(max(0, -dj), ny - max(0, dj)))
        dst = (slice(max(0, di), nx + min(0, di)), slice(max(0, dj), ny + min(0, dj)))
        step = np.abs(heights[dst] - heights[src]) <= max_step_m  # NaN: no edge
        edges.append((src, dst, step & passable[dst]))
    while True:
        grown = seen.copy()
        for src, dst, edge in edges:
            grown[dst] |= seen[src] & edge
        if np.array_equal(grown, seen):
            return seen
        seen = grown


def graph_layers(
    grid: dict, cell_xy: np.ndarray, traversable_lut: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(known, usable, blocked, doubtful) masks of the raster cells centred at `cell_xy`
    (..., 2), as the graph node over each calls it: `known` its node is FLAG_KNOWN; `blocked`
    known and FLAG_OBSTACLE or FLAG_SAFETY_ZONE; `usable` known, not blocked, and labelled a
    traversable class (`traversable_lut[label]`, the class table's: a finite cost) or doubtful
    (FLAG_DOUBTFUL: an unconfirmed obstacle class, which the planner prices at its
    `doubtful_cost` and drives through): what the robot could drive on; `doubtful` the usable
    cells that are doubtful. A label outside the table is not traversable."""
    flags = sample_grid(grid, cell_xy)
    known = (flags & FLAG_KNOWN) != 0
    blocked = known & ((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0)
    doubtful = known & ~blocked & ((flags & FLAG_DOUBTFUL) != 0)
    passable = {**grid, "passable": passable_nodes(grid, traversable_lut)}
    return known, sample_grid(passable, cell_xy, "passable"), blocked, doubtful


def gt_obstacle_cells(world) -> np.ndarray:
    """Cells of the world's top-down class raster (`world.top_class()`, the one its
    traversability and the report's reachable area come from) whose class is an obstacle: not
    traversable because an object stands there (not water, not a clearance margin)."""
    return world.classes.obstacle_lut[world.top_class().data]


def exploration_coverage(
    grid: dict,
    cell_xy: np.ndarray,
    reachable: np.ndarray,
    cell_area_m2: float,
    traversable_lut: np.ndarray,
    gt_obstacle: np.ndarray | None = None,
    drivable: np.ndarray | None = None,
) -> dict:
    """What the final navigation graph knows of the ground truth, per raster cell.

    `cell_xy` (..., 2) are the world centres of the raster cells, `reachable` the GT mask of the
    traversable cells the robot could reach and `gt_obstacle` the GT mask of obstacle cells
    (`gt_obstacle_cells`; none when not given), `drivable` the graph's nodes the robot could
    drive to (`drivable_nodes`; when not given, every passable node). Against the graph's
    `graph_layers`:
    - usable: reachable, usable in the graph and under a drivable node, what the robot could
      drive on (`coverage` is its share of the reachable area, the report's headline);
    - false obstacle: reachable, but an obstacle or a safety zone in the graph;
    - false free: an obstacle in ground truth that the graph calls usable (the dangerous one);
    - known: reachable under a known node whatever its label (obstacles included);
    - doubtful: the part of usable under doubtful nodes (passable at a cost).
    Every share is of the reachable area, so that they compare."""
    known, usable, blocked, doubtful = graph_layers(grid, cell_xy, traversable_lut)
    if drivable is not None:
        usable &= sample_grid({**grid, "drivable": drivable}, cell_xy, "drivable")
        doubtful &= usable
    obstacle = np.zeros(reachable.shape, bool) if gt_obstacle is None else gt_obstacle
    n_reach = int(reachable.sum())
    counts = {
        "usable": int((usable & reachable).sum()),
        "false_obstacle": int((blocked & reachable).sum()),
        "false_free": int((usable & obstacle).sum()),
        "known_reachable": int((known & reachable).sum()),
        "doubtful": int((doubtful & reachable).sum()),
    }
    out = {"reachable_area_m2": n_reach * cell_area_m2}
    for name, n in counts.items():
        out[f"{name}_area_m2"] = n * cell_area_m2
        out[f"{name}_share"] = n / n_reach if n_reach else 0.0
    out["coverage"] = out["usable_share"]
    out["known_area_m2"] = float(known.sum() * cell_area_m2)
    return out


def no_coverage(reachable_area_m2: float) -> dict:
    """`exploration_coverage`'s keys for a run that left no graph: nothing known."""
    out = {"reachable_area_m2": reachable_area_m2, "coverage": 0.0, "known_area_m2": 0.0}
    for name in ("usable", "false_obstacle", "false_free", "known_reachable", "doubtful"):
        out[f"{name}_area_m2"] = 0.0
        out[f"{name}_share"] = 0.0
    return out


def travelled_nodes(traj_xy: np.ndarray, resolution_m: float, origin_xy=(0.0, 0.0)) -> np.ndarray:
    """The graph nodes a trajectory entered, in order, each time it entered one: (K, 2) cells."""
    traj_xy = np.asarray(traj_xy, float).reshape(-1, 2)
    if len(traj_xy) == 0:
        return np.zeros((0, 2), np.int64)
    cells = np.floor((traj_xy - np.asarray(origin_xy)) / resolution_m).astype(np.int64)
    change = np.ones(len(cells), bool)
    change[1:] = (cells[1:] != cells[:-1]).any(axis=1)
    return cells[change]


def label_shares(labels: np.ndarray, class_names: dict[int, str]) -> dict[str, float]:
    """Share of each class among `labels` (names as keys), over the classes present."""
    labels = np.asarray(labels).reshape(-1)
    if len(labels) == 0:
        return {}
    ids, counts = np.unique(labels, return_counts=True)
    return {
        class_names.get(int(i), str(int(i))): float(c / len(labels))
        for i, c in zip(ids, counts, strict=True)
    }


def terrain_share(labels: np.ndarray, terrain_id: int = 2, grass_id: int = 1) -> float | None:
    """Travelled nodes on terrain over those on terrain or grass (the paper's 60/70/88 %)."""
    labels = np.asarray(labels)
    n_t = int((labels == terrain_id).sum())
    n_g = int((labels == grass_id).sum())
    return n_t / (n_t + n_g) if n_t + n_g else None


def clearance_along(
    traj_xy: np.ndarray, obstacle: np.ndarray, origin_xy, resolution_m
) -> np.ndarray:
    """Distance (m) from each trajectory point to the nearest obstacle cell of a raster whose cell
    (i, j) is centred at origin + (i, j) * res (the simulator's ground-aligned rasters)."""
    free_dist = ndimage.distance_transform_edt(~obstacle) * resolution_m
    ij = np.rint((np.asarray(traj_xy, float) - np.asarray(origin_xy)) / resolution_m).astype(int)
    ij[:, 0] = np.clip(ij[:, 0], 0, obstacle.shape[0] - 1)
    ij[:, 1] = np.clip(ij[:, 1], 0, obstacle.shape[1] - 1)
    # the raster is sampled at cell centres: a point can be half a diagonal closer than its cell
    return np.maximum(free_dist[ij[:, 0], ij[:, 1]] - resolution_m * np.sqrt(0.5), 0.0)


def collision_raster(world, height_m: float = 0.25, step_m: float = 0.05) -> np.ndarray:
    """Cells of the world's ground raster where an object occupies the band from just above the
    ground to `height_m` (the robot's height): what the robot's body can hit. A tree's crown
    over the robot is not an obstacle; its trunk is."""
    top = world.top_class()
    xs, ys = top.cell_centres()
    gx, gy = (a.ravel() for a in np.meshgrid(xs, ys, indexing="ij"))
    ground = world.ground.height_at(gx, gy)
    hit = np.zeros(gx.shape, bool)
    for dz in np.arange(0.03, height_m + 1e-9, step_m):
        pts = np.column_stack([gx, gy, ground + dz])
        hit |= world.object_class_at(pts) > 0
    return hit.reshape(top.data.shape)


def robot_footprint() -> list[tuple[float, float, float, float]]:
    """The simulated robot's footprint as rectangles (centre x, centre y, half x, half y) in its
    base frame: the chassis and the two wheels (`[sim.robot]`, RobotConfig)."""
    from smana.common.config.sim import RobotConfig

    s = RobotConfig()
    hx, hy, _ = s.chassis_half_extents
    r, half_track = s.wheel_radius_m, s.track_m / 2
    return [(0.0, 0.0, hx, hy), (0.0, half_track, r, r), (0.0, -half_track, r, r)]


def robot_height_m() -> float:
    """Top of the simulated robot's chassis above the ground (what it can pass under)."""
    from smana.common.config.sim import RobotConfig

    s = RobotConfig()
    return s.base_height_m + s.chassis_half_extents[2]


def footprint_contacts(
    traj_xyyaw: np.ndarray,
    obstacle: np.ndarray,
    origin_xy,
    resolution_m: float,
    footprint: list[tuple[float, float, float, float]] | None = None,
) -> np.ndarray:
    """Per trajectory pose, whether the robot's footprint (rectangles in its base frame, default
    `robot_footprint()`) covers the centre of an obstacle cell of a ground-aligned raster."""
    traj = np.asarray(traj_xyyaw, float).reshape(-1, 3)
    rects = np.asarray(footprint if footprint is not None else robot_footprint(), float)
    cells = np.argwhere(obstacle)
    out = np.zeros(len(traj), bool)
    if len(cells) == 0 or len(traj) == 0:
        return out
    centres = np.asarray(origin_xy, float) + cells * resolution_m
    tree = cKDTree(centres)
    reach = float(
        np.max(np.hypot(np.abs(rects[:, 0]) + rects[:, 2], np.abs(rects[:, 1]) + rects[:, 3]))
    )
    for k, near in enumerate(tree.query_ball_point(traj[:, :2], reach)):
        if not near:
            continue
        d = centres[near] - traj[k, :2]
        c, s = np.cos(traj[k, 2]), np.sin(traj[k, 2])
        lx = c * d[:, 0] + s * d[:, 1]
        ly = -s * d[:, 0] + c * d[:, 1]
        inside = (np.abs(lx[:, None] - rects[:, 0]) <= rects[:, 2]) & (
            np.abs(ly[:, None] - rects[:, 1]) <= rects[:, 3]
        )
        out[k] = bool(inside.any())
    return out


def count_events(flags: np.ndarray) -> int:
    """Number of runs of True in a boolean sequence (a contact that lasts is one contact)."""
    f = np.asarray(flags, bool).astype(np.int8)
    return int((np.diff(np.concatenate([[0], f])) == 1).sum())


# -- run directories ----------------------------------------------------------------------------

MAP_CANDIDATES = ("map.ply", "mapper/map.ply", "final_map.ply")


def find_map(run_dir: Path) -> Path:
    for name in MAP_CANDIDATES:
        if (run_dir / name).is_file():
            return run_dir / name
    found = sorted(run_dir.rglob("*.ply"), key=lambda p: p.stat().st_mtime, reverse=True)
    found = [p for p in found if p.name != "gt.ply"]
    if not found:
        raise FileNotFoundError(f"no map PLY in {run_dir} (looked for {', '.join(MAP_CANDIDATES)})")
    return found[0]


def load_labelled_cloud(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), labels (N,)) from a labelled PLY or a saved map (.npz)."""
    path = Path(path)
    if path.suffix == ".npz":
        from smana.services.mapper.semantic_map import SemanticMap

        m = SemanticMap.load(path)
        d = m.occupied_voxels()
        return np.asarray(d.centres, np.float64), np.asarray(d.labels)
    from smana.services.sim.labelled_ply import read_labelled_ply

    return read_labelled_ply(path)


def world_from_config(config):
    """The simulated world a run used, rebuilt from its config (same seed, same world)."""
    from smana.common.classes import ClassTable
    from smana.services.sim.worlds import build_world

    return build_world(config.sim, ClassTable.load(config.general.class_table))


def gt_cloud_for_run(run_dir: Path, config, spacing_m: float = 0.03):
    """The GT cloud of a run: `<run_dir>/gt.ply`, exported there from the world if missing.
    ValueError when it is missing and the run had no simulator (no world to export)."""
    gt = run_dir / "gt.ply"
    if not gt.is_file() and not config.deploy.sim.enabled:
        raise ValueError(
            f"no ground truth for {run_dir}: the simulator was off in this run (no {gt.name}); "
            "give one with --gt FILE"
        )
    if not gt.is_file():
        world_from_config(config).export_ply(gt, spacing_m)
    return load_labelled_cloud(gt)


def load_run_config(run_dir: Path):
    from smana.common.config import SmanaConfig

    path = run_dir / "config.toml"
    return SmanaConfig.load(path if path.is_file() else None)
