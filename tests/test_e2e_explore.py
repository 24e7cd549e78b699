"""End to end: a short `smana up` on a small garden, every service a process on an isolated
loopback router, then the run directory is checked: the map grew, the explorer followed paths,
the robot moved without touching an obstacle, and the recording and metrics are readable."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from smana.common.zenoh_config import free_loopback_port

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
BUDGET_S = 30.0


def small_run_overrides(port: int, budget_s: float = BUDGET_S) -> list[str]:
    """A garden of 6 m, a small fast camera, a 10 cm map: a closed loop that fits a test."""
    return [
        f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
        # keys of its own: stray processes of an earlier stack that reach a reused port stay apart
        f'general.robot="e2e{os.getpid()}"',
        # no hot spares: a run this short would start five only to stop them (they are tested in
        # test_supervisor.py and test_resilience.py)
        "deploy.standby_delay_s=3600",
        "sim.garden.size_m=6.0",
        "sim.seed=3",
        "sim.camera.width=160",
        "sim.camera.height=160",
        "sim.camera.publish_images=true",
        "mapper.resolution_m=0.1",
        "mapper.autosave_period_s=5.0",
        "navgraph.bounds_min_xy=[-4.0, -4.0]",
        "navgraph.bounds_max_xy=[4.0, 4.0]",
        f"explorer.time_budget_s={budget_s}",
    ]


def run_stack(run_dir: Path, overrides: list[str], timeout_s: float) -> int:
    """What `smana up` does: the supervisor with the recorder, then the report."""
    from smana.common.config import SmanaConfig
    from smana.deploy.report import write_report
    from smana.deploy.supervisor import Supervisor
    from smana.services.recorder.service import recorder_argv

    cfg = SmanaConfig.load(None, [*overrides, f'general.run_dir="{run_dir}"'])
    sup = Supervisor(cfg, run_dir)
    if "recorder" not in sup.procs:  # until `smana up` starts it itself
        sup.add("recorder", recorder_argv(sup.config_path, cfg.general.robot))
    code = sup.run(duration_s=timeout_s)
    write_report(run_dir, sup.service_config)
    return code


def test_short_closed_loop_run(tmp_path):
    run_dir = tmp_path / "run"
    code = run_stack(run_dir, small_run_overrides(free_loopback_port()), BUDGET_S + 90)
    logs = {p.name: p.read_text(errors="replace")[-3000:] for p in (run_dir / "logs").glob("*")}
    assert code == 0, logs

    # every service logged, the config used is there
    for name in ("sim", "mapper", "navgraph", "planner", "explorer", "recorder"):
        assert (run_dir / "logs" / f"{name}.log").is_file(), (name, sorted(logs))
    assert (run_dir / "config.toml").is_file()

    # the explorer chose goals, asked the planner and drove
    state = json.loads((run_dir / "explorer" / "state.json").read_text())
    assert state["n_goals"] >= 1 and state["path_queries"] >= 1, state
    # one plan-log entry per goal set: the figure's goals and the report's count agree
    assert len(state["plans"]) == state["n_goals"], (len(state["plans"]), state["n_goals"])
    assert state["distance_m"] > 0.5, state
    assert state["explored_m2"] > 2.0, state

    m = json.loads((run_dir / "metrics.json").read_text())
    ex = m["exploration"]
    assert ex["trajectory_source"] == "ground truth"
    assert ex["collisions"] == 0, ex
    assert ex["coverage"] > 0.2, ex
    # the map grew and is close to the ground truth
    assert m["map"]["n_points"] > 500, m["map"]
    assert m["map"]["reconstruction_error_mean_m"] < 0.1
    assert m["map"]["classification_ratio"] > 0.7
    assert (run_dir / "map.ply").is_file() and (run_dir / "graph.npz").is_file()

    # the recording opens and holds the main streams
    from rerun.chunk import RrdReader

    rrd = run_dir / "recording.rrd"
    assert rrd.is_file() and rrd.stat().st_size > 10_000
    entities = {str(c.entity_path) for c in RrdReader(str(rrd)).stream().to_chunks()}
    for e in ("/world/robot", "/world/trajectory", "/world/graph/nodes", "/camera/rgb"):
        assert e in entities, sorted(entities)
    assert any(e.startswith("/world/map/") for e in entities)
    truth = np.loadtxt(run_dir / "trajectory_truth.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(truth) > 50
    assert (run_dir / "report.md").read_text().count("|") > 20
