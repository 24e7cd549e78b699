"""`smana experiment risk`, the closed loop (issue 29, item 4; lab/experiments/riskloop.py): its
arms, the ground-truth measures of a true path in the wet garden, its rules decided on synthetic
rows, its outputs and resuming from faked runs, the report's section and claims, and the quick
form end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.config import SmanaConfig
from smana.lab import stats
from smana.lab.experiments import cli, report
from smana.lab.experiments import exploration as ex
from smana.lab.experiments import riskloop as rl
from smana.lab.experiments.claims import verdict_claims


def test_the_arms_differ_only_in_noise_and_risk_and_their_config_loads():
    sets = {c.name: c.sets() for c in rl.CONDITIONS}
    assert list(sets) == ["clean", "expected", "cvar", "chance"]
    common = set.intersection(*(set(v) for v in sets.values()))
    assert 'mapper.backend="tsdf"' in common
    # the wet garden is the experiment's world (where the starts are drawn), not an arm's
    assert set(rl.WET_GARDEN) <= set(rl.experiment_config().extra)
    assert 'general.class_table="garden3drms_wet"' in rl.WET_GARDEN
    for name, items in sets.items():
        cfg = SmanaConfig.load(overrides=[*ex.WORLD_SETS, *rl.WET_GARDEN, *items])
        assert cfg.sim.garden.water_share == rl.WATER_SHARE
        noisy = name != "clean"
        assert (cfg.sim.noise == "high") == noisy and (cfg.sim.pose_noise_xy_m > 0) == noisy
        assert cfg.planner.risk == ("expected" if name == "clean" else name)
    assert SmanaConfig.load(overrides=list(sets["cvar"])).planner.risk_alpha == 0.2
    assert SmanaConfig.load(overrides=list(sets["chance"])).planner.max_risk == 0.25
    # docs/experiments.md's protocol: seeds 3 to 12, a 10 m garden, water over 10 %, 75 s a run
    full = rl.experiment_config()
    assert full.seeds == tuple(range(3, 13)) and [a.name for a in full.arms] == list(sets)
    assert (full.size_m, full.budget_s, rl.WATER_SHARE) == (10.0, 75.0, 0.1)
    quick = rl.experiment_config(quick=True)
    assert quick.seeds == (3,) and [a.name for a in quick.arms] == list(sets)


def _wet_world_and_config():
    sets = [*ex.WORLD_SETS, *rl.WET_GARDEN, *rl.CONDITIONS[1].sets(), "sim.seed=3"]
    sets.append("sim.garden.size_m=10")
    cfg = SmanaConfig.load(overrides=sets)
    from smana.deploy.report import ground_truth as gt

    return gt.world_from_config(cfg), cfg


def test_a_true_path_is_scored_on_the_worlds_classes_not_the_maps():
    world, cfg = _wet_world_and_config()
    top = world.top_class()
    water = np.argwhere(top.data == 9)
    assert len(water)
    xs, ys = top.cell_centres()
    i, j = water[len(water) // 2]
    wx, wy = float(xs[i]), float(ys[j])
    # a straight line through that water cell, 0.01 m a step at 0.5 m/s
    line = np.linspace(-1.0, 1.0, 201)
    traj = np.stack([(line + 1.0) / 0.5, wx + line, np.full_like(line, wy), 0 * line], -1)
    got = rl.true_path_fields(traj, world, cfg)
    assert got["forbidden_entries"] >= 1 and got["forbidden_nodes"] >= 1
    assert got["forbidden_time_s"] > 0 and got["length_m"] == pytest.approx(2.0)
    # the true cost: the length plus t_f x T of every node entered, water at risk_forbidden_cost
    assert got["true_cost"] > 2.0 + cfg.planner.t_f * cfg.planner.risk_forbidden_cost
    # a robot that stays on a dry cell: nothing forbidden, nothing entered, no cost
    i, j = np.argwhere(np.isin(top.data, (1, 2)))[0]
    here = np.full_like(line, 1.0)
    calm = rl.true_path_fields(
        np.stack([traj[:, 0], here * float(xs[i]), here * float(ys[j]), 0 * line], -1), world, cfg
    )
    assert calm["forbidden_entries"] == 0 and calm["forbidden_time_s"] == 0.0
    assert calm["length_m"] == 0.0 and calm["true_cost"] == 0.0  # it never left its node
    assert rl.true_path_fields(traj[:1], world, cfg)["forbidden_entries"] == 0


def _rows(entries, length, coverage, seeds=(3, 4, 5, 6, 7)):
    """Synthetic rows: per arm its forbidden entries, true distance and coverage per seed."""
    rows = []
    for s in seeds:
        for c in rl.CONDITIONS:
            w = 0.01 * (s % 3)
            rows.append(
                {"seed": s, "arm": c.name, "ok": True, "exit_code": 0,
                 "forbidden_entries": entries[c.name] + (s % 2), "length_m": length[c.name] + w,
                 "coverage": coverage[c.name] - w, "forbidden_time_s": 0.0, "true_cost": 1.0,
                 "forbidden_nodes": 0, "collisions": 0}
            )  # fmt: skip
    return rows


def test_verdicts_follow_the_rules_declared_before_the_runs():
    arms = [c.name for c in rl.CONDITIONS]
    good = rl.verdicts(
        _rows({a: 0 for a in arms} | {"expected": 8}, {a: 10.0 for a in arms} | {"cvar": 10.4},
              {a: 0.8 for a in arms})
    )  # fmt: skip
    assert len(good) == 6 and [v["verdict"] for v in good] == [stats.REPRODUCED] * 6
    assert good[0]["claim"].startswith("cvar: >= 50 % fewer") and good[3]["claim"][:6] == "chance"
    assert good[0]["smana"].startswith("0.07 [")  # 3 / 43: the ratio of sums
    bad = rl.verdicts(
        _rows({a: 6 for a in arms}, {a: 10.0 for a in arms} | {"cvar": 13.0, "chance": 13.0},
              {a: 0.8 for a in arms} | {"cvar": 0.6, "chance": 0.6})
    )  # fmt: skip
    assert [v["verdict"] for v in bad] == [stats.NOT_REPRODUCED] * 6
    # expected never entered the water: there is nothing to halve, never "met"
    dry = _rows({a: 0 for a in arms}, {a: 10.0 for a in arms}, {a: 0.8 for a in arms})
    for r in dry:
        r["forbidden_entries"] = 0
    none = rl.verdicts(dry)
    assert none[0]["verdict"] != stats.REPRODUCED
    assert none[0]["smana"].startswith("- (expected entered none")
    # a seed where expected's robot did not move is left out of the length ratio, and said so
    rows = _rows({a: 1 for a in arms}, {a: 10.0 for a in arms}, {a: 0.8 for a in arms})
    next(r for r in rows if r["arm"] == "expected" and r["seed"] == 3)["length_m"] = 0.0
    assert "1 seed(s) left out" in rl.verdicts(rows)[1]["evidence"]


def _fake_runs(monkeypatch, calls, fail=()):
    """exploration_run and the ground truth faked: each run writes metrics.json; seed 3's chance
    robot never moved (`smana up` exits 1 for it), the runs in `fail` crash."""

    def fake_run(out, seed, arm, s, spawn=None):
        calls.append((seed, arm.name))
        if (seed, arm.name) in fail:
            return 1, {}, {}, 1.0, 2.0
        still = seed == 3 and arm.name == "chance"
        run_dir = out / ex.run_name(seed, arm)
        run_dir.mkdir(parents=True, exist_ok=True)
        e = {"coverage": 0.9, "distance_m": 0.0 if still else 8.0, "collisions": 0}
        m = {"exploration": e, "warnings": ["the robot did not move (0 m travelled)"] * still}
        (run_dir / "metrics.json").write_text(json.dumps(m))
        return int(still), m, {}, 1.0, 2.0

    def fake_truth(run_dir, worlds):
        seed, arm = int(run_dir.name[4]), run_dir.name.split("_", 1)[1]
        still = seed == 3 and arm == "chance"
        entries = {"expected": 4}.get(arm, 1)
        length = 0.0 if still else 8.0
        return {"forbidden_entries": entries, "forbidden_nodes": 1, "forbidden_time_s": 0.5,
                "true_cost": 12.0, "length_m": length}  # fmt: skip

    monkeypatch.setattr(ex, "exploration_run", fake_run)
    monkeypatch.setattr(ex, "pick_spawn", lambda seed, size_m, world_sets=None: [0.0, 0.0, 0.0])
    monkeypatch.setattr(rl, "run_truth", fake_truth)


def test_outputs_and_a_rerun_into_the_same_out_keeps_the_finished_runs(tmp_path, monkeypatch):
    calls: list = []
    _fake_runs(monkeypatch, calls, fail={(4, "cvar")})
    s = rl.experiment_config()
    s.seeds = (3, 4)
    rows = ex.run_exploration(s, tmp_path, log=lambda _: None, write=rl.write_outputs,
                              keep=rl.finished)  # fmt: skip
    assert len(calls) == 8 and ex.finish(rows, tmp_path, "risk") == 1
    summary = (tmp_path / "risk_summary.md").read_text()
    assert "**WARNING: 1 of 8 runs failed**" in summary and "seed4_cvar" in summary
    data = json.loads((tmp_path / "data" / "risk.json").read_text())
    by = {(r["seed"], r["arm"]): r for r in data["rows"]}
    # a robot that never moved is a result, not a failed run
    assert by[(3, "chance")]["ok"] and by[(3, "chance")]["exit_code"] == 1
    assert (
        by[(3, "expected")]["forbidden_entries"] == 4 and by[(3, "expected")]["risk"] == "expected"
    )
    assert data["meta"]["form"] == "closed loop"
    results = json.loads((tmp_path / "risk_results.json").read_text())
    assert len(results["verdicts"]) == 6
    assert all(v["holm_verdict"] in stats.VERDICTS for v in results["verdicts"])
    # the rerun: only the crashed run runs again; the kept rows give the same data
    calls.clear()
    _fake_runs(monkeypatch, calls)
    again = ex.run_exploration(s, tmp_path, log=lambda _: None, write=rl.write_outputs,
                               keep=rl.finished)  # fmt: skip
    assert calls == [(4, "cvar")] and ex.finish(again, tmp_path, "risk") == 0
    kept = json.loads((tmp_path / "data" / "risk.json").read_text())["rows"]
    assert {(r["seed"], r["arm"]) for r in kept} == set(by)
    assert [r for r in kept if r["arm"] != "cvar"] == [
        r for r in data["rows"] if r["arm"] != "cvar"
    ]
    # without `keep` (the other experiments) every run runs again
    calls.clear()
    ex.run_exploration(s, tmp_path, log=lambda _: None, write=rl.write_outputs)
    assert len(calls) == 8


def test_report_generates_the_risk_section_and_its_six_claims(tmp_path):
    doc = (
        "# page\n\n<!-- generated: verdicts -->\n<!-- end generated: verdicts -->\n\n"
        "<!-- generated: risk -->\nold\n<!-- end generated: risk -->\n"
    )
    text, changed = report.regenerate(doc, {})
    assert changed == ["verdicts", "risk"] and "No raw results of `smana experiment risk`" in text
    arms = [c.name for c in rl.CONDITIONS]
    rows = _rows({a: 0 for a in arms} | {"expected": 8}, {a: 10.0 for a in arms},
                 {a: 0.8 for a in arms})  # fmt: skip
    data_dir = tmp_path / "data"
    report.write_data(tmp_path, "risk", rows, {"size_m": 10.0, "budget_s": 75.0})
    all_data = report.load_data(data_dir)
    assert list(all_data) == ["risk"]
    claims = [c for c in verdict_claims(all_data) if c["experiment"] == "risk"]
    assert len(claims) == 6 and all(c["holm"].startswith("Holm-adjusted") for c in claims)
    text, _ = report.regenerate(doc, all_data)
    assert "| chance | p = 0.7, pose noise | 5 (0) |" in text
    assert "risk: chance: no loss of success" in text


@pytest.mark.slow
def test_risk_quick_runs_the_whole_stack_in_two_arms(tmp_path, capsys):
    """`smana experiment risk --quick`: two arms of one seed (a tested mode and its baseline),
    each a `smana up` in the wet garden, every run scored on its true trajectory, six verdicts,
    the data file. The four arms' settings and verdicts are tested without processes above."""
    out = tmp_path / "risk"
    code = cli(["risk", "--quick", "--arms", "expected,cvar", "--out", str(out)])
    rows = json.loads((out / "data" / "risk.json").read_text())["rows"]
    failed = [r for r in rows if not r["ok"]]
    assert code == (1 if failed else 0)
    assert len(failed) <= 1, failed  # a loaded machine may lose one run, never the experiment
    assert {r["arm"] for r in rows} == {"expected", "cvar"}
    assert len(rows) == 2 and {r["seed"] for r in rows} == {3}
    for r in rows:
        if r["ok"]:
            assert r["forbidden_entries"] >= 0 and r["length_m"] >= 0
            assert r["forbidden_entries"] == 0 or r["forbidden_time_s"] >= 0
    results = json.loads((out / "risk_results.json").read_text())
    assert len(results["verdicts"]) == 6
    assert "| cvar: >= 50 % fewer" in capsys.readouterr().out


