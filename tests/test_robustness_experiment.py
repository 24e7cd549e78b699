"""`smana experiment robustness`: its arms and seeds, its rules decided on synthetic rows, a
faked run's fields (a robot that did not move is a measured failure), the report's generated
section and claims, and (multi-process, slow) the quick form of the whole stack."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from smana.lab import experiments as exp
from smana.lab import stats
from smana.lab.experiments import exploration as ex
from smana.lab.experiments import report
from smana.lab.experiments import robustness as rb
from smana.lab.experiments import robustness_report as rr
from smana.lab.experiments.claims import verdict_claims


def _rows(high=0.95, realistic=0.85, seeds=rb.SEEDS, **over):
    """Synthetic measured rows: per seed a noise-free usable share, the noisy arms a share of it."""
    rows = []
    for c in rb.conditions():
        for s in seeds:
            base = 0.80 + 0.01 * (s % 3)
            share = {"high": high, "realistic": realistic}.get(c.perception, 0.97)
            share = 1.0 if c.perception == rb.CLEAN else share
            rows.append(
                {"seed": s, "arm": c.name, "backend": c.backend, "perception": c.perception,
                 "measured": True, "run_failed": False, "moved": True, "collisions": 0,
                 "exit_code": 0, "usable_share": base * share,
                 "false_obstacle_share": 0.1, "false_free_share": 0.001, "distance_m": 40.0,
                 "time_to_90_s": 150.0, "distance_to_90_m": 30.0, "done_reason": "time_budget",
                 **over}
            )  # fmt: skip
    return rows


def _row(rows, seed, arm):
    return next(r for r in rows if r["seed"] == seed and r["arm"] == arm)


def test_the_arms_seeds_and_noise_are_the_declared_ones():
    from smana.common.config import MapperConfig, SmanaConfig

    names = [c.name for c in rb.conditions()]
    assert rb.default_backend() == MapperConfig().backend == "octree-max"
    assert names == [
        "max_clean", "max_off", "max_medium", "max_high", "max_realistic", "bayes_high",
        "bayes_realistic", "tsdf_high", "tsdf_realistic",
    ]  # fmt: skip
    s = rb.experiment_config()
    assert [a.name for a in s.arms] == names and s.seeds == tuple(range(51, 61))
    assert 15 <= s.size_m <= 20 and s.jobs == 2 and s.budget_s == rb.BUDGET_S
    # no committed experiment of the docs uses these worlds
    for data in report.load_data(report.DATA_DIR).values():
        if data["experiment"] != "robustness":
            assert not {r.get("seed") for r in data["rows"]} & set(rb.SEEDS)
    for c in rb.conditions():
        cfg = SmanaConfig.load(overrides=[*ex.WORLD_SETS, *c.arm().all_sets, *s.extra])
        assert cfg.mapper.backend == c.backend
        noisy = c.perception != rb.CLEAN
        assert cfg.sim.noise == ("off" if not noisy else c.perception)
        assert cfg.sim.pose_noise_xy_m == (0.10 if noisy else 0.0)
        assert cfg.sim.pose_noise_yaw_rad == (0.02 if noisy else 0.0)
        assert cfg.sim.pose_drift_xy_m_per_sqrt_s == (0.01 if noisy else 0.0)
        assert cfg.sim.pose_drift_yaw_rad_per_sqrt_s == (0.002 if noisy else 0.0)
        # the graph's bounds cover the garden
        assert cfg.navgraph.bounds_max_xy[0] >= s.size_m / 2 + 1
    # each run's robot is named exp<pid>-s<seed>-<arm>, a key chunk of at most 32 characters
    from smana.common.keys import check_name

    for c in rb.conditions():
        check_name(f"exp{2**22}-s99-{c.name}")


def test_the_rules_count_seeds_and_every_run():
    met = {v["claim"].split(" at ")[1].split(" ")[0]: v for v in rr.verdicts(_rows())[:2]}
    assert met["high"]["verdict"] == met["realistic"]["verdict"] == "met"
    assert all(v["p"] is None and v["rule"] == "a count" for v in rr.verdicts(_rows()))
    # under the target in every seed: not met
    assert rr.verdicts(_rows(high=0.85))[0]["verdict"] == "not met"
    assert rr.verdicts(_rows(realistic=0.75))[1]["verdict"] == "not met"
    # one seed short is allowed (9 of 10), two are not
    rows = _rows()
    _row(rows, 51, "max_high")["collisions"] = 1
    assert rr.verdicts(rows)[0]["verdict"] == "met"
    assert "9 of 10 seeds (short: seeds 51)" in rr.verdicts(rows)[0]["smana"]
    _row(rows, 52, "max_high")["moved"] = False  # did not move: a failure, whatever
    assert rr.verdicts(rows)[0]["verdict"] == "not met"
    # a seed without its reference counts against; too few seeds to decide: inconclusive
    rows = [r for r in _rows() if not (r["seed"] in (51, 52) and r["perception"] == rb.CLEAN)]
    assert rr.verdicts(rows)[0]["verdict"] == "not met"
    assert rr.verdicts(_rows(seeds=(51,)))[0]["verdict"] == stats.INCONCLUSIVE
    # false free: every run of every arm under 1 %
    rows = _rows()
    assert rr.verdicts(rows)[2]["verdict"] == "met"
    _row(rows, 55, "tsdf_realistic")["false_free_share"] = 0.012
    assert rr.verdicts(rows)[2]["verdict"] == "not met"
    assert "largest 1.20 %" in rr.verdicts(rows)[2]["smana"]
    # a run without the measure cannot show it was under: inconclusive, never met
    rows = _rows()
    _row(rows, 55, "tsdf_realistic")["false_free_share"] = None
    assert rr.verdicts(rows)[2]["verdict"] == stats.INCONCLUSIVE
    assert "; 1 without the measure" in rr.verdicts(rows)[2]["smana"]
    # and no figure without a usable coverage to draw
    assert rr.figure([{**r, "usable_share": None} for r in rows], Path("unused.png")) is None


def _fake_run(run_dir, distance_m, exit_code_warnings):
    run_dir.mkdir(parents=True)
    exploration = {
        "distance_m": distance_m, "usable_share": 0.31, "usable_area_m2": 40.0,
        "false_obstacle_share": 0.5, "false_obstacle_area_m2": 64.0, "false_free_share": 0.0,
        "false_free_area_m2": 0.0, "reachable_area_m2": 128.0, "collisions": 0,
        "trajectory_source": "ground truth",
    }  # fmt: skip
    metrics = {"exploration": exploration, "explorer": {"done_reason": "closed_in",
               "explored_m2": 40.0}, "warnings": exit_code_warnings}  # fmt: skip
    (run_dir / "metrics.json").write_text(json.dumps(metrics))
    (run_dir / "explorer").mkdir()
    history = [[40.0, 10.0, 5, 100.0], [50.0, 30.0, 5, 200.0], [60.0, 40.0, 5, 300.0]]
    (run_dir / "explorer" / "state.json").write_text(json.dumps({"history": history}))
    (run_dir / "trajectory_truth.csv").write_text(
        "t_s,x_m,y_m,z_m,yaw_rad\n0.0,0,0,0,0\n45.0,0.03,0,0,0\n60.0,0.04,0,0,0\n"
    )


def test_a_robot_that_did_not_move_is_a_measured_failure(tmp_path):
    arm = rb.Condition("octree-max", "realistic").arm()
    run_dir = tmp_path / ex.run_name(51, arm)
    _fake_run(run_dir, 0.04, ["the robot did not move (0.04 m travelled)"])
    row = {"seed": 51, "arm": arm.name, "exit_code": 1, "ok": False, "distance_m": 0.04,
           "done_reason": "closed_in"}  # fmt: skip
    assert rb.finished(row, run_dir)  # kept: a result, not a gap
    assert row["measured"] and row["ok"] and row["run_failed"] and row["moved"] is False
    assert row["outcome_only"] and row["usable_share"] == 0.31  # its measured coverage
    assert row["false_obstacle_area_m2"] == 64.0 and row["reachable_area_m2"] == 128.0
    # 90 % of the final usable count (40 m2) first at the third plan: 20 s after the first;
    # the distance is the true one by then, not the noisy odometer's
    assert row["time_to_90_s"] == 20.0 and row["distance_to_90_m"] == pytest.approx(0.04)
    d = next(d for d in rr.summarise([row]) if d["arm"] == arm.name)
    assert (d["runs"], d["not_measured"], d["run_failed"], d["did_not_move"]) == (1, 0, 1, 1)
    assert d["closed_in"] == 1 and d["usable_share"].mean == 0.31
    # and it fails its seed under the rules
    ref = {**row, "perception": rb.CLEAN, "run_failed": False, "moved": True, "usable_share": 0.4}
    assert not rr.seed_passes(row, ref, 0.5)
    # a run that left no report is not measured: not kept, and listed
    lost = {"seed": 22, "arm": arm.name, "exit_code": -9, "ok": False}
    assert not rb.finished(lost, tmp_path / "nothing")
    assert lost["measured"] is False and lost["usable_share"] is None


def test_a_run_without_a_report_exits_1_and_a_rerun_keeps_the_measured_one(tmp_path, monkeypatch):
    calls = []

    def fake_run(out, seed, arm, s, spawn=None):
        calls.append(arm.name)
        if arm.name == "max_high":  # its robot stood still: FAILED, measured
            _fake_run(out / ex.run_name(seed, arm), 0.02, ["the robot did not move (0.02 m)"])
            return 1, ex.load_json(out / ex.run_name(seed, arm) / "metrics.json"), {}, 1.0, 30.0
        return -9, {}, {}, 1.0, 30.0  # killed before its report

    monkeypatch.setattr(ex, "exploration_run", fake_run)
    argv = ["robustness", "--quick", "--arms", "max_high,max_realistic", "--out", str(tmp_path)]
    assert exp.cli(argv) == 1
    text = (tmp_path / "robustness_summary.md").read_text()
    assert "**WARNING: 1 of 2 runs did not run to their report**" in text
    assert "seed51_max_realistic (exit -9)" in text
    assert "| octree-max | high labels + pose noise | 1 (0) |" in text  # FAILED, measured
    assert sorted(calls) == ["max_high", "max_realistic"]
    calls.clear()
    assert exp.cli(argv) == 1
    assert calls == ["max_realistic"]  # the measured run is kept, the lost one runs again


def test_outputs_data_file_and_resume_from_it(tmp_path):
    rows = _rows(seeds=(51, 52))
    s = rb.experiment_config()
    s.seeds = (51, 52)
    rr.write_outputs([dict(r, wall_time_s=300.0) for r in rows], s, tmp_path)
    data = json.loads((tmp_path / "data" / "robustness.json").read_text())
    assert data["experiment"] == "robustness" and len(data["rows"]) == len(rows)
    text = (tmp_path / "robustness_summary.md").read_text()
    assert "| octree-max | high labels + pose noise | 2 (0) |" in text
    assert "![robustness_usable_coverage](robustness_usable_coverage.png)" in text
    assert (tmp_path / "robustness_usable_coverage.png").stat().st_size > 10_000
    # the rows a data file holds are kept: nothing left to run
    kept = rb.rows_from_data(tmp_path / "data" / "robustness.json")
    assert {(r["seed"], r["arm"]) for r in kept} == {(r["seed"], r["arm"]) for r in rows}


def test_report_generates_the_section_and_its_claims(tmp_path):
    report.write_data(tmp_path, "robustness", _rows(), {"seeds": list(rb.SEEDS), "size_m": 16.0,
                      "budget_s": rb.BUDGET_S, "jobs": 2})  # fmt: skip
    all_data = report.load_data(tmp_path / "data")
    text = report.sections(all_data)["robustness"]
    assert "Generated from docs/experiments/data/robustness.json (garden 16 m, seeds 51 to 60" in (
        text
    )
    assert "| tsdf | realistic labels + pose noise | 10 (0) |" in text
    claims = [c for c in verdict_claims(all_data) if c["experiment"] == "robustness"]
    assert len(claims) == 3 and all(c["holm"] == "a count, not a test" for c in claims)
    assert "_No raw results of `smana experiment robustness`" in rr.section(None)


def test_bad_arms_or_set_is_one_line_and_exit_2(tmp_path, capsys):
    from smana.common.cli import run_command

    for argv in (["--arms", "max_nope"], ["--set", "sim.noise=loud"]):
        argv = ["robustness", "--quick", "--out", str(tmp_path / "no"), *argv]
        assert run_command("experiment", exp.cli, argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
    assert not (tmp_path / "no").exists()


@pytest.mark.multiprocess
@pytest.mark.slow
def test_robustness_quick_counts_a_robot_that_did_not_move_as_a_failure(tmp_path):
    # one 20 s run in the 6 m garden under realistic noise, its robot held still (a follower
    # and a creep speed of 1 mm/s): the run is measured, FAILED, did not move, and kept as such
    stall = ["explorer.follower.max_linear_mps=0.001", "explorer.creep_speed_mps=0.001"]
    argv = ["robustness", "--quick", "--out", str(tmp_path)]
    for item in stall:
        argv += ["--set", item]
    assert exp.cli(argv) == 0  # a measured failure is a result, not an error
    runs = json.loads((tmp_path / "robustness_results.json").read_text())["runs"]
    assert [r["arm"] for r in runs] == ["max_realistic"]
    (r,) = runs
    assert r["measured"] and r["exit_code"] == 1 and r["run_failed"], r
    assert r["moved"] is False and "did not move" in r["run_warnings"], r
    metrics = json.loads((tmp_path / "seed51_max_realistic" / "metrics.json").read_text())
    e = metrics["exploration"]
    assert r["usable_share"] == e.get("usable_share") and r["collisions"] == e["collisions"]
    assert r["reachable_area_m2"] == e["reachable_area_m2"] > 0
    cfg = (tmp_path / "seed51_max_realistic" / "config.toml").read_text()
    assert 'noise = "realistic"' in cfg and "pose_drift_xy_m_per_sqrt_s = 0.01" in cfg
    data = json.loads((tmp_path / "data" / "robustness_quick.json").read_text())
    assert data["experiment"] == "robustness" and len(data["rows"]) == 1
    text = (tmp_path / "robustness_summary.md").read_text()
    assert "**Quick run**: 1 seed of 20 s in a 6 m garden" in text and "WARNING" not in text
    assert "| octree-max | realistic labels + pose noise | 1 (0) |" in text
    # a rerun keeps the finished run: nothing runs again
    assert exp.cli(argv) == 0
    assert json.loads((tmp_path / "robustness_results.json").read_text())["runs"] == runs


def test_a_run_that_runs_again_starts_in_an_empty_folder(tmp_path):
    """An interrupted run's folder (its map autosave, journal and explorer state) is moved aside
    before the run runs again: the new run's services would resume from it otherwise (the
    robot back at its spawn inside the last run's map)."""
    from smana.lab.experiments.exploration import set_aside

    run = tmp_path / "seed53_max_clean"
    (run / "explorer").mkdir(parents=True)
    (run / "explorer" / "state.json").write_text("{}")
    (run / "map.npz").write_bytes(b"x")
    set_aside(run)
    assert not run.exists()
    assert (tmp_path / "seed53_max_clean.interrupted-1" / "explorer" / "state.json").exists()
    run.mkdir()
    set_aside(run)
    assert (tmp_path / "seed53_max_clean.interrupted-2").is_dir()
    set_aside(tmp_path / "never_ran")  # nothing there: nothing to do


