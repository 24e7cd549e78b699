"""The run report `smana up` writes at the end: `metrics.json`, `report.md` and PNG plots.

`write_report(run_dir, config)` reads what the services left in the run directory:
- `explorer/state.json`, `explorer/trajectory.csv`, `explorer/graph.npz` (the explorer's copy of
  the navigation graph, saved on shutdown);
- the mapper's final map (`map.ply`, or a saved `.npz` map that is exported to `map.ply`);
- `recording.rrd`, `recorder.json`, `trajectory_{pose,truth}.csv` (the Rerun recorder) and `logs/`;
- for a replayed dataset, `replay.json` (passed in) and `replay_trajectory.csv` (every pose the
  replay published);
and measures the run against the simulated world's ground truth (rebuilt from the config):
explored share of the reachable traversable area, travelled labels (terrain vs grass), clearance
from obstacles along the trajectory, and the map's reconstruction error and classification ratio.

A fleet's run (`fleet.robots` set) is laid out per member instead: `robots/<r>/map.npz` (the
member's own map), `robots/<r>/explorer/{state.json,trajectory.csv,graph.npz}`,
`robots/<r>/trajectory_{pose,truth}.csv`, beside the merged `map.npz` and the simulator's
`sim.json` (robot-robot contacts, separations). Its report adds a "fleet" section
(`fleet_metrics`): per member, contacts, merged coverage, the overlap of the members' maps, time
and total distance to 95 % coverage, the merged map's scores beside each member's own map's; and
its warnings (`fleet_warnings`): a contact, a member without state or that did not move.

Also a command: `python -m smana.lab.report RUN_DIR` re-writes the report of a finished run.
"""

from __future__ import annotations

import json
import logging
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from smana.common.classes import ClassTable
from smana.common.messages import json_default
from smana.common.version import smana_version
from smana.lab import evaluation as ev
from smana.lab import plots

log = logging.getLogger("smana.report")

CLOSE_CALL_M = 0.30  # clearance under which the base (half-width 0.31 m with wheels) may touch


def _load_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


REPLAY_TRAJECTORY = "replay_trajectory.csv"  # services/replay/service.py::TRAJECTORY_NAME
RECORDED_POSES = "trajectory_pose.csv"  # deploy/recording.py::TRAJECTORY_FILES


def _trajectory(run_dir: Path) -> tuple[np.ndarray, str]:
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


def _graph(run_dir: Path) -> dict | None:
    for path in (run_dir / "explorer" / "graph.npz", run_dir / "graph.npz"):
        if path.is_file():
            with np.load(path) as g:
                return {k: g[k] for k in g.files}
    return None


