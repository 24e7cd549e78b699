"""The run report `smana up` writes at the end: `metrics.json`, `report.md` and PNG plots.

`write_report(run_dir, config)` reads what the services left in the run directory:
- `explorer/state.json`, `explorer/trajectory.csv`, `explorer/graph.npz` (the explorer's copy of
  the navigation graph, saved on shutdown);
- the mapper's final map (`map.ply`, or a saved `.npz` map that is exported to `map.ply`);
- `recording.rrd`, `recorder.json`, `trajectory_{pose,truth}.csv` (the Rerun recorder) and `logs/`;
- for a replayed dataset, `replay.json` (passed in) and `replay_trajectory.csv` (every pose the
  replay published);
and measures the run against the simulated world's ground truth (rebuilt from the config):
usable coverage (the share of the reachable traversable area the final graph knows as
traversable), the false-obstacle and false-free areas, travelled labels (terrain vs grass),
clearance from obstacles along the trajectory, and the map's reconstruction error and
classification ratio.

A fleet's run (`fleet.robots` set) is laid out per member instead: `robots/<r>/map.npz` (the
member's own map), `robots/<r>/explorer/{state.json,trajectory.csv,graph.npz}`,
`robots/<r>/trajectory_{pose,truth}.csv`, beside the merged `map.npz` and the simulator's
`sim.json` (robot-robot contacts, separations). Its report adds a "fleet" section
(`fleet_metrics`): per member, contacts, merged coverage, the overlap of the members' maps, time
and total distance to 95 % coverage, the merged map's scores beside each member's own map's; and
its warnings (`fleet_warnings`): a contact, under half the reachable area usable, a member
without state or that did not move.

Also a command: `python -m smana.deploy.report RUN_DIR` re-writes the report of a finished run.

The package is the product's (no import of `smana.lab`): `measures` (one robot's figures),
`ground_truth` (the paper's measures against the simulated world), `fleet`, `checks` (the
warnings), `render` (report.md and the terminal summary), `run_plots` (plots/, through
common/plotting.py), `write` (`write_report`) and `finish` (the end of `smana up` and
`smana replay --run`: the report, the summary, the exit status).
"""

from __future__ import annotations

import importlib

# What the package offers, by module: imported on first use, so that `smana up` starts without
# loading scipy (deploy/supervisor.py imports `finish` when it starts, the rest at the end).
_WHERE = {
    "CLOSE_CALL_M": "measures",
    "COVERAGE_TARGET": "measures",
    "EXPLORED_AREAS": "render",
    "FLEET_DIR": "measures",
    "MAP_SCORES": "fleet",
    "MOVED_M": "measures",
    "NO_SIMULATOR": "measures",
    "OUTCOME_WARNINGS": "checks",
    "PLOT_FILES": "run_plots",
    "RECORDED_POSES": "measures",
    "REPLAY_TRAJECTORY": "measures",
    "SIM_SUMMARY": "measures",
    "USABLE_FLOOR": "measures",
    "exploration_metrics": "measures",
    "first_reach": "fleet",
    "fleet_coverage_curve": "fleet",
    "fleet_exploration": "fleet",
    "fleet_graph": "fleet",
    "fleet_metrics": "fleet",
    "fleet_warnings": "checks",
    "map_content": "measures",
    "map_overlap": "fleet",
    "member_dir": "measures",
    "observed_cells": "fleet",
    "observed_voxels": "fleet",
    "reachable_area": "measures",
    "recorded_poses": "measures",
    "render_markdown": "render",
    "replay_metrics": "measures",
    "replay_warnings": "checks",
    "run_warnings": "checks",
    "summary_lines": "render",
    "summary_rows": "render",
    "usable_warnings": "checks",
    "write_report": "write",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
