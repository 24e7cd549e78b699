"""End to end, a fleet: `smana up --robots 2` on a small garden, every service its own process on
an isolated loopback router (one simulator for both robots, a mapper, planner and explorer each,
the fleet mapper, its navigation graph, the coordinator, one recorder), then the run directory:
both robots explored on the shared graph and never touched, the merged map holds what each
robot's own map holds, the report has its fleet section and the recording every robot."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from smana.common.zenoh_config import free_loopback_port
from tests.test_e2e_explore import BUDGET_S, small_run_overrides

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


def test_two_robots_share_one_map(tmp_path):
    run_dir = tmp_path / "run"
    sets = [s for s in small_run_overrides(free_loopback_port()) if "general.robot" not in s]
    sets = [s for s in sets if "publish_images" not in s]
    argv = [sys.executable, "-m", "smana.deploy.cli", "up", "--robots", "2"]
    # the explorers' budget is robot time: on a loaded machine the simulator runs well under
    # real time, so the wall-time cap leaves it room (the run ends when both explorers are done)
    argv += ["--run-dir", str(run_dir), "--duration", str(BUDGET_S + 300)]
    for s in sets:
        argv += ["--set", s]
    done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    logs = {p.name: p.read_text(errors="replace")[-2000:] for p in (run_dir / "logs").glob("*")}
    assert done.returncode == 0, (done.stdout[-3000:], logs)

    m = json.loads((run_dir / "metrics.json").read_text())
    fleet = m["fleet"]
    assert fleet["robots"] == ["r1", "r2"]
    assert fleet["sim"]["robot_contacts_total"] == 0
    assert fleet["coverage"] > 0.5, fleet
    for r in ("r1", "r2"):
        state = json.loads((run_dir / "robots" / r / "explorer" / "state.json").read_text())
        assert state["n_goals"] >= 1 and state["path_ok"] >= 1, (r, state)
        assert (run_dir / "robots" / r / "map.npz").is_file()
    # the merged map: both members' deltas reached it, and it holds every voxel each observed
    from smana.services.mapper.semantic_map import SemanticMap

    merged = SemanticMap.load(run_dir / "map.npz")

    def keys(m):
        return {tuple(k) for k in m.observed_voxels().keys.tolist()}

    own = [SemanticMap.load(run_dir / "robots" / r / "map.npz") for r in ("r1", "r2")]
    assert keys(own[0]) | keys(own[1]) <= keys(merged)
    rec = json.loads((run_dir / "recorder.json").read_text())
    assert all(rec["members"][r]["pose"] > 0 for r in ("r1", "r2")), rec
    assert (run_dir / "recording.rrd").stat().st_size > 0
    assert "smana up: ok" in done.stdout