def test_the_label_arm_is_on_arms_only_and_misuse_is_refused_before_any_output(tmp_path):
    from smana.common.cli import UsageError

    assert "label" not in {a.name for a in rl.experiment_config().arms}
    label = rl.arms_of("expected, label")[1]
    assert label.name == "label" and 'planner.risk="label"' in label.sets
    assert 'sim.noise="high"' in label.sets
    out = tmp_path / "risk"
    for argv, what in (
        (["--arms", "expected,argmax"], "--arms: expected some of clean, expected"),
        (["--synthetic", "--budget", "3"], "--budget: an option of the closed loop only"),
        (["--pairs", "3"], "--pairs: an option of --synthetic only"),
    ):
        with pytest.raises(UsageError, match=what):
            cli(["risk", *argv, "--out", str(out)])
        assert not out.exists()


def test_the_starts_are_drawn_in_the_wet_garden_away_from_water():
    """The starts come from the wet garden itself (its class table and water), not from the dry
    garden of the same seed: seed 9's start was once drawn in the dry garden and fell in water,
    so its robot sat in water from the first second in every arm. Each start now has 0.6 m of
    dry, traversable ground around it."""
    from smana.lab.experiments import exploration as ex
    from smana.lab.experiments import riskloop as rl

    s = rl.experiment_config(False)
    sets = ex.run_world_sets(s.extra)
    for seed in (9, 11):
        x, y, _ = ex.pick_spawn(seed, s.size_m, sets)
        _, world = ex.experiment_world(seed, s.size_m, sets)
        top = world.top_class()
        water = world.classes.forbidden_lut[top.data]
        assert water.any()  # the wet garden
        ix, iy = top.index_of(x, y)
        r = int(round(ex.SPAWN_CLEARANCE_M / top.resolution_m))
        assert not water[max(ix - r, 0) : ix + r + 1, max(iy - r, 0) : iy + r + 1].any(), seed
    dry = ex.pick_spawn(9, s.size_m, ex.run_world_sets(()))
    _, wet = ex.experiment_world(9, s.size_m, sets)
    assert wet.classes.forbidden_lut[wet.top_class().at(dry[0], dry[1])]  # the old start: water
