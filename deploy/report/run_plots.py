"""A run's plots (plots/*.png), drawn through common/plotting.py: the ground truth with the
trajectory, the navigation graph, the exploration progress, a replay's latency per scan; a fleet's
with each member's trajectory and its coverage curve."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smana.common import plotting
from smana.common.classes import ClassTable


def run_plots(
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
        files[name] = str(plotting.save(fig, out_dir / f"{PLOT_FILES[name]}").relative_to(run_dir))

    if world is not None:
        top = world.top_class()
        put(
            "map",
            plotting.world_map(
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
            plotting.graph_map(
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
            plotting.progress_plot(
                hist[:, 0] - hist[0, 0],
                hist[:, 1],
                hist[:, 3],
                (exploration or {}).get("usable_area_m2"),
            ),
        )
    rows = [r for r in (replay or {}).get("per_scan") or [] if r[5] is not None]
    if len(rows) >= 2:
        put(
            "replay_latency",
            plotting.line_plot(
                [
                    plotting.Series(
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


def fleet_plots(
    run_dir: Path, classes, world, fleet_traj: dict, graph, fleet: dict
) -> dict[str, str]:
    """The ground truth and the shared graph with every member's trajectory in its own colour,
    and the fleet's coverage curve."""
    files = {}
    trajs = {r: t[:, 1:3] for r, t in fleet_traj.items() if len(t)}
    if world is not None:
        top = world.top_class()
        fig = plotting.world_map(
            classes,
            top.data,
            top.origin_xy,
            top.resolution_m,
            "Ground truth from above, with each member's trajectory",
            trajectories=trajs,
        )
        files["fleet_map"] = str(plotting.save(fig, run_dir / "plots" / "fleet_trajectories.png"))
    if graph is not None:
        fig = plotting.graph_map(
            classes,
            graph["labels"],
            graph["flags"],
            graph["origin_xy"],
            float(graph["resolution_m"]),
            "The fleet's shared navigation graph at the end, with each member's trajectory",
            trajectories=trajs,
        )
        files["graph"] = str(plotting.save(fig, run_dir / "plots" / "graph.png"))
    curve = fleet.get("curve") or {}
    if len(curve.get("t_s") or []) >= 2:
        fig = plotting.line_plot(
            [
                plotting.Series(
                    "fleet (rescaled to ground truth at the end)", curve["t_s"], curve["coverage"]
                ),
                plotting.Series(
                    "95 %", [curve["t_s"][0], curve["t_s"][-1]], [0.95, 0.95], dashed=True
                ),
            ],
            "Coverage of the reachable traversable area, the fleet's",
            "robot time (s, simulated, shared by the members)",
            "coverage",
            ylim=(0.0, 1.02),
        )
        files["fleet_progress"] = str(plotting.save(fig, run_dir / "plots" / "fleet_progress.png"))
    return {k: str(Path(v).relative_to(run_dir)) for k, v in files.items()}