def test_python_runs_the_stack_with_another_checkout_and_this_code_reports(tmp_path, monkeypatch):
    """`--python PATH`: each `smana up` runs with that interpreter (a baseline of older code),
    and the run's report is written again by this code's `smana.deploy.report`; a path that is
    no executable is refused in one line."""
    import resource
    import subprocess
    import sys
    import types

    from smana.common.cli import UsageError
    from smana.lab.experiments import exploration as ex
    from smana.lab.experiments import robustness as rb

    started, reported = [], []

    class FakeProc:
        pid = 4242

        def __init__(self, argv, **kw):
            started.append(argv)
            run_dir = Path(argv[argv.index("--run-dir") + 1])
            (run_dir / "metrics.json").write_text("{}")

    def fake_run(argv, **kw):
        reported.append(argv)
        return types.SimpleNamespace(returncode=0)

    usage = resource.getrusage(resource.RUSAGE_SELF)
    monkeypatch.setattr(subprocess, "Popen", FakeProc)
    monkeypatch.setattr(subprocess, "run", fake_run)
    monkeypatch.setattr(ex.os, "wait4", lambda pid, opt: (pid, 0, usage))
    s = rb.experiment_config()
    s.python = "/opt/baseline/.venv/bin/python"
    arm = s.arms[0]
    ex.exploration_run(tmp_path, 61, arm, s)
    assert started[0][0] == "/opt/baseline/.venv/bin/python"
    assert reported == [
        [
            sys.executable,
            "-m",
            "smana.deploy.report",
            str((tmp_path / ex.run_name(61, arm)).resolve()),
        ]
    ]
    s.python = ""
    ex.exploration_run(tmp_path, 62, arm, s)
    assert started[1][0] == sys.executable and len(reported) == 1
    args = types.SimpleNamespace(extra=[], arms=None, python=str(tmp_path / "nope"))
    with pytest.raises(UsageError, match="not an executable"):
        rb.check_args(args)
