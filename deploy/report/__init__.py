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

Also a command: `python -m smana.deploy.report RUN_DIR` re-writes the report of a finished run.

The package is the product's (no import of `smana.lab`): `measures` (one robot's figures),
`ground_truth` (the paper's measures against the simulated world), `fleet`, `checks` (the
warnings), `render` (report.md and the terminal summary), `figures` (plots/, through
common/figures.py), `write` (`write_report`) and `finish` (the end of `smana up` and
`smana replay --run`: the report, the summary, the exit status).
"""

from smana.deploy.report.checks import fleet_warnings, replay_warnings, run_warnings
from smana.deploy.report.figures import PLOT_FILES
from smana.deploy.report.fleet import (
    MAP_SCORES,
    first_reach,
    fleet_coverage_curve,
    fleet_exploration,
    fleet_graph,
    fleet_metrics,
    map_overlap,
    observed_cells,
    observed_voxels,
)
from smana.deploy.report.measures import (
    CLOSE_CALL_M,
    COVERAGE_TARGET,
    FLEET_DIR,
    MOVED_M,
    NO_SIMULATOR,
    RECORDED_POSES,
    REPLAY_TRAJECTORY,
    SIM_SUMMARY,
    exploration_metrics,
    map_content,
    member_dir,
    reachable_area,
    recorded_poses,
    replay_metrics,
)
from smana.deploy.report.render import (
    EXPLORED_AREAS,
    render_markdown,
    summary_lines,
    summary_rows,
)
from smana.deploy.report.write import write_report

__all__ = [
    "CLOSE_CALL_M",
    "COVERAGE_TARGET",
    "EXPLORED_AREAS",
    "FLEET_DIR",
    "MAP_SCORES",
    "MOVED_M",
    "NO_SIMULATOR",
    "PLOT_FILES",
    "RECORDED_POSES",
    "REPLAY_TRAJECTORY",
    "SIM_SUMMARY",
    "exploration_metrics",
    "first_reach",
    "fleet_coverage_curve",
    "fleet_exploration",
    "fleet_graph",
    "fleet_metrics",
    "fleet_warnings",
    "map_content",
    "map_overlap",
    "member_dir",
    "observed_cells",
    "observed_voxels",
    "reachable_area",
    "recorded_poses",
    "render_markdown",
    "replay_metrics",
    "replay_warnings",
    "run_warnings",
    "summary_lines",
    "summary_rows",
    "write_report",
]
