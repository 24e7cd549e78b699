"""`smana experiment fleet` without a stack: rows from fabricated metrics, the summary, the
verdicts (paired ratios, censoring, not-worse map, contacts) and the outputs."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from smana.lab import stats
from smana.lab.experiments import fleet as fx
from smana.lab.experiments import fleet_report as fr

W12, W22 = fx.DEFAULT_GARDEN, fx.LARGE_GARDEN


def _row(world, n, seed, t95, err=0.03, ratio=0.9, contacts=0, ok=True, coverage=0.99):
    t = np.linspace(0, 100, 11)
    cov = np.minimum(1.0, t / 100 + 0.05) * coverage
    return {
        "seed": seed,
        "world": world.name,
        "size_m": world.size_m,
        "n_robots": n,
        "exit_code": 0 if ok else 1,
        "ok": ok,
        "coverage": coverage,
        "time_to_95_s": t95,
        "distance_to_95_m": None if t95 is None else t95 / 5,
        "total_distance_m": 30.0,
        "overlap": None if n == 1 else 0.3,
        "robot_contacts": contacts,
        "min_separation_m": None if n == 1 else 1.5,
        "map_error_m": err,
        "classification_ratio": ratio,
        "collisions": 0,
        "wall_time_s": 100.0,
        "cpu_s": 150.0,
        "curve": {"t_s": t.tolist(), "distance_m": (t / 5).tolist(), "coverage": cov.tolist()},
    }


def _rows(times: dict[int, list], **kw):
    """World 22 rows with the given times to 95 % per N over seeds 3, 4, 5."""
    return [_row(W22, n, 3 + k, t, **kw) for n, ts in times.items() for k, t in enumerate(ts)]


def _verdict(table, start):
    return next(v for v in table if v["claim"].startswith(start))


def test_time_verdicts_are_the_sign_test_paired_per_seed():
    # six seeds: the fleet of 2 at half the lone robot's time in each (under 0.6: met, p = 1/64),
    # the fleet of 3 at 0.6 of it (over 0.45: not met)
    rows = _rows({1: [100] * 6, 2: [50] * 6, 3: [60] * 6})
    table = fr.verdicts(rows)
    two = _verdict(table, "garden22: time to 95 % coverage with 2")
    three = _verdict(table, "garden22: time to 95 % coverage with 3")
    assert two["verdict"] == fx.MET and two["p"] == pytest.approx(1 / 64)
    assert two["p_tests"] == "at most 0.6 x one robot's" and two["rule"] == "at most T, sign test"
    assert two["smana"].startswith("under 0.6 x one robot's time in 6 of 6 seeds, over in 0")
    assert (
        "restricted mean time to 95 % within 100 s: 50 s vs 100 s alone (ratio 0.50)"
        in (two["smana"])
    )
    assert three["verdict"] == fx.NOT_MET and three["p_tests"] == "more than 0.45 x one robot's"
    assert two["need"]["how"] == "exact sign test" and two["need"]["seeds"] == 6
    # three seeds of the same: never decided (1/8 > 0.025), whatever the spread
    rows = _rows({1: [100, 100, 100], 2: [50, 50, 50]})
    assert _verdict(fr.verdicts(rows), "garden22: time to 95 % coverage with 2")["verdict"] == (
        stats.INCONCLUSIVE
    )


def test_a_run_that_never_reached_95_is_censored_at_the_budget_and_its_order_kept():
    # budget 700 s: seed 4's lone robot never reached 95 % (T > 700: 0.6 T > 420, the fleet's
    # 100 s is under it: known); seed 5's fleet never did (over 0.6 x 300: known); seed 6
    # neither (unknown: left out of the test, named)
    rows = _rows({1: [100, None, 300, None], 2: [50, 100, None, None]})
    seeds, (a, ac), (b, bc) = fr.time_pairs(rows, W22.name, 2, 0.6, {W22.name: 700.0})
    assert seeds == [3, 4, 5, 6]
    assert (a, ac) == ([50.0, 100.0, 700.0, 700.0], [False, False, True, True])
    assert b == pytest.approx([60.0, 420.0, 180.0, 420.0]) and bc == [False, True, False, True]
    d, text = fr.decide_time(rows, W22.name, 2, 0.6, {W22.name: 700.0})
    assert text.startswith(
        "under 0.6 x one robot's time in 2 of 4 seeds, over in 1, order unknown in 1 (seed 6) "
        "(2 known through a run that did not reach 95 % within the 700 s budget)"
    )
    assert d.verdict == stats.INCONCLUSIVE
    # the restricted mean counts a run that did not reach it as the budget, never its bound
    assert "within 700 s: 388 s vs 450 s alone" in text
    # without a budget (older data, none given): censored at the latest time any of the world's
    # runs was followed to (its end, or here the lone robot's 300 s)
    assert fr.time_pairs(rows, W22.name, 2, 0.6)[1][0][2] == 300.0


def test_a_failed_run_counts_as_not_reached_and_is_never_dropped():
    # seed 5's fleet reached 95 % in 40 s but one of its members never moved: smana up said
    # FAILED (exit 1, figures left): counted as not reached, its map scored as it is
    rows = _rows({1: [100, 100, 100], 2: [50, 50, 40]})
    rows[-1].update(ok=False, exit_code=1)
    assert fx.failed(rows[-1]) and fx.measured(rows[-1])
    d, text = fr.decide_time(rows, W22.name, 2, 0.6)
    assert "over in 1" in text and "FAILED runs counted as not reached: seed 5 (2 robots)" in text
    assert fr.paired_difference(rows, W22.name, 2, "map_error_m").n == 3
    # a newer row says so itself; a run that left no figures is missing, and named
    rows[-1].update(run_failed=False, ok=True)
    assert not fx.failed(rows[-1])
    gone = dict(rows[-1], ok=False, exit_code=-9, coverage=None, run_failed=False)
    assert not fx.measured(gone)
    s = {d["n_robots"]: d for d in fr.summarise_fleet([*rows[:-1], gone])}
    assert (s[2]["runs"], s[2]["failed"], s[2]["run_failed"]) == (3, 1, 0)


def test_merged_map_not_worse_and_contacts():
    rows = [_row(W12, 1, s, 50, err=0.030 + 0.001 * s, ratio=0.90) for s in (3, 4, 5)]
    rows += [
        _row(W12, 2, s, 30, err=0.030 + 0.001 * s + d, ratio=0.9)
        for s, d in ((3, 0.001), (4, -0.001), (5, 0.0))
    ]
    table = fr.verdicts(rows)
    assert _verdict(table, "garden12: merged map's reconstruction")["verdict"] == fx.MET
    # the same ratio in every seed: a difference of exactly 0
    assert _verdict(table, "garden12: merged map's classification")["verdict"] == fx.MET
    worse = [
        dict(
            r,
            map_error_m=r["map_error_m"]
            + 0.01 * (r["n_robots"] - 1)
            + 0.001 * r["seed"] * (r["n_robots"] - 1),
        )
        for r in rows
    ]
    table = fr.verdicts(worse)
    v = _verdict(table, "garden12: merged map's reconstruction")
    assert v["verdict"] == fx.NOT_MET and v["p_tests"] == "worse by more than the margin"
    assert _verdict(table, "robot-robot contacts")["verdict"] == fx.MET
    rows[-1]["robot_contacts"] = 2
    v = _verdict(fr.verdicts(rows), "robot-robot contacts")
    assert v["verdict"] == fx.NOT_MET and v["smana"].startswith("2 in 6 runs")
    rows[-1]["robot_contacts"] = None
    assert _verdict(fr.verdicts(rows), "robot-robot contacts")["verdict"] == stats.INCONCLUSIVE


def test_not_worse_by_hand():
    iv = stats.Interval
    # non-inferiority: the interval must clear the margin; holding 0 is not enough
    assert fr.not_worse(iv(0.0, -0.01, 0.01, 3), True, 0.005) == stats.INCONCLUSIVE
    assert fr.not_worse(iv(0.0, -0.01, 0.01, 3), True, 0.02) == fx.MET
    assert fr.not_worse(iv(-0.02, -0.03, -0.01, 3), True, 0.0) == fx.MET
    assert fr.not_worse(iv(0.02, 0.01, 0.03, 3), True, 0.005) == fx.NOT_MET
    assert fr.not_worse(iv(-0.02, -0.03, -0.01, 3), False, 0.005) == fx.NOT_MET
    assert fr.not_worse(iv(-0.002, -0.004, 0.0, 3), False, 0.005) == fx.MET


def test_summary_per_world_and_fleet_size():
    rows = _rows({1: [100, 200, None], 2: [50, 100, 150]})
    rows.append(_row(W22, 2, 6, 10, ok=False))  # exit 1 with its figures: FAILED, kept
    s = {(d["world"], d["n_robots"]): d for d in fr.summarise_fleet(rows, {W22.name: 700.0})}
    one, two = s[("garden22", 1)], s[("garden22", 2)]
    assert (one["runs"], one["failed"], one["reached_95"]) == (3, 0, 2)
    # Kaplan-Meier: 100, 200 and one censored at the 700 s budget; median 200, restricted mean
    # (100 + 200 + 700) / 3
    km = one["km_time_to_95_s"]
    assert km["median"] == 200 and km["rmst"]["mean"] == pytest.approx(1000 / 3)
    assert (two["runs"], two["failed"], two["run_failed"], two["reached_95"]) == (4, 0, 1, 3)
    assert two["km_time_to_95_s"]["rmst"]["mean"] == pytest.approx((50 + 100 + 150 + 700) / 4)
    assert "two-sided; the data lean to 2 robots sooner" in two["logrank_text"]
    assert two["overlap"]["mean"] == pytest.approx(0.3) and one["overlap"]["n"] == 0
    table = fr.summary_table(list(s.values()))
    assert table[0] == fr.SUMMARY_HEAD and len(table[1].split("|")) == len(table[0].split("|"))
    assert "| garden22 | 2 | 4 (1; 0) | 3 of 4 |" in table[3]


def test_rows_from_a_fleet_run_and_a_single_robot_run():
    metrics = {
        "fleet": {
            "coverage": 0.98,
            "time_to_95_s": 42.0,
            "distance_to_95_m": 12.0,
            "total_distance_m": 20.0,
            "overlap": 0.25,
            "sim": {"robot_contacts_total": 0, "min_separation_overall_m": 1.1},
            "map": {"merged": {"reconstruction_error_mean_m": 0.03, "classification_ratio": 0.9}},
            "curve": {"t_s": [0, 42], "distance_m": [0, 12], "coverage": [0.1, 0.98]},
        },
        "exploration": {"collisions": 1},
    }
    r = fx.make_row(3, W22, 2, 0, metrics, 10.0, 20.0)
    assert r["ok"] and r["time_to_95_s"] == 42.0 and r["overlap"] == 0.25
    assert r["map_error_m"] == 0.03 and r["robot_contacts"] == 0 and r["collisions"] == 1
    failed = fx.make_row(3, W22, 2, -1, {}, 0.0, 0.0)
    assert not failed["ok"] and failed["robot_contacts"] is None


def test_a_run_whose_only_warning_is_a_contact_is_data_and_its_contacts_count():
    """`smana up` exits 1 for a robot-robot contact; the experiment keeps that run (dropping it
    would leave the contact count to the runs that had none), and one whose member did not do
    its job (a FAILED run, counted as such), but not one that failed otherwise."""
    fleet = {"coverage": 0.97, "sim": {"robot_contacts_total": 1}, "curve": {}}
    contact = {"fleet": fleet, "warnings": ["1 robot-robot contact(s) (r1-r2 x1)"]}
    r = fx.make_row(7, W22, 3, 1, contact, 10.0, 20.0)
    assert r["ok"] and r["robot_contacts"] == 1 and r["warnings"] == contact["warnings"]
    assert not r["run_failed"]
    # a member that did not move: an outcome too, the run is data and counts as FAILED
    still = dict(contact, warnings=[*contact["warnings"], "r2: the robot did not move (0 m)"])
    r2 = fx.make_row(7, W22, 3, 1, still, 10.0, 20.0, budget_s=700.0)
    assert r2["ok"] and r2["run_failed"] and fx.failed(r2) and r2["budget_s"] == 700.0
    lost = dict(
        contact, warnings=["the simulator left no sim.json: robot-robot contacts are unknown"]
    )
    assert not fx.make_row(7, W22, 3, 1, lost, 10.0, 20.0)["ok"]  # not an outcome
    assert not fx.make_row(7, W22, 3, -9, contact, 10.0, 20.0)["ok"]  # killed: not a finished run
    assert not fx.make_row(7, W22, 3, 1, {"fleet": fleet}, 10.0, 20.0)["ok"]  # 1, but no reason
    rows = [_row(W12, n, s, 50) for n in (1, 2) for s in (3, 4, 5)] + [r]
    v = _verdict(fr.verdicts(rows), "robot-robot contacts")
    assert v["verdict"] == fx.NOT_MET and v["smana"].startswith("1 in 7 runs"), v


def test_outputs_say_quick_on_top_and_draw_one_curve_per_fleet_size(tmp_path):
    s = fx.FleetExperimentConfig.quick()
    rows = [_row(W12, n, 3 + k, 50 / n) for n in (1, 2) for k in range(2)]
    rows.append(_row(W12, 2, 5, None, ok=False))
    rows[-1]["warnings"] = ["r2: the robot did not move (0.00 m travelled)"]  # a newer row's field
    figures = fr.write_fleet_outputs(rows, s, tmp_path)
    with open(tmp_path / "fleet.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert len(table) == len(rows) and table[0]["warnings"] == "" and table[-1]["warnings"]
    text = (tmp_path / "fleet.md").read_text()
    assert text.splitlines()[2].startswith("**Quick run**")
    assert "**WARNING: 1 of 5 runs FAILED on what their robots did**" in text
    assert "counted as not reached in the times to 95 %" in text and "garden12_n2_seed5" in text
    data = json.loads((tmp_path / "fleet.json").read_text())
    assert {"settings", "runs", "summary", "verdicts"} <= set(data)
    compact = json.loads((tmp_path / "data" / "fleet.json").read_text())["rows"]
    assert len(compact) == len(rows) and "curve" not in compact[0]
    assert [p.name for p in figures] == ["fleet_coverage_time_garden12.png"]
    assert figures[0].stat().st_size > 1000


def test_argv_and_arguments(tmp_path):
    import argparse

    s = fx.FleetExperimentConfig()
    argv = fx.fleet_argv(tmp_path, 3, W22, 3, s, spawn=[1.0, 2.0, 0.5], port=7000)
    assert argv[3:7] == ["up", "--robots", "3", "--run-dir"]
    assert "sim.garden.size_m=22.0" in argv and "explorer.time_budget_s=700.0" in argv
    assert "sim.spawn=[1.0, 2.0, 0.5]" in argv
    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    fx.add_parser(sub)
    args = p.parse_args(["fleet", "--robots", "1,3", "--worlds", "garden22", "--budget", "90"])
    s = fx.apply_args(fx.FleetExperimentConfig(), args)
    assert s.robots == (1, 3) and [w.name for w in s.worlds] == ["garden22"]
    assert s.budget(W22) == 90
    assert s.seeds == (3, 4, 5)
    # a share of the seeds: --first-seed alone keeps the number, with --seeds it is both
    seeds = fx.apply_args(fx.FleetExperimentConfig(), p.parse_args(["fleet", "--first-seed", "7"]))
    assert seeds.seeds == (7, 8, 9)
    both = p.parse_args(["fleet", "--first-seed", "7", "--seeds", "4"])
    assert fx.apply_args(fx.FleetExperimentConfig(), both).seeds == (7, 8, 9, 10)
    from smana.common.cli import UsageError

    with pytest.raises(UsageError):
        fx.apply_args(fx.FleetExperimentConfig(), p.parse_args(["fleet", "--robots", "0,x"]))
    assert "80 minutes" in sub.choices["fleet"].epilog and "--quick 2 minutes" in (
        sub.choices["fleet"].epilog
    )


def test_a_rerun_into_the_same_out_keeps_finished_runs_and_runs_the_rest(tmp_path, monkeypatch):
    s = fx.FleetExperimentConfig.quick()  # garden12, 1 and 2 robots, seed 3
    s.seeds = (3, 4)
    ran = []

    def fake_run(out, seed, world, n, s_, spawn=None):
        ran.append((seed, n))
        return 0 if (seed, n) != (4, 2) else 1, {"fleet": {"coverage": 0.9}}, 1.0, 2.0

    monkeypatch.setattr(fx, "fleet_run", fake_run)
    monkeypatch.setattr(fr, "write_fleet_outputs", lambda rows, s_, out: [])
    for seed, n in [(3, 1), (3, 2), (4, 1), (4, 2)]:
        (tmp_path / fx.run_name(seed, "garden12", n)).mkdir(parents=True)
    first = fx.run_fleet(s, tmp_path, log=lambda *a: None)
    assert sorted(ran) == [(3, 1), (3, 2), (4, 1), (4, 2)] and len(first) == 4
    # a corrupt row file and another run's row are not kept: that run runs again
    (tmp_path / fx.run_name(3, "garden12", 2) / fx.ROW_FILE).write_text("{not json")
    (tmp_path / fx.run_name(4, "garden12", 1) / fx.ROW_FILE).write_text(
        (tmp_path / fx.run_name(3, "garden12", 1) / fx.ROW_FILE).read_text()
    )
    ran.clear()
    second = fx.run_fleet(s, tmp_path, log=lambda *a: None)
    # kept: (3, 1) and the failed (4, 2), which finished; run again: the corrupt and the foreign
    assert sorted(ran) == [(3, 2), (4, 1)]
    assert [(r["seed"], r["n_robots"], r["ok"]) for r in second] == [
        (3, 1, True),
        (4, 1, True),
        (3, 2, True),
        (4, 2, False),
    ]
    # a run killed (or one that could not start) did not finish: not kept, it runs again
    assert not fx.make_row(4, fx.DEFAULT_GARDEN, 2, -9, {"fleet": {}}, 1.0, 2.0)["finished"]
    assert not fx.make_row(4, fx.DEFAULT_GARDEN, 2, 1, {}, 1.0, 2.0)["finished"]


def test_the_committed_data_decides_as_the_run_did_censored_seeds_included(tmp_path):
    """The data file has no curves but keeps `end_time_s` and its meta the budgets: the verdicts
    `smana experiment report` computes from it are the run's own."""
    rows = _rows({1: [300, None, 250, 280], 2: [150, 140, None, 150], 3: [100, 90, 80, None]})
    s = fx.FleetExperimentConfig(seeds=(3, 4, 5, 6), worlds=(W22,))
    fr.write_fleet_outputs(rows, s, tmp_path)
    ran = json.loads((tmp_path / "fleet.json").read_text())["verdicts"]
    compact = json.loads((tmp_path / "data" / "fleet.json").read_text())["rows"]
    assert all("curve" not in r and r["end_time_s"] == 100.0 for r in compact)
    meta = json.loads((tmp_path / "data" / "fleet.json").read_text())["meta"]
    again = fr.verdicts(compact, budgets=fr.budgets_of(meta))
    assert [v["smana"] for v in again] == [v["smana"] for v in ran]
    assert (
        "known through a run that did not reach 95 % within the 700 s budget" in again[0]["smana"]
    )  # the lone robot's censored seed
