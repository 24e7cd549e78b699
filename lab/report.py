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


def _final_map(run_dir: Path, classes: ClassTable) -> Path | None:
    """The run's map as PLY (exported from a saved .npz map when only that exists)."""
    try:
        return ev.find_map(run_dir)
    except FileNotFoundError:
        pass
    maps = [
        p for p in run_dir.rglob("*.npz") if "explorer" not in p.parts and p.name != "graph.npz"
    ]
    for path in sorted(maps, key=lambda p: p.stat().st_mtime, reverse=True):
        try:
            from smana.services.mapper.semantic_map import SemanticMap

            SemanticMap.load(path).export_ply(run_dir / "map.ply", classes)
            return run_dir / "map.ply"
        except Exception as exc:  # not a map file
            log.debug("%s is not a saved map: %s", path, exc)
    return None


def exploration_metrics(world, graph: dict | None, traj: np.ndarray, config) -> dict:
    """Coverage, travelled labels and clearance of a run, against the world's ground truth."""
    classes = world.classes
    top = world.top_class()
    res = top.resolution_m
    radius = config.navgraph.robot_radius_m
    trav = world.traversability(radius)
    xs, ys = trav.cell_centres()
    cell_xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    start = traj[0, 1:3] if len(traj) else np.array(world.spawn_pose(radius)[:2])
    si, sj = trav.index_of(start[0], start[1])
    reach = ev.reachable_traversable(trav.data, (int(si), int(sj)))
    out: dict = {"robot_radius_m": radius}
    if not reach.any():
        # the start cell itself may sit inside the clearance margin: take the nearest reachable
        d = np.where(
            trav.data, np.hypot(cell_xy[..., 0] - start[0], cell_xy[..., 1] - start[1]), np.inf
        )
        i, j = np.unravel_index(np.argmin(d), d.shape)
        reach = ev.reachable_traversable(trav.data, (int(i), int(j)))
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
        out["travelled_label_share"] = ev.label_shares(gt_labels, names)
        # what the robot's body can hit: objects up to its height (it passes under tree crowns)
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
    state = _load_json(run_dir / "explorer" / "state.json")
    traj, traj_source = _trajectory(run_dir)
    graph = _graph(run_dir)
    if graph is not None and not (run_dir / "graph.npz").exists():
        shutil.copy(run_dir / "explorer" / "graph.npz", run_dir / "graph.npz")
    metrics: dict = {
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
    else:
        try:
            world = ev.world_from_config(config)
        except Exception as exc:  # a real robot or a missing world file: no ground truth
            metrics["ground_truth"] = f"unavailable: {exc}"
    if world is not None:
        metrics["exploration"] = exploration_metrics(world, graph, traj, config)
        metrics["exploration"]["trajectory_source"] = traj_source
    map_path = _final_map(run_dir, classes)
    if map_path is not None:
        try:
            metrics["map_content"] = map_content(map_path, names)
        except (OSError, ValueError) as exc:
            metrics["map_content"] = f"unreadable: {exc}"
    if map_path is not None and world is not None:
        try:
            mp, ml = ev.load_labelled_cloud(map_path)
            gt = run_dir / "gt.ply"
            if not gt.is_file():
                world.export_ply(gt, 0.03)
            gp, gl = ev.load_labelled_cloud(gt)
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
    metrics["files"]["plots"] = _plots(
        run_dir, classes, world, graph, traj, state, replay, metrics.get("exploration")
    )
    metrics["warnings"] = list(warnings) + run_warnings(metrics, explored)
    metrics["report_time_s"] = time.perf_counter() - t0
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=json_default))
    report = run_dir / "report.md"
    report.write_text(render_markdown(metrics))
    return report


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
    ex, ee = m.get("exploration") or {}, m.get("explorer") or {}
    if ex or ee:
        lines += ["## Exploration", "", "| figure | value |", "|---|---|"]
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
