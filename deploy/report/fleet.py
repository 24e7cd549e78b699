"""A fleet's run (`fleet.robots` set), laid out per member: `robots/<r>/map.npz` (the member's own
map), `robots/<r>/explorer/{state.json,trajectory.csv,graph.npz}`, `robots/<r>/trajectory_{pose,
truth}.csv`, beside the merged `map.npz` and the simulator's `sim.json` (robot-robot contacts,
separations). `fleet_metrics` is metrics.json's "fleet" section: per member, contacts, merged
coverage, the overlap of the members' maps, time and total distance to 95 % coverage, the merged
map's scores beside each member's own map's."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from smana.deploy.report import ground_truth as ev
from smana.deploy.report.measures import (
    COVERAGE_KEYS,
    COVERAGE_TARGET,
    KNOWN_CURVE,
    SIM_SUMMARY,
    drivable_nodes,
    exploration_metrics,
    load_json,
    load_trajectory,
    member_dir,
    reachable_area,
)

log = logging.getLogger("smana.report")


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
    `coverage_curve`): the last value equals `coverage_end`, the ground truth's known share.
    Empty arrays when there is no history or no end to rescale to."""
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
    sim = load_json(run_dir / SIM_SUMMARY)
    graph = fleet_graph(run_dir, robots)
    obstacle = ev.collision_raster(world, ev.robot_height_m()) if world is not None else None
    members, trajectories, histories = {}, {}, {}
    for r in robots:
        d = member_dir(run_dir, r)
        state = load_json(d / "explorer" / "state.json")
        traj, source = load_trajectory(d)
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
            lut, gt_obstacle = world.classes.traversable_lut, ev.gt_obstacle_cells(world)
            drove = [t[:, 1:3] for t in trajectories.values() if len(t)]
            drove_xy = np.concatenate(drove) if drove else np.zeros((0, 2))
            drivable = drivable_nodes(graph, lut, drove_xy, config)
            out.update(
                ev.exploration_coverage(graph, cell_xy, reach, area, lut, gt_obstacle, drivable)
            )
        else:
            out.update(ev.no_coverage(float(reach.sum() * area)))
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
    # the curve ends at the known share, any label (measures.py KNOWN_CURVE)
    t, dist, cov = fleet_coverage_curve(histories, out.get(KNOWN_CURVE))
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


def fleet_exploration(fleet: dict) -> dict:
    """The run's "exploration" section for a fleet: the merged coverage, and the members'
    distances and collisions added (what the summary table shows of any run)."""
    members = fleet.get("members") or {}
    out = {k: fleet[k] for k in COVERAGE_KEYS if k in fleet}
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
