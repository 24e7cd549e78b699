"""The run's report is the product's: nothing under common/, services/ or deploy/ imports the
research harness (lab/), a report is written with lab/ absent, and the end of a run, shared by
`smana up` and `smana replay --run` (deploy/report/finish.py), gives the exit status the run
earned."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from smana.common.config import SmanaConfig
from smana.deploy.report.finish import finish
from tests.test_eval_report import run  # noqa: F401 - the fixture: a small hand-made run
from tests.test_replay_report import N, summary, write_poses

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("common", "services", "deploy")


def _lab_imports(path: Path, root: Path = ROOT) -> list[str]:
    """`file:line module` of each import of smana.lab (any form) in `path`."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [f"{node.module}.{a.name}" for a in node.names]
        lab = [n for n in names if n == "smana.lab" or n.startswith("smana.lab.")]
        out += [f"{path.relative_to(root)}:{node.lineno} {n}" for n in lab]
    return out


def test_the_product_imports_nothing_from_the_lab():
    files = [p for d in PRODUCT for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 50  # the scan found the product's sources
    found = [hit for p in files for hit in _lab_imports(p)]
    assert found == []


def test_the_lab_scan_finds_each_form_of_import(tmp_path):
    for line in (
        "from smana import lab",
        "from smana.lab import plots",
        "import smana.lab.report",
        "from smana.lab.evaluation import find_map",
    ):
        f = tmp_path / "probe.py"
        f.write_text(f"def f():\n    {line}\n")
        assert len(_lab_imports(f, tmp_path)) == 1, line


# A run's report written in a process where `import smana.lab` fails, as in an install without it.
NO_LAB = """
import importlib.abc, runpy, sys

class NoLab(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "smana.lab" or name.startswith("smana.lab."):
            raise ImportError(f"{name} is not installed")
        return None

sys.meta_path.insert(0, NoLab())
sys.argv = ["smana report", sys.argv[1]]
runpy.run_module("smana.deploy.report", run_name="__main__")
"""


def test_a_run_report_needs_no_lab(run):  # noqa: F811 - the fixture
    run_dir, _, _ = run
    out = subprocess.run(
        [sys.executable, "-c", NO_LAB, str(run_dir)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "# smana run:" in out.stdout  # report.md, printed
    m = json.loads((run_dir / "metrics.json").read_text())
    assert 0.3 < m["exploration"]["coverage"] < 0.7  # measured against ground truth
    assert m["map"]["n_points"] > 0
    assert set(m["files"]["plots"]) == {"map", "graph", "progress"}
    for rel in m["files"]["plots"].values():
        assert (run_dir / rel).stat().st_size > 1000


def _supervisor(run_dir: Path, cfg, warnings: list[str]):
    """What `finish` reads of a finished `Supervisor`."""
    return SimpleNamespace(
        run_dir=run_dir.resolve(),
        config=cfg,
        service_config=cfg,
        procs={},
        ended="replay finished",
        warnings=lambda: list(warnings),
    )


def _replay_cfg():
    return SmanaConfig.load(None, ["general.class_table=rellis3d", 'deploy.finish_with="replay"'])


def test_a_replay_caught_exiting_after_its_work_is_ok(tmp_path, capsys):
    cfg = _replay_cfg()
    (tmp_path / "replay.json").write_text(json.dumps(summary("lockstep")))
    write_poses(tmp_path / "replay_trajectory.csv", N)
    cut = "replay exited with status -9 and was not restarted (restart = never)"
    sup = _supervisor(tmp_path, cfg, [cut])
    assert finish(sup, tmp_path, 1, 3.0, "smana replay") == 0
    out = capsys.readouterr()
    assert "smana replay: ok" in out.out and "its exit was cut short" in out.err
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["warnings"] == [] and m["replay"]["published"] == N
    assert m["run"] == {"ended": "replay finished", "wall_time_s": 3.0}


def test_a_replay_that_did_not_finish_fails(tmp_path, capsys):
    sup = _supervisor(tmp_path, _replay_cfg(), [])
    assert finish(sup, tmp_path, 0, 3.0, "smana replay") == 1
    out = capsys.readouterr().out
    warning = "the replay did not finish (no replay.json; see logs/replay.log)"
    assert "smana replay: FAILED" in out and f"  warning: {warning}" in out
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert warning in m["warnings"]
    assert (tmp_path / "report.md").read_text().count(warning) == 1


def test_a_run_whose_supervisor_saw_a_failure_exits_1(run, capsys):  # noqa: F811 - the fixture
    run_dir, cfg, _ = run
    sup = _supervisor(run_dir, cfg, ["planner never became ready (see logs/planner.log)"])
    sup.ended = "explorer finished"
    assert finish(sup, run_dir, 0, 12.0) == 1
    out = capsys.readouterr().out
    assert "smana up: FAILED" in out and "  warning: planner never became ready" in out
    assert f"smana up: report written to {run_dir / 'report.md'}" in out


def test_replay_run_goes_through_smana_ups_path(tmp_path, monkeypatch):
    """`smana replay DATASET --run` hands its stack to `smana up`'s `main`: the replay is one of
    the stack's services (never restarted) and the run ends with it."""
    from smana.deploy import supervisor
    from smana.lab.data import synthetic as syn
    from smana.services.replay.__main__ import cli

    syn.write_rellis_sequence(tmp_path / "data", syn.SyntheticConfig(n_scans=2, beams=4, columns=8))
    seen = {}

    def main(config, duration_s=None, services=None, prog="smana up"):
        seen.update(config=config, duration_s=duration_s, services=services, prog=prog)
        return 0

    monkeypatch.setattr(supervisor, "main", main)
    run_dir = tmp_path / "run"
    assert cli([str(tmp_path / "data"), "--run", "--run-dir", str(run_dir)]) == 0
    stack = ["mapper", "navgraph", "planner"]
    assert seen["services"] in ([*stack, "recorder", "replay"], [*stack, "replay"])
    assert seen["prog"] == "smana replay" and seen["duration_s"] is None
    cfg = seen["config"]
    assert cfg.deploy.finish_with == "replay" and cfg.deploy.replay.restart == "never"
    assert cfg.general.run_dir == str(run_dir) and cfg.general.class_table == "rellis3d"
    assert cfg.mapper.inputs == ["scan"]
    assert cfg.replay.wait_for == seen["services"][:-1]  # the replay waits for the rest


def test_rewriting_the_report_of_no_run_is_one_line(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "smana.deploy.report", str(tmp_path / "nowhere")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [
        f"smana report: {tmp_path / 'nowhere'} is not a run directory"
    ]
