"""`write_report(run_dir, config)`: measure a finished run and write metrics.json, report.md and
plots/ (see the package's docstring for what it reads)."""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from smana.common.classes import ClassTable
from smana.common.messages import json_default
from smana.common.version import smana_version
from smana.deploy.report import ground_truth as ev
from smana.deploy.report.checks import fleet_warnings, run_warnings
from smana.deploy.report.fleet import fleet_exploration, fleet_graph, fleet_metrics
from smana.deploy.report.measures import (
    NO_SIMULATOR,
    exploration_metrics,
    final_map,
    load_graph,
    load_json,
    load_trajectory,
    map_content,
    member_dir,
    recorded_poses,
    replay_metrics,
)
from smana.deploy.report.render import render_markdown
from smana.deploy.report.run_plots import fleet_plots, run_plots

log = logging.getLogger("smana.report")


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
    previous = (load_json(run_dir / "metrics.json") or {}).get("run") or {}
    classes = ClassTable.load(config.general.class_table)
    names = {i: c.name for i, c in classes.classes.items()}
    is_fleet = config.fleet.enabled and replay is None
    state = load_json(run_dir / "explorer" / "state.json")
    traj, traj_source = load_trajectory(run_dir)
    graph = load_graph(run_dir)
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
                "n_turns_avoided",
                "guard",
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
    map_path = final_map(run_dir, classes, fleet=is_fleet, backend=config.mapper.backend)
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
        fleet_traj = {r: load_trajectory(member_dir(run_dir, r))[0] for r in config.fleet.robots}
        metrics["files"]["plots"] = fleet_plots(
            run_dir, classes, world, fleet_traj, graph, metrics["fleet"]
        )
        metrics["warnings"] = list(warnings) + fleet_warnings(metrics["fleet"])
    else:
        metrics["files"]["plots"] = run_plots(
            run_dir, classes, world, graph, traj, state, replay, metrics.get("exploration")
        )
        metrics["warnings"] = list(warnings) + run_warnings(metrics, explored)
    metrics["report_time_s"] = time.perf_counter() - t0
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=json_default))
    report = run_dir / "report.md"
    report.write_text(render_markdown(metrics))
    return report
