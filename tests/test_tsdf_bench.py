"""`smana bench tsdf --quick`: smana and Open3D on 1 and 2 threads per workload, the ratio
columns and their spread printed (figures, not timing assertions)."""

from __future__ import annotations

import json
import re

import pytest

from smana.lab.bench import tsdf as bench


def test_quick_bench_prints_both_sides_the_ratios_and_their_spread(capsys, tmp_path):
    pytest.importorskip("open3d", reason="an optional peer (smana[bench])")
    assert bench.cli(["--quick", "--out", str(tmp_path / "r.json")]) == 0
    text = capsys.readouterr().out
    report = json.loads((tmp_path / "r.json").read_text())
    assert [r["workload"] for r in report["rows"]] == list(bench.QUICK)
    for row in report["rows"]:
        assert set(row["runs"]) == {"ours1", "ours2", "o3d1", "o3d2"}
        for run in row["runs"].values():
            assert run["median_ms"] > 0 and run["cpu_median_ms"] > 0 and len(run["load"]) == 2
        for col, (t_ours, t_o3d, measure) in bench.RATIOS.items():
            want = row["runs"][f"ours{t_ours}"][measure] / row["runs"][f"o3d{t_o3d}"][measure]
            assert row[col] == pytest.approx(want)
        # the row: both sides on both thread counts, then the four ratios and the load
        cells = r" +\d+( +[\d.]+/[\d.]+){4}( +[\d.]+){4} +[\d.]+-[\d.]+$"
        assert re.search(rf"^{re.escape(row['workload'])}{cells}", text, re.M)
    assert set(report["spread"]) == set(bench.RATIOS)
    for col, s in report["spread"].items():
        vals = [r[col] for r in report["rows"]]
        assert (s["min"], s["max"], s["n"]) == (min(vals), max(vals), len(vals))
        assert re.search(
            rf"^ratio {col} +median [\d.]+, range [\d.]+-[\d.]+ over 2 workloads", text, re.M
        )
    assert re.search(r"^ratio cpu_1t .*goal <= 0.8: ", text, re.M)
    assert re.search(r"^ratio wall_2t .*goal <= 1: ", text, re.M)
    assert re.search(r"^load average [\d.]+ at the end", text, re.M)


def test_an_unknown_workload_is_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        bench.cli(["--workloads", "nope"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "nope" in err and "Traceback" not in err


def test_a_failed_run_is_named_and_exits_1(capsys, monkeypatch):
    pytest.importorskip("open3d", reason="an optional peer (smana[bench])")
    real = bench.mb.run_config

    def run(cfg, path, in_process):
        if cfg["kind"] == "ours" and cfg["threads"] == 2:
            return {**cfg, "error": ["RuntimeError: provoked"]}
        return real(cfg, path, True)

    monkeypatch.setattr(bench.mb, "run_config", run)
    assert bench.cli(["--quick"]) == 1
    captured = capsys.readouterr()
    assert "ERROR ours os1-16 20m 0.3 2t: ['RuntimeError: provoked']" in captured.err
    assert re.search(r"^ratio cpu_1t +median", captured.out, re.M)  # what ran is still reported
    assert not re.search(r"^ratio wall_2t", captured.out, re.M)


def test_a_missed_goal_is_reported_not_an_error(capsys, monkeypatch):
    """--help: "a missed goal is reported, not an error": runs that all succeed with smana ten
    times Open3D's time miss every goal, say so, and the bench exits 0."""

    def run(cfg, path, in_process):  # no Open3D needed: the figures are made up
        ms = 10.0 if cfg["kind"] == "ours" else 1.0
        return {**cfg, "median_ms": ms, "cpu_median_ms": ms, "load": [1.0, 1.0]}

    monkeypatch.setattr(bench.mb, "have_module", lambda name: True)
    monkeypatch.setattr(bench.mb, "run_config", run)
    assert bench.cli(["--quick"]) == 0
    out = capsys.readouterr().out
    for col, goal in bench.GOALS.items():
        assert re.search(rf"^ratio {col} +median 10.000, .*goal <= {goal:g}: missed by", out, re.M)


def test_without_open3d_it_says_what_to_install_and_exits_1(capsys, monkeypatch):
    """--help: "Needs open3d (smana[bench])"."""
    import sys

    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d raises ImportError
    assert bench.cli(["--quick"]) == 1
    assert "open3d not installed (pip install 'smana[bench]')" in capsys.readouterr().err