def _final_map(
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


def exploration_metrics(
    world, graph: dict | None, traj: np.ndarray, config, obstacle: np.ndarray | None = None
) -> dict:
    """Coverage, travelled labels and clearance of a run, against the world's ground truth.
    `obstacle`: the world's `ev.collision_raster` when the caller has it already (a fleet's
    members share it)."""
    classes = world.classes
    top = world.top_class()
    res = top.resolution_m
    radius = config.navgraph.robot_radius_m
    _, cell_xy, reach = reachable_area(world, traj, radius)
    out: dict = {"robot_radius_m": radius}
    if graph is not None:
        out.update(ev.exploration_coverage(graph, cell_xy, reach, res * res))
    else:
        # no graph: nothing explored (the same keys exploration_coverage gives)
        out.update(
            {
                "coverage": 0.0,
                "reachable_area_m2": float(reach.sum() * res * res),
                "explored_reachable_area_m2": 0.0,
                "known_area_m2": 0.0,
            }
        )
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


def _plots(
    run_dir: Path,
    classes: ClassTable,
    world,
    graph,
    traj,
    state,
    replay: dict | None = None,
    exploration: dict | None = None,
) -> dict[str, str]:
    """Top-down ground truth (simulated runs), the graph, exploration progress and, for a replay,
    the integration latency per scan. `exploration`: the report's exploration metrics, so the
    progress plot can show the report's explored area beside the explorer's own."""
    out_dir = run_dir / "plots"
    files = {}
    goals = np.array([p["goal"] for p in (state or {}).get("plans", [])]).reshape(-1, 2)
    xy = traj[:, 1:3] if len(traj) else None

    def put(name: str, fig) -> None:
        files[name] = str(plots.save(fig, out_dir / f"{PLOT_FILES[name]}").relative_to(run_dir))

    if world is not None:
        top = world.top_class()
        put(
            "map",
            plots.world_map(
                classes,
                top.data,
                top.origin_xy,
                top.resolution_m,
                "Ground truth from above, with the robot's trajectory",
                trajectory=xy,
                goals=goals,
            ),
        )
    if graph is not None:
        put(
            "graph",
            plots.graph_map(
                classes,
                graph["labels"],
                graph["flags"],
                graph["origin_xy"],
                float(graph["resolution_m"]),
                "Navigation graph at the end of the run (the explorer's copy)",
                trajectory=xy,
                goals=goals,
            ),
        )
    hist = np.asarray((state or {}).get("history") or [], float).reshape(-1, 4)
    if len(hist) >= 2:
        put(
            "progress",
            plots.progress_plot(
                hist[:, 0] - hist[0, 0],
                hist[:, 1],
                hist[:, 3],
                (exploration or {}).get("explored_reachable_area_m2"),
            ),
        )
    rows = [r for r in (replay or {}).get("per_scan") or [] if r[5] is not None]
    if len(rows) >= 2:
        put(
            "replay_latency",
            plots.line_plot(
                [
                    plots.Series(
                        "scan published -> integrated by the mapper",
                        [float(r[1]) for r in rows],
                        [float(r[5]) for r in rows],
                    )
                ],
                "Replay: integration latency per scan (one run)",
                "scan index",
                "latency (ms, wall time)",
            ),
        )
    return files


PLOT_FILES = {
    "map": "world_trajectory.png",
    "graph": "graph.png",
    "progress": "progress.png",
    "replay_latency": "replay_latency.png",
}


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
    measured on `traj` (from `_trajectory`: the replay's own poses when it wrote them)."""
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


MOVED_M = 0.1  # a robot that travelled less did not move


def run_warnings(metrics: dict, explored: bool) -> list[str]:
    """What in a finished run's figures says it did not do its job. `explored`: the run was an
    exploration (the explorer ran), so it should have answered paths and moved the robot."""
    out = []
    ee = metrics.get("explorer")
    if explored and ee is None:
        out.append("the explorer left no state (explorer/state.json): it never ran to its end")
    if ee:
        queries, ok = int(ee.get("path_queries") or 0), int(ee.get("path_ok") or 0)
        errs = ee.get("path_errors") or {}
        if queries and not ok:
            detail = ", ".join(f"{k} x{v}" for k, v in sorted(errs.items())) or "no detail"
            out.append(f"no path query was ever answered with a path ({queries} asked: {detail})")
        if ee.get("done_reason") == "no_graph":
            out.append("the explorer never received a navigation graph (ended `no_graph`)")
        if ee.get("done_reason") == "no_planner":
            out.append("the explorer never saw a planner (ended `no_planner`)")
    if explored:
        ex = metrics.get("exploration") or {}
        dist = ex.get("distance_m", (ee or {}).get("distance_m"))
        if dist is None or dist < MOVED_M:
            out.append(f"the robot did not move ({_f(dist, '.2f', ' m')} travelled)")
    return out + replay_warnings(metrics.get("replay") or {})


def replay_warnings(rp: dict) -> list[str]:
    """What in a replay's figures says it did not do its job: a scan lost in lockstep (where
    nothing may be lost; realtime drops are by design and only reported), a recorder that
    missed poses the replay published or did not stop cleanly."""
    out = []
    if rp.get("mode") == "lockstep" and rp.get("lost"):
        out.append(
            f"{rp['lost']} scan(s) lost in lockstep: no MapDelta even after resending "
            "them, so the map misses them (see logs/mapper.log)"
        )
    published, recorded = rp.get("poses_published"), rp.get("poses_recorded")
    if published is not None and recorded is not None and recorded < published:
        out.append(
            f"the recorder recorded {recorded} of the {published} poses the replay "
            "published (see logs/recorder.log): its recording is incomplete"
        )
    if recorded is not None and not rp.get("recorder_stopped_cleanly", True):
        out.append(
            "the recorder did not stop cleanly (no recorder.json): its recording may be "
            "incomplete (see logs/recorder.log)"
        )
    return out


# -- a fleet's run -------------------------------------------------------------------------------

FLEET_DIR = "robots"  # <run>/robots/<member>/: the member's map.npz, explorer/, trajectories
SIM_SUMMARY = "sim.json"  # the fleet simulator's: robot-robot contacts and separations
COVERAGE_TARGET = 0.95


def member_dir(run_dir: Path, robot: str) -> Path:
    return Path(run_dir) / FLEET_DIR / robot


def fleet_graph(run_dir: Path, robots) -> dict | None:
    """The fleet's shared navigation graph at the end: the newest member's copy (each member's
    explorer saves the same graph), else `<run>/graph.npz`."""
    copies = [member_dir(run_dir, r) / "explorer" / "graph.npz" for r in robots]
    copies = sorted((p for p in copies if p.is_file()), key=lambda p: p.stat().st_mtime)
    for path in [*reversed(copies), Path(run_dir) / "graph.npz"]:
        if path.is_file():
            with np.load(path) as g:
                return {k: g[k] for k in g.files}
    return None


def fleet_coverage_curve(histories: dict[str, list], coverage_end: float | None):
    """(robot time s from the fleet's first row, total distance m, coverage) arrays from the
    members' explorer histories (rows t, explored_m2, frontier_size, distance_m; t is the
    simulated time all members share). The fleet's explored area at t is the largest any member
    reported up to t (they count the same shared graph); its distance at t the sum of each
    member's last distance up to t. Rescaled as a single robot's (exploration.py's
    `coverage_curve`): the last value equals the ground-truth coverage. Empty arrays when there
    is no history or no end to rescale to."""
    hs = [np.asarray(h or [], float).reshape(-1, 4) for h in histories.values()]
    hs = [h[np.argsort(h[:, 0], kind="stable")] for h in hs if len(h)]
    empty = np.zeros(0)
    if not hs or coverage_end is None:
        return empty, empty, empty
    t = np.unique(np.concatenate([h[:, 0] for h in hs]))
    explored, distance = np.zeros(len(t)), np.zeros(len(t))
    for h in hs:
        k = np.searchsorted(h[:, 0], t, side="right") - 1  # the member's last row up to t
        seen = k >= 0
        explored[seen] = np.maximum(explored[seen], np.maximum.accumulate(h[:, 1])[k[seen]])
        distance[seen] += h[k[seen], 3]
    if not explored[-1] > 0:
        return empty, empty, empty
    cov = np.clip(explored / explored[-1] * coverage_end, 0.0, 1.0)
    return t - t[0], distance, cov


def first_reach(x: np.ndarray, cov: np.ndarray, target: float = COVERAGE_TARGET) -> float | None:
    """x at the first row where coverage reaches `target`; None (censored) if it never does."""
    hit = np.nonzero(np.asarray(cov) >= target)[0]
    return float(x[hit[0]]) if len(hit) else None


def observed_cells(points: np.ndarray, voxel_m: float, cell_xy: np.ndarray) -> np.ndarray:
    """Mask of the raster cells (centres `cell_xy` (nx, ny, 2)) that lie in a map column holding
    one of `points` (voxel centres of a map of resolution `voxel_m`): whatever the raster's and
    the map's resolutions, each cell reads the one voxel column over its centre."""
    if not len(points):
        return np.zeros(cell_xy.shape[:2], bool)

    def code(ij):  # one int64 per column
        return (ij[..., 0].astype(np.int64) << 32) + ij[..., 1].astype(np.int64)

    cols = np.unique(code(np.floor(np.asarray(points)[:, :2] / voxel_m)))
    # a cell centre on a column's border reads the same column for every member
    return np.isin(code(np.floor(cell_xy / voxel_m + 1e-6)), cols)


def observed_voxels(semantic_map):
    """Every voxel the map observed, free ones too (`SemanticMap.observed_voxels`); a map class
    without that method (before the fleet mapper) gives its occupied voxels."""
    get = getattr(semantic_map, "observed_voxels", None) or semantic_map.occupied_voxels
    return get()


def map_overlap(observed: dict[str, np.ndarray], reach: np.ndarray, cell_area_m2: float) -> dict:
    """The share of the explored reachable area that more than one member observed: reachable
    cells observed by >= 2 members over those observed by >= 1 (None when none were)."""
    count = np.zeros(reach.shape, np.int32)
    for mask in observed.values():
        count += mask & reach
    n1, n2 = int((count >= 1).sum()), int((count >= 2).sum())
    return {
        "overlap": n2 / n1 if n1 else None,
        "observed_reachable_area_m2": n1 * cell_area_m2,
        "observed_by_several_m2": n2 * cell_area_m2,
        "observed_share_per_member": {
            r: float((m & reach).sum() / reach.sum()) if reach.any() else None
            for r, m in observed.items()
        },
    }


MAP_SCORES = ("n_points", "reconstruction_error_mean_m", "classification_ratio")


def fleet_metrics(run_dir: Path, config, world, gt=None, names=None) -> dict:
    """The "fleet" section of metrics.json: per member (distance, goals, times, world
    collisions), robot-robot contacts and separation (`sim.json`), the merged coverage, the
    overlap of the members' maps, time and total distance to 95 % coverage, and the merged map's
    scores beside each member's own map's. `gt`: the ground-truth (points, labels), `world`:
    None without ground truth (then only what needs none)."""
    from smana.services.mapper.semantic_map import SemanticMap

    run_dir = Path(run_dir)
    robots = list(config.fleet.robots)
    radius = config.navgraph.robot_radius_m
    sim = _load_json(run_dir / SIM_SUMMARY)
    graph = fleet_graph(run_dir, robots)
    obstacle = ev.collision_raster(world, ev.robot_height_m()) if world is not None else None
    members, trajectories, histories = {}, {}, {}
    for r in robots:
        d = member_dir(run_dir, r)
        state = _load_json(d / "explorer" / "state.json")
        traj, source = _trajectory(d)
        trajectories[r] = traj
        m: dict = {"state": state is not None, "trajectory_source": source}
        if world is not None and len(traj) >= 2:
            ex = exploration_metrics(world, None, traj, config, obstacle)
            for k in ("distance_m", "collisions", "collision_time_s", "min_clearance_m"):
                m[k] = ex.get(k)
            m["close_calls"] = ex.get("close_calls")
            m["terrain_share"] = ex.get("terrain_share")
            m["robot_time_s"] = ex.get("duration_robot_s")
        elif len(traj) >= 2:
            m["distance_m"] = float(np.hypot(*np.diff(traj[:, 1:3], axis=0).T).sum())
            m["robot_time_s"] = float(traj[-1, 0] - traj[0, 0])
        if state is not None:
            for k in ("done_reason", "n_goals", "explored_m2", "path_queries", "path_ok"):
                m[k] = state.get(k)
            m["path_errors"] = state.get("path_errors")
            m["explorer_distance_m"] = state.get("distance_m")
            m["wall_time_s"] = state.get("wall_time_s")
            m.setdefault("robot_time_s", state.get("elapsed_s"))
            histories[r] = state.get("history") or []
        members[r] = m
    out: dict = {"name": config.fleet.name, "robots": robots, "members": members}
    # a real fleet (no simulator in the stack) has no sim.json to miss
    out["simulated"] = bool(config.deploy.sim.enabled)
    pairs = (sim or {}).get("min_separation_m") or {}
    out["sim"] = {
        "summary": SIM_SUMMARY if sim is not None else None,
        "robot_contacts": (sim or {}).get("robot_contacts") or {},
        "robot_contacts_total": (sim or {}).get("robot_contacts_total"),
        "min_separation_m": pairs,
        "min_separation_overall_m": min(pairs.values()) if pairs else None,
        "sim_time_s": (sim or {}).get("sim_time_s"),
    }
    dists = [m.get("distance_m", m.get("explorer_distance_m")) for m in members.values()]
    out["total_distance_m"] = float(sum(v for v in dists if v is not None))
    if world is not None:
        start = next((t for t in trajectories.values() if len(t)), np.zeros((0, 4)))
        trav, cell_xy, reach = reachable_area(world, start, radius)
        area = trav.resolution_m**2
        if graph is not None:
            out.update(ev.exploration_coverage(graph, cell_xy, reach, area))
        else:
            out.update(coverage=0.0, reachable_area_m2=float(reach.sum() * area))
            out.update(explored_reachable_area_m2=0.0, known_area_m2=0.0)
        observed = {}
        for r in robots:
            path = member_dir(run_dir, r) / "map.npz"
            if path.is_file():
                try:
                    own = SemanticMap.load(path, backend=config.mapper.backend)
                    observed[r] = observed_cells(
                        observed_voxels(own).centres, own.resolution_m, cell_xy
                    )
                except (OSError, ValueError) as exc:
                    log.warning("%s: %s", path, exc)
        out.update(map_overlap(observed, reach, area))
        out["maps_read"] = sorted(observed)
    t, dist, cov = fleet_coverage_curve(histories, out.get("coverage"))
    out["time_to_95_s"] = first_reach(t, cov)
    out["distance_to_95_m"] = first_reach(dist, cov)
    out["curve"] = {"t_s": t.tolist(), "distance_m": dist.tolist(), "coverage": cov.tolist()}
    if gt is not None:
        gp, gl = gt
        from scipy.spatial import cKDTree

        tree = cKDTree(gp)
        maps = {"merged": run_dir / "map.npz"}
        maps.update({r: member_dir(run_dir, r) / "map.npz" for r in robots})
        scores = {}
        for who, path in maps.items():
            if not path.is_file():
                scores[who] = None
                continue
            try:
                mp, ml = ev.load_labelled_cloud(path)
                full = ev.evaluate_map(mp, ml, gp, gl, names, gt_tree=tree)
                scores[who] = {k: full[k] for k in MAP_SCORES}
            except (OSError, ValueError) as exc:
                scores[who] = f"evaluation failed: {exc}"
        out["map"] = scores
    return out


def fleet_warnings(fleet: dict) -> list[str]:
    """What in a fleet's figures says it did not do its job: a robot-robot contact, a member
    whose explorer left no state or that did not move while the fleet fell short of 95 %
    coverage (and each member's explorer checks)."""
    out = []
    sim = fleet.get("sim") or {}
    total = sim.get("robot_contacts_total")
    if sim.get("summary") is None and fleet.get("simulated", True):
        out.append(f"the simulator left no {SIM_SUMMARY}: robot-robot contacts are unknown")
    elif total:
        pairs = ", ".join(f"{k} x{v}" for k, v in sorted(sim["robot_contacts"].items()) if v)
        out.append(f"{total} robot-robot contact(s) ({pairs or 'no pair named'})")
    # A member left nothing to do (the others saw its part: a small world, a spawn that sees it
    # all) may stay put: its standing still is a failure only when the fleet fell short.
    covered = (fleet.get("coverage") or 0.0) >= COVERAGE_TARGET
    for r, m in (fleet.get("members") or {}).items():
        ee = None
        if m.get("state"):
            ee = {k: m.get(k) for k in ("path_queries", "path_ok", "path_errors", "done_reason")}
        dist = m.get("distance_m", m.get("explorer_distance_m"))
        where = f"robots/{r}/explorer/state.json"
        for w in run_warnings({"explorer": ee, "exploration": {"distance_m": dist}}, True):
            idle = w.startswith("the robot did not move") and covered
            idle &= (ee or {}).get("done_reason") in ("no_view_worth_it", "no_frontier")
            if not idle:
                out.append(f"{r}: " + w.replace("explorer/state.json", where))
    return out


def fleet_exploration(fleet: dict) -> dict:
    """The run's "exploration" section for a fleet: the merged coverage, and the members'
    distances and collisions added (what the summary table shows of any run)."""
    members = fleet.get("members") or {}
    keys = ("coverage", "reachable_area_m2", "explored_reachable_area_m2", "known_area_m2")
    out = {k: fleet[k] for k in keys if k in fleet}
    out["distance_m"] = fleet.get("total_distance_m")
    for k in ("collisions", "close_calls"):
        vals = [m.get(k) for m in members.values() if m.get(k) is not None]
        if vals:
            out[k] = int(sum(vals))
    clear = [m["min_clearance_m"] for m in members.values() if m.get("min_clearance_m") is not None]
    if clear:
        out["min_clearance_m"] = min(clear)
    times = [m.get("robot_time_s") for m in members.values() if m.get("robot_time_s") is not None]
    if times:
        out["duration_robot_s"] = max(times)
    sources = sorted({m.get("trajectory_source") for m in members.values()} - {None})
    out["trajectory_source"] = ", ".join(sources) or "none"
    return out


def fleet_summary_rows(fleet: dict) -> list[tuple[str, str]]:
    """The fleet's lines of the summary table (from metrics.json's "fleet" section only)."""
    sim = fleet.get("sim") or {}
    robots = fleet.get("robots") or []
    n = len(robots)
    rows = [("fleet", f"{n} member{'s' if n != 1 else ''}: {', '.join(robots)}")]
    t95, d95 = fleet.get("time_to_95_s"), fleet.get("distance_to_95_m")
    rows.append(
        (
            f"to {100 * COVERAGE_TARGET:.0f} % coverage",
            "not reached"
            if t95 is None
            else f"{t95:.0f} s robot time, {_f(d95, '.1f', ' m')} total distance",
        )
    )
    rows.append(("overlap of the members' maps", _pct(fleet.get("overlap"))))
    contacts = sim.get("robot_contacts_total")
    rows.append(
        (
            "robot-robot contacts",
            f"{'-' if contacts is None else contacts} (minimum separation "
            f"{_f(sim.get('min_separation_overall_m'), '.2f', ' m')})",
        )
    )
    mp = fleet.get("map") or {}
    if isinstance(mp.get("merged"), dict):
        rows.append(("merged map", _map_scores(mp["merged"])))
    for r, m in (fleet.get("members") or {}).items():
        own = mp.get(r)
        rows.append(
            (
                f"{r}",
                f"{_f(m.get('distance_m', m.get('explorer_distance_m')), '.1f', ' m')}, "
                f"{m.get('n_goals', '-')} goals, {m.get('collisions', '-')} collisions, "
                f"{_f(m.get('robot_time_s'), '.0f', ' s')} robot time"
                + (f"; own map {_map_scores(own)}" if isinstance(own, dict) else ""),
            )
        )
    return rows


def _map_scores(s: dict) -> str:
    return (
        f"error {_f(s.get('reconstruction_error_mean_m'), '.3f', ' m')}, "
        f"classification {_f(s.get('classification_ratio'), '.3f')}"
    )


def _fleet_lines(fleet: dict) -> list[str]:
    """report.md's "Fleet" section."""
    sim = fleet.get("sim") or {}
    mp = fleet.get("map") or {}
    lines = [
        "## Fleet",
        "",
        f"Fleet `{fleet.get('name')}`: {len(fleet.get('robots') or [])} members sharing one map "
        "and one navigation graph. Coverage is the merged graph's, against ground truth; the "
        "overlap is the share of the explored reachable area observed by more than one member "
        "(a cell observed by a member: an occupied voxel in its column in that member's own "
        "map); time and total distance to 95 % are read off the fleet's coverage curve (the "
        "largest explored area any member had reported, rescaled to the ground truth at the "
        "end).",
        "",
        "| figure | value |",
        "|---|---|",
        (
            "| merged coverage of the reachable traversable area | "
            f"{_pct(fleet.get('coverage'))} of {_f(fleet.get('reachable_area_m2'), '.1f', ' m2')} |"
        ),
        f"| overlap | {_pct(fleet.get('overlap'))} |",
        f"| time to 95 % (robot time) | {_f(fleet.get('time_to_95_s'), '.0f', ' s')} |",
        f"| total distance to 95 % | {_f(fleet.get('distance_to_95_m'), '.1f', ' m')} |",
        f"| total distance | {_f(fleet.get('total_distance_m'), '.1f', ' m')} |",
        f"| robot-robot contacts | {sim.get('robot_contacts_total', '-')} |",
        f"| minimum separation | {_f(sim.get('min_separation_overall_m'), '.2f', ' m')} |",
        f"| simulated time | {_f(sim.get('sim_time_s'), '.0f', ' s')} |",
        "",
        "| member | distance (m) | goals | robot time (s) | wall time (s) | collisions | "
        "observed share | map error (m) | classification ratio | ended because |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    seen = fleet.get("observed_share_per_member") or {}
    for who in ["merged", *(fleet.get("members") or {})]:
        m = (fleet.get("members") or {}).get(who, {})
        s = mp.get(who) if isinstance(mp.get(who), dict) else {}
        lines.append(
            f"| {'merged map' if who == 'merged' else who} | "
            f"{_f(m.get('distance_m', m.get('explorer_distance_m')), '.1f')} | "
            f"{m.get('n_goals', '-')} | {_f(m.get('robot_time_s'), '.0f')} | "
            f"{_f(m.get('wall_time_s'), '.0f')} | {m.get('collisions', '-')} | "
            f"{_pct(seen.get(who))} | {_f(s.get('reconstruction_error_mean_m'), '.3f')} | "
            f"{_f(s.get('classification_ratio'), '.3f')} | {m.get('done_reason') or '-'} |"
        )
    pairs = sim.get("min_separation_m") or {}
    if pairs:
        lines += ["", "| pair | contacts | minimum separation (m) |", "|---|---|---|"]
        for k, v in sorted(pairs.items()):
            lines.append(f"| {k} | {(sim.get('robot_contacts') or {}).get(k, 0)} | {v:.2f} |")
    return lines + [""]


def _fleet_plots(
    run_dir: Path, classes, world, fleet_traj: dict, graph, fleet: dict
) -> dict[str, str]:
    """The ground truth and the shared graph with every member's trajectory in its own colour,
    and the fleet's coverage curve."""
    files = {}
    trajs = {r: t[:, 1:3] for r, t in fleet_traj.items() if len(t)}
    if world is not None:
        top = world.top_class()
        fig = plots.world_map(
            classes,
            top.data,
            top.origin_xy,
            top.resolution_m,
            "Ground truth from above, with each member's trajectory",
            trajectories=trajs,
        )
        files["fleet_map"] = str(plots.save(fig, run_dir / "plots" / "fleet_trajectories.png"))
    if graph is not None:
        fig = plots.graph_map(
            classes,
            graph["labels"],
            graph["flags"],
            graph["origin_xy"],
            float(graph["resolution_m"]),
            "The fleet's shared navigation graph at the end, with each member's trajectory",
            trajectories=trajs,
        )
        files["graph"] = str(plots.save(fig, run_dir / "plots" / "graph.png"))
    curve = fleet.get("curve") or {}
    if len(curve.get("t_s") or []) >= 2:
        fig = plots.line_plot(
            [
                plots.Series(
                    "fleet (rescaled to ground truth at the end)", curve["t_s"], curve["coverage"]
                ),
                plots.Series(
                    "95 %", [curve["t_s"][0], curve["t_s"][-1]], [0.95, 0.95], dashed=True
                ),
            ],
            "Coverage of the reachable traversable area, the fleet's",
            "robot time (s, simulated, shared by the members)",
            "coverage",
            ylim=(0.0, 1.02),
        )
        files["fleet_progress"] = str(plots.save(fig, run_dir / "plots" / "fleet_progress.png"))
    return {k: str(Path(v).relative_to(run_dir)) for k, v in files.items()}


def _pct(share) -> str:
    return _f(None if share is None else 100 * share, ".1f", " %")


def summary_rows(metrics: dict) -> list[tuple[str, str]]:
    """What happened in a run, as (figure, value) rows, from `metrics.json`'s values only: the one
    table `smana up` ends with in the terminal and that heads `report.md` (`summary_lines`,
    `render_markdown`). A figure the run did not measure is `-` (a replay has no ground truth)."""
    ex, ee = metrics.get("exploration") or {}, metrics.get("explorer") or {}
    rp, run = metrics.get("replay") or {}, metrics.get("run") or {}
    warnings = metrics.get("warnings") or []
    n = len(warnings)
    rows = [("outcome", f"FAILED ({n} warning{'s' * (n != 1)})" if warnings else "ok")]
    if metrics.get("fleet"):
        rows += fleet_summary_rows(metrics["fleet"])
    if metrics.get("ground_truth") == NO_SIMULATOR:
        rows.append(("ground truth", "none: the simulator was off"))
    if ex:
        area = ex.get("explored_reachable_area_m2")
        rows.append(
            (
                "explored area (against ground truth)",
                f"{_f(area, '.1f', ' m2')} = "
                f"{_pct(ex.get('coverage'))} of the reachable "
                f"{_f(ex.get('reachable_area_m2'), '.1f', ' m2')}",
            )
        )
    if ee:
        rows.append(
            ("explored area (explorer's own count)", _f(ee.get("explored_m2"), ".1f", " m2"))
        )
    distance = ex.get("distance_m", rp.get("distance_m", ee.get("distance_m")))
    rows.append(("distance travelled", _f(distance, ".1f", " m")))
    if ex:
        rows.append(
            (
                "collisions",
                f"{ex.get('collisions', '-')} ({ex.get('close_calls', '-')} close calls "
                f"under {CLOSE_CALL_M} m)",
            )
        )
    if ee:
        rows.append(
            (
                "path queries",
                f"{ee.get('path_queries') or 0} ({ee.get('path_ok') or 0} answered with a path)",
            )
        )
    if rp:
        rows.append(
            (
                "scans published / integrated",
                f"{rp.get('published', '-')} / {rp.get('acknowledged', '-')}",
            )
        )
    robot_s = ex.get("duration_robot_s", ee.get("elapsed_s", rp.get("duration_s")))
    wall_s = run.get("wall_time_s")  # the supervisor's, start to stop; else the explorer's
    wall_s = ee.get("wall_time_s") if wall_s is None else wall_s
    rows.append(
        ("duration", f"{_f(robot_s, '.0f', ' s')} robot time, {_f(wall_s, '.0f', ' s')} wall time")
    )
    mc = metrics.get("map_content")
    voxels = mc.get("n_points") if isinstance(mc, dict) else None
    rows.append(("map", f"{voxels} occupied voxels" if voxels is not None else "-"))
    # the explorer's reason, and what stopped the stack (`explorer finished`, `--duration`, ...)
    why = [w for w in (ee.get("done_reason"), run.get("ended")) if w]
    rows.append(("ended because", f"{why[0]} ({why[1]})" if len(why) == 2 else "".join(why) or "-"))
    rows.append(("run directory", str(metrics.get("run_dir", "-"))))
    return rows


def summary_lines(metrics: dict) -> list[str]:
    """The terminal's end of `smana up`: a headline (`smana up: ok` / `smana up: FAILED`), the
    `summary_rows` table, one line per warning."""
    warnings = metrics.get("warnings") or []
    rows = summary_rows(metrics)
    width = max(len(a) for a, _ in rows)
    lines = [f"smana up: {'FAILED' if warnings else 'ok'}"]
    lines += [f"  {a:<{width}}  {b}" for a, b in rows[1:]]
    lines += [f"  warning: {w}" for w in warnings]
    return lines


def write_report(
    run_dir: str | Path,
    config,
    replay: dict | None = None,
    warnings=(),
    explored: bool = False,
    ended: str = "",
    wall_time_s: float | None = None,
) -> Path:
    """Measure a finished run and write metrics.json, report.md and plots/; returns report.md.

    `replay` is the replay's summary (`RUN_DIR/replay.json`) when the run replayed a dataset: the
    report then describes the dataset instead of a simulated world, and measures nothing against
    ground truth (there is none). `warnings` are what the supervisor saw go wrong (services that
    never became ready, crash loops); `explored` says the run was an exploration, whose figures
    are checked too (`run_warnings`). Every warning heads report.md and is in metrics.json.
    `ended` (what stopped the stack) and `wall_time_s` (the run's, start to stop) are the
    supervisor's; re-writing a report keeps those of the metrics.json it replaces."""
    run_dir = Path(run_dir)
    t0 = time.perf_counter()
    previous = (_load_json(run_dir / "metrics.json") or {}).get("run") or {}
    classes = ClassTable.load(config.general.class_table)
    names = {i: c.name for i, c in classes.classes.items()}
    is_fleet = config.fleet.enabled and replay is None
    state = _load_json(run_dir / "explorer" / "state.json")
    traj, traj_source = _trajectory(run_dir)
    graph = _graph(run_dir)
    if graph is not None and not (run_dir / "graph.npz").exists():
        shutil.copy(run_dir / "explorer" / "graph.npz", run_dir / "graph.npz")
    if is_fleet:
        # a fleet's explorers and trajectories are its members' (robots/<r>/); the shared graph
        # is copied to <run>/graph.npz as a single robot's is
        graph = fleet_graph(run_dir, config.fleet.robots)
        if graph is not None:
            np.savez(run_dir / "graph.npz", **graph)
    metrics: dict = {
        "smana_version": smana_version(),
        "run_dir": str(run_dir),
        "run": {
            "ended": ended or previous.get("ended") or "",
            "wall_time_s": wall_time_s if wall_time_s is not None else previous.get("wall_time_s"),
        },
        "config": {
            "backend": config.mapper.backend,
            "map_resolution_m": config.mapper.resolution_m,
            "graph_resolution_m": config.navgraph.resolution_m,
            "world": config.sim.world,
            "seed": config.sim.seed,
            "label_noise": config.sim.noise,
            "pose_noise_xy_m": config.sim.pose_noise_xy_m,
            "pose_noise_yaw_rad": config.sim.pose_noise_yaw_rad,
            "class_costs": list(config.explorer.class_costs),
            "time_budget_s": config.explorer.time_budget_s,
        },
    }
    if state is not None:
        metrics["explorer"] = {
            k: state.get(k)
            for k in (
                "done_reason",
                "elapsed_s",
                "wall_time_s",
                "distance_m",
                "explored_m2",
                "n_goals",
                "n_plans",
                "n_blocked",
                "n_stuck",
                "path_queries",
                "path_ok",
                "path_errors",
            )
        }
        counts = {int(k): v for k, v in (state.get("label_counts") or {}).items()}
        metrics["explorer"]["map_label_share"] = ev.label_shares(
            np.repeat(list(counts), list(counts.values())), names
        )
    world = None
    if replay is not None:
        metrics["ground_truth"] = "none: a replayed dataset"
        metrics["replay"] = replay_metrics(replay, traj, traj_source)
        metrics["replay"]["trajectory_source"] = traj_source
        metrics["replay"]["poses_recorded"] = recorded_poses(run_dir)
        metrics["replay"]["recorder_stopped_cleanly"] = (run_dir / "recorder.json").is_file()
    elif not config.deploy.sim.enabled:
        # A real robot (or a ROS 2 one): the config's world was never simulated, so nothing is
        # scored against it.
        metrics["ground_truth"] = NO_SIMULATOR
    else:
        try:
            world = ev.world_from_config(config)
        except Exception as exc:  # a real robot or a missing world file: no ground truth
            metrics["ground_truth"] = f"unavailable: {exc}"
    gt = None  # (points, labels) of the ground truth, read once for every map of a fleet
    if is_fleet:
        if world is not None:
            try:
                gt = ev.gt_cloud_for_run(run_dir, config)
            except (OSError, ValueError) as exc:
                log.warning("gt.ply: %s", exc)
        metrics["fleet"] = fleet_metrics(run_dir, config, world, gt, names)
        metrics["exploration"] = fleet_exploration(metrics["fleet"])
    elif world is not None:
        metrics["exploration"] = exploration_metrics(world, graph, traj, config)
        metrics["exploration"]["trajectory_source"] = traj_source
    map_path = _final_map(run_dir, classes, fleet=is_fleet, backend=config.mapper.backend)
    if map_path is not None:
        try:
            metrics["map_content"] = map_content(map_path, names)
        except (OSError, ValueError) as exc:
            metrics["map_content"] = f"unreadable: {exc}"
    if map_path is not None and world is not None:
        try:
            mp, ml = ev.load_labelled_cloud(map_path)
            if gt is None:
                gt_path = run_dir / "gt.ply"
                if not gt_path.is_file():
                    world.export_ply(gt_path, 0.03)
                gt = ev.load_labelled_cloud(gt_path)
            gp, gl = gt
            metrics["map"] = ev.evaluate_map(mp, ml, gp, gl, names)
            metrics["map"]["file"] = str(map_path.relative_to(run_dir))
        except (OSError, ValueError) as exc:
            metrics["map"] = f"evaluation failed: {exc}"
    rrd = run_dir / "recording.rrd"
    metrics["files"] = {
        "recording": str(rrd.relative_to(run_dir)) if rrd.is_file() else None,
        "recording_bytes": rrd.stat().st_size if rrd.is_file() else 0,
        "map": str(map_path.relative_to(run_dir)) if map_path else None,
        "graph": "graph.npz" if (run_dir / "graph.npz").is_file() else None,
        "logs": sorted(str(p.relative_to(run_dir)) for p in (run_dir / "logs").glob("*.log")),
    }
    if is_fleet:
        fleet_traj = {r: _trajectory(member_dir(run_dir, r))[0] for r in config.fleet.robots}
        metrics["files"]["plots"] = _fleet_plots(
            run_dir, classes, world, fleet_traj, graph, metrics["fleet"]
        )
        metrics["warnings"] = list(warnings) + fleet_warnings(metrics["fleet"])
    else:
        metrics["files"]["plots"] = _plots(
            run_dir, classes, world, graph, traj, state, replay, metrics.get("exploration")
        )
        metrics["warnings"] = list(warnings) + run_warnings(metrics, explored)
    metrics["report_time_s"] = time.perf_counter() - t0
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=json_default))
    report = run_dir / "report.md"
    report.write_text(render_markdown(metrics))
    return report


NO_SIMULATOR = (
    "none: the simulator was off (a real robot), so nothing is scored against a simulated "
    "world; `smana eval map RUN_DIR --gt FILE` scores the map against a ground-truth cloud"
)

# Why the two explored areas differ (the explorer's is in its progress plot, the report's here).
EXPLORED_AREAS = (
    "Two explored areas, measuring different things: *against ground truth* counts the cells of "
    "the world the robot could reach (traversable, with its radius of clearance, connected to its "
    "start) whose node in the final graph is known; *the explorer's own count* "
    "(`explorer/state.json` `explored_m2`, its progress plot) counts the known nodes its graph "
    "calls traversable (a traversable class, no obstacle, outside the safety zone) when it last "
    "planned, reachable or not, in the robot's own (possibly "
    "noisy) frame, and misses what the map learned after that plan."
)


def _f(v, fmt=".2f", unit=""):
    return "-" if v is None else f"{format(v, fmt)}{unit}"


def render_markdown(m: dict) -> str:
    c = m["config"]
    rp = m.get("replay")
    lines = [f"# smana run: {Path(m['run_dir']).name}", ""]
    if m.get("warnings"):
        lines += ["## Warnings", "", "This run did not do its job:", ""]
        lines += [f"- {w}" for w in m["warnings"]]
        lines.append("")
    lines += ["## Summary", "", "| figure | value |", "|---|---|"]
    lines += [f"| {a} | {b} |" for a, b in summary_rows(m)]
    lines.append("")
    if rp:
        lines += [
            f"Replay of `{rp.get('dataset')}` ({rp.get('format')}, class table "
            f"`{rp.get('class_table')}`), map back-end `{c['backend']}` at "
            f"{c['map_resolution_m']} m, graph {c['graph_resolution_m']} m. No ground truth: the "
            "map is described, not measured.",
            "",
        ]
    elif m.get("ground_truth") == NO_SIMULATOR:
        lines += [
            f"Map back-end `{c['backend']}` at {c['map_resolution_m']} m, graph "
            f"{c['graph_resolution_m']} m. No ground truth: {NO_SIMULATOR[6:]}.",
            "",
        ]
    else:
        lines += [
            f"World `{c['world']}` seed {c['seed']}, map back-end `{c['backend']}` at "
            f"{c['map_resolution_m']} m, graph {c['graph_resolution_m']} m, label noise "
            f"`{c['label_noise']}`, pose noise {c['pose_noise_xy_m']} m / "
            f"{c['pose_noise_yaw_rad']} rad, class costs "
            f"{c['class_costs'] or 'from the class table'}.",
            "",
        ]
    if rp:
        lines += _replay_lines(rp)
    if m.get("fleet"):
        lines += _fleet_lines(m["fleet"])
    ex, ee = m.get("exploration") or {}, m.get("explorer") or {}
    if ex or ee:
        title = "## Exploration"
        if m.get("fleet"):
            title += " (the fleet: merged coverage, the members' figures added)"
        lines += [title, "", "| figure | value |", "|---|---|"]
        rows = [
            ("ended because", ee.get("done_reason") or "-"),
            (
                "wall time, the explorer's (the run's is in the summary)",
                _f(ee.get("wall_time_s"), ".0f", " s"),
            ),
            ("robot time", _f(ex.get("duration_robot_s"), ".0f", " s")),
            (
                "explored share of the reachable traversable area",
                _f(100 * ex["coverage"] if ex.get("coverage") is not None else None, ".1f", " %"),
            ),
            (
                "reachable traversable area (ground truth)",
                _f(ex.get("reachable_area_m2"), ".1f", " m2"),
            ),
            (
                "explored area, against ground truth (reachable traversable area under a known "
                "node of the final graph)",
                _f(ex.get("explored_reachable_area_m2"), ".1f", " m2"),
            ),
            (
                "explored area, the explorer's own count (known nodes its graph calls "
                "traversable, at its last plan)",
                _f(ee.get("explored_m2"), ".1f", " m2"),
            ),
            (
                "known graph area (every known node of the final graph, obstacles included)",
                _f(ex.get("known_area_m2"), ".1f", " m2"),
            ),
            ("distance travelled", _f(ex.get("distance_m"), ".1f", " m")),
            ("goals", str(ee.get("n_goals", "-"))),
            (
                "travelled nodes on terrain (vs grass, ground truth)",
                _f(
                    100 * ex["terrain_share"] if ex.get("terrain_share") is not None else None,
                    ".0f",
                    " %",
                ),
            ),
            ("minimum clearance from obstacles", _f(ex.get("min_clearance_m"), ".2f", " m")),
            (f"close calls (clearance < {CLOSE_CALL_M} m)", str(ex.get("close_calls", "-"))),
            ("collisions (footprint over an obstacle)", str(ex.get("collisions", "-"))),
            ("trajectory measured from", ex.get("trajectory_source", "-")),
        ]
        if m.get("fleet"):
            # a fleet's explorers are its members' (the Fleet section): only what was measured
            rows = [(a, b) for a, b in rows if b not in ("-", "None")]
        lines += [f"| {a} | {b} |" for a, b in rows]
        lines.append("")
        if ex and ee:
            lines += [EXPLORED_AREAS, ""]
    mp = m.get("map")
    if isinstance(mp, dict) and mp.get("n_points"):
        lines += [
            "## Map against ground truth",
            "",
            f"{mp['n_points']} map points (`{mp.get('file')}`): reconstruction error "
            f"{_f(mp['reconstruction_error_mean_m'], '.3f')} m mean, "
            f"{_f(mp['reconstruction_error_std_m'], '.3f')} m std; classification ratio "
            f"{_f(mp['classification_ratio'], '.3f')}.",
            "",
            "| class (map label) | points | error mean (m) | classification ratio |",
            "|---|---|---|---|",
        ]
        for name, s in mp["per_class"].items():
            lines.append(
                f"| {name} | {s['n_points']} | {_f(s['error_mean_m'], '.3f')} | "
                f"{_f(s['classification_ratio'], '.3f')} |"
            )
        lines.append("")
    elif mp:
        lines += ["## Map against ground truth", "", str(mp), ""]
    mc = m.get("map_content")
    if isinstance(mc, dict) and mc.get("n_points"):
        lines += [
            "## Map content",
            "",
            f"{mc['n_points']} occupied voxels.",
            "",
            "| class | voxels | share |",
            "|---|---|---|",
        ]
        lines += [
            f"| {name} | {s['points']} | {100 * s['share']:.1f} % |"
            for name, s in mc["per_class"].items()
        ]
        lines.append("")
    files = m.get("files") or {}
    if files.get("plots"):
        lines += ["## Plots", ""]
        lines += [f"![{k}]({v})" for k, v in files["plots"].items()]
        lines.append("")
    lines += ["## Files", ""]
    lines.append(
        f"- Rerun recording: `{files.get('recording')}` "
        f"({files.get('recording_bytes', 0) / 1e6:.1f} MB; `smana view {m['run_dir']}`)"
    )
    lines.append(f"- final map: `{files.get('map')}`, graph: `{files.get('graph')}`")
    lines.append(
        "- config used: `config.toml`; logs: " + ", ".join(f"`{p}`" for p in files.get("logs", []))
    )
    return "\n".join(lines) + "\n"


def _replay_lines(rp: dict) -> list[str]:
    lat = rp.get("latency") or {}
    rate = rp.get("recorded_rate_hz")
    lockstep = rp.get("mode") == "lockstep"
    mode = rp.get("mode", "-")
    if mode == "realtime" and rp.get("rate_factor"):
        mode += f" x{rp['rate_factor']:g}"
    kept = rp.get("points_kept_share")
    kept = None if kept is None else 100 * kept
    if lockstep:  # nothing may be lost: a loss is a failure (and a warning above)
        losses = (
            "lost (no MapDelta after 3 resends) / resent",
            f"{rp.get('lost', '-')} / {rp.get('resends', '-')}",
        )
    else:  # the mapper keeps the newest scan only: what it cannot keep up with, it drops
        losses = (
            "not integrated: overtaken by a newer scan / unacknowledged",
            f"{rp.get('overtaken', '-')} / {rp.get('unacknowledged', '-')}",
        )
    recorded = rp.get("poses_recorded")
    rows = [
        ("mode", mode),
        ("recorded rate", _f(rate, ".1f", " Hz")),
        ("scans in the dataset (readable)", str(rp.get("scans", "-"))),
        ("skipped by the reader", str(len(rp.get("skipped_by_reader") or []))),
        ("published / integrated", f"{rp.get('published', '-')} / {rp.get('acknowledged', '-')}"),
        (
            "empty after filtering / unreadable",
            f"{rp.get('empty', '-')} / {len(rp.get('read_errors') or [])}",
        ),
        losses,
        (
            "late: published / integrated",
            f"{rp.get('late_published', '-')} / {rp.get('late_integrated', '-')}",
        ),
        (
            "integration latency mean / p95 / max",
            f"{_f(lat.get('mean_ms'), '.0f')} / {_f(lat.get('p95_ms'), '.0f')} / "
            f"{_f(lat.get('max_ms'), '.0f')} ms",
        ),
        ("latency per point (mean scan)", _f(rp.get("latency_per_point_us"), ".2f", " us")),
        (
            "points kept",
            f"{rp.get('points_published', '-')} of {rp.get('points_in', '-')} "
            f"({_f(kept, '.0f', ' %')})",
        ),
        (
            "dropped: out of range / ignored class / non-finite",
            f"{rp.get('points_out_of_range', '-')} / {rp.get('points_ignored_class', '-')} / "
            f"{rp.get('points_nonfinite', '-')}",
        ),
        ("throughput", _f(rp.get("scans_per_s"), ".1f", " scans/s")),
        (
            "poses published / recorded by the recorder",
            f"{rp.get('poses_published', '-')} / {'no recorder' if recorded is None else recorded}",
        ),
        (
            "distance covered by the poses",
            _f(rp.get("distance_m"), ".2f", " m")
            + (f" (measured on {rp['distance_source']})" if rp.get("distance_source") else ""),
        ),
    ]
    lines = [
        "## Replay",
        "",
        "| figure | value |",
        "|---|---|",
        *[f"| {a} | {b} |" for a, b in rows],
        "",
    ]
    if not lockstep and rp.get("overtaken"):
        lines += [
            f"Realtime: {rp['overtaken']} of the {rp.get('published', '-')} scans were "
            "overtaken by a newer one before the mapper integrated them: dropped as stale "
            "by its latest-wins input (or on the way, by the link's DROP congestion "
            "control), as on a robot whose mapper is slower than its sensor. Not a failure "
            "of the replay: `--lockstep` integrates every scan.",
            "",
        ]
    return lines


def cli(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="smana report", description="(Re)write a run's report.")
    p.add_argument("run_dir", type=Path)
    args = p.parse_args(argv)
    config = ev.load_run_config(args.run_dir)
    path = write_report(args.run_dir, config)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(cli())
