"""A finished run's figures measured from its run directory, for one robot: its trajectory
(the best source there is), its navigation graph, its final map, the usable, false-obstacle and
false-free shares of the reachable area, travelled labels and clearance against ground truth, a
replay's own summary; and the file names and thresholds the rest of the report shares."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from smana.common.classes import ClassTable
from smana.deploy.report import ground_truth as ev

log = logging.getLogger("smana.report")

CLOSE_CALL_M = 0.30  # clearance under which the base (half-width 0.31 m with wheels) may touch


def load_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


REPLAY_TRAJECTORY = "replay_trajectory.csv"  # services/replay/service.py::TRAJECTORY_NAME
RECORDED_POSES = "trajectory_pose.csv"  # services/recorder/recorder.py::TRAJECTORY_FILES
MOVED_M = 0.1  # a robot that travelled less did not move
FLEET_DIR = "robots"  # <run>/robots/<member>/: the member's map.npz, explorer/, trajectories
SIM_SUMMARY = "sim.json"  # the fleet simulator's: robot-robot contacts and separations
COVERAGE_TARGET = 0.95
# A run that stops while its robot knows less than this share of the reachable area as usable
# (usable coverage) did not do its job (checks.py)
USABLE_FLOOR = 0.5
# What ground_truth.exploration_coverage gives (a fleet's "exploration" section copies them)
COVERAGE_KEYS = (
    "coverage",
    "reachable_area_m2",
    *(f"{n}_{u}" for n in ("usable", "false_obstacle", "false_free") for u in ("area_m2", "share")),
    "known_reachable_area_m2",
    "known_reachable_share",
    "known_area_m2",
    "doubtful_area_m2",
    "doubtful_share",
)
# Coverage curves (the explorer's explored_m2 over time, rescaled to the ground truth at the end)
# and the time and distance to COVERAGE_TARGET count the known area, any label: the usable share
# stays well under 95 % even noise-free (the safety zones round true obstacles take their
# margin), so a usable target would never be reached. Usable coverage is the run's outcome;
# this is its speed.
KNOWN_CURVE = "known_reachable_share"


NO_SIMULATOR = (
    "none: the simulator was off (a real robot), so nothing is scored against a simulated "
    "world; `smana eval map RUN_DIR --gt FILE` scores the map against a ground-truth cloud"
)


def as_text(v, fmt=".2f", unit=""):
    """A measure as the report writes it: `v` in `fmt` with its unit, "-" when not measured."""
    return "-" if v is None else f"{format(v, fmt)}{unit}"


def as_percent(share) -> str:
    """A share in [0, 1] as a percentage with one decimal, "-" when not measured."""
    return as_text(None if share is None else 100 * share, ".1f", " %")


def member_dir(run_dir: Path, robot: str) -> Path:
    return Path(run_dir) / FLEET_DIR / robot


def load_trajectory(run_dir: Path) -> tuple[np.ndarray, str]:
    """(t, x, y, yaw) rows of the robot's trajectory and where they come from: every pose a
    replay published (it knows them all, whoever heard them), else the true poses the recorder
    saved when it ran (simulation), else the poses the explorer drove by, else the poses the
    recorder heard."""
    for path, cols, source in (
        (run_dir / REPLAY_TRAJECTORY, [0, 1, 2, 4], "the poses the replay published"),
        (run_dir / "trajectory_truth.csv", [0, 1, 2, 4], "ground truth"),
        (run_dir / "explorer" / "trajectory.csv", [0, 1, 2, 3], "published pose"),
        (run_dir / RECORDED_POSES, [0, 1, 2, 4], "published pose, as the recorder heard it"),
    ):
        if path.is_file():
            try:
                data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
            except ValueError:
                continue
            if len(data):
                return data[:, cols], source
    return np.zeros((0, 4)), "none"


def load_graph(run_dir: Path) -> dict | None:
    for path in (run_dir / "explorer" / "graph.npz", run_dir / "graph.npz"):
        if path.is_file():
            with np.load(path) as g:
                return {k: g[k] for k in g.files}
    return None


def final_map(
    run_dir: Path, classes: ClassTable, fleet: bool = False, backend: str | None = None
) -> Path | None:
    """The run's map as PLY (exported from a saved .npz map when only that exists). A fleet's
    is the merged map, `<run>/map.npz` (its members' own maps are under robots/)."""
    try:
        return ev.find_map(run_dir)
    except FileNotFoundError:
        pass
    maps = [
        p for p in run_dir.rglob("*.npz") if "explorer" not in p.parts and p.name != "graph.npz"
    ]
    if fleet:
        maps = [p for p in maps if p == run_dir / "map.npz"]
    for path in sorted(maps, key=lambda p: p.stat().st_mtime, reverse=True):
        try:
            from smana.services.mapper.semantic_map import SemanticMap

            # backend: the run's own, trusted even as a module:Class spec (map files are checked)
            SemanticMap.load(path, backend=backend).export_ply(run_dir / "map.ply", classes)
            return run_dir / "map.ply"
        except Exception as exc:  # not a map file
            log.debug("%s is not a saved map: %s", path, exc)
    return None


def reachable_area(world, traj: np.ndarray, radius_m: float):
    """(traversability raster, cell centres (nx, ny, 2), mask of the cells reachable from the
    trajectory's start, or from the world's spawn point without one)."""
    trav = world.traversability(radius_m)
    xs, ys = trav.cell_centres()
    cell_xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    start = traj[0, 1:3] if len(traj) else np.array(world.spawn_pose(radius_m)[:2])
    si, sj = trav.index_of(start[0], start[1])
    reach = ev.reachable_traversable(trav.data, (int(si), int(sj)))
    if not reach.any():
        # the start cell itself may sit inside the clearance margin: take the nearest reachable
        d = np.where(
            trav.data, np.hypot(cell_xy[..., 0] - start[0], cell_xy[..., 1] - start[1]), np.inf
        )
        i, j = np.unravel_index(np.argmin(d), d.shape)
        reach = ev.reachable_traversable(trav.data, (int(i), int(j)))
    return trav, cell_xy, reach


def drivable_nodes(graph: dict, lut: np.ndarray, drove_xy: np.ndarray, config) -> np.ndarray:
    """`ev.drivable_nodes` with the run's own rules: the planner's step, the explorer's start
    search radius."""
    return ev.drivable_nodes(
        graph,
        lut,
        drove_xy,
        config.planner.max_step_m,
        config.explorer.start_search_radius_m,
    )


def exploration_metrics(
    world, graph: dict | None, traj: np.ndarray, config, obstacle: np.ndarray | None = None
) -> dict:
    """Coverage (usable, false obstacle, false free: `ev.exploration_coverage`), travelled labels
    and clearance of a run, against the world's ground truth.
    `obstacle`: the world's `ev.collision_raster` when the caller has it already (a fleet's
    members share it)."""
    classes = world.classes
    top = world.top_class()
    res = top.resolution_m
    radius = config.navgraph.robot_radius_m
    _, cell_xy, reach = reachable_area(world, traj, radius)
    out: dict = {"robot_radius_m": radius}
    if graph is not None:
        lut = classes.traversable_lut
        gt_obstacle = ev.gt_obstacle_cells(world)
        drivable = drivable_nodes(graph, lut, traj[:, 1:3], config)
        out.update(
            ev.exploration_coverage(graph, cell_xy, reach, res * res, lut, gt_obstacle, drivable)
        )
    else:
        out.update(ev.no_coverage(float(reach.sum() * res * res)))  # no graph: nothing known
    names = {i: c.name for i, c in classes.classes.items()}
    gres = config.navgraph.resolution_m
    if len(traj) >= 2:
        xy = traj[:, 1:3]
        out["distance_m"] = float(np.hypot(*np.diff(xy, axis=0).T).sum())
        nodes = ev.travelled_nodes(xy, gres, config.navgraph.bounds_min_xy)
        centres = (nodes + 0.5) * gres + np.asarray(config.navgraph.bounds_min_xy)
        gt_labels = top.at(centres[:, 0], centres[:, 1])
        out["travelled_nodes"] = int(len(nodes))
        out["terrain_share"] = ev.terrain_share(gt_labels)
        if graph is not None:
            # what the robot's own graph called the same nodes: the map's belief beside the truth
            out["terrain_share_map"] = ev.terrain_share(ev.sample_grid(graph, centres, "labels"))
        out["travelled_label_share"] = ev.label_shares(gt_labels, names)
        # what the robot's body can hit: objects up to its height (it passes under tree crowns)
        if obstacle is None:
            obstacle = ev.collision_raster(world, ev.robot_height_m())
        clear = ev.clearance_along(xy, obstacle, top.origin_xy, res)
        out["min_clearance_m"] = float(clear.min())
        out["close_calls"] = ev.count_events(clear < CLOSE_CALL_M)
        contact = ev.footprint_contacts(traj[:, [1, 2, 3]], obstacle, top.origin_xy, res)
        out["collisions"] = ev.count_events(contact)
        out["collision_time_s"] = float(np.sum(np.diff(traj[:, 0])[contact[1:]]))
        out["duration_robot_s"] = float(traj[-1, 0] - traj[0, 0])
    return out


def map_content(map_path: Path, names: dict[int, str]) -> dict:
    """What the map holds, per class: needs no ground truth (a replayed dataset has none)."""
    _, labels = ev.load_labelled_cloud(map_path)
    ids, counts = np.unique(labels, return_counts=True)
    n = int(labels.size)
    per_class = {
        names.get(int(i), str(int(i))): {"points": int(c), "share": float(c) / n}
        for i, c in sorted(zip(ids, counts), key=lambda ic: -ic[1])
    }
    return {"n_points": n, "per_class": per_class}


def recorded_poses(run_dir: Path) -> int | None:
    """How many poses the recorder recorded (rows of trajectory_pose.csv); None when no recorder
    ran (it leaves recording.rrd, and recorder.json when it stops)."""
    run_dir = Path(run_dir)
    if not any((run_dir / n).is_file() for n in ("recording.rrd", "recorder.json")):
        return None
    path = run_dir / RECORDED_POSES
    return max(0, len(path.read_text().splitlines()) - 1) if path.is_file() else 0


def replay_metrics(summary: dict, traj: np.ndarray, traj_source: str = "") -> dict:
    """The replay's own summary (without the per-scan rows) and the distance its poses cover,
    measured on `traj` (from `load_trajectory`: the replay's own poses when it wrote them)."""
    out = {k: v for k, v in summary.items() if k != "per_scan"}
    if len(traj) >= 2:
        out["distance_m"] = float(np.hypot(*np.diff(traj[:, 1:3], axis=0).T).sum())
        out["duration_s"] = float(traj[-1, 0] - traj[0, 0])
        out["distance_source"] = traj_source
    elif "distance_m" in out:
        out["distance_source"] = "the replay's summary"
    n = summary.get("points_published") or 0
    lat = (summary.get("latency") or {}).get("mean_ms")
    per_scan = summary.get("per_scan") or []
    if lat is not None and per_scan:
        points = np.array([r[4] for r in per_scan if r[5] is not None], float)
        if points.size:
            out["points_per_scan_mean"] = float(points.mean())
            out["latency_per_point_us"] = 1000.0 * lat / float(points.mean())
    out["points_kept_share"] = n / summary["points_in"] if summary.get("points_in") else None
    return out
