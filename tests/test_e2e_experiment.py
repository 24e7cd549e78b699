"""`smana experiment exploration --quick`: short runs of the whole stack in the cluttered garden,
two at once, and the experiment's tables and plots (its verdicts over several seeds are checked on
synthetic rows in test_eval_experiments.py)."""

from __future__ import annotations

import json

import pytest

from smana.lab import experiments as exp

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


def test_exploration_quick(tmp_path):
    # Two of the quick run's arms (an NBV grass weight and the baseline) and one seed keep the
    # suite's time: each run is a whole `smana up`, two at once on the machine's two cores.
    arms = "nbv_x4,nearest_frontier_x2"
    argv = ["exploration", "--quick", "--arms", arms, "--seeds", "1", "--out", str(tmp_path)]
    assert exp.cli(argv) == 0
    data = json.loads((tmp_path / "exploration_results.json").read_text())
    runs = data["runs"]
    assert [(r["arm"], r["seed"]) for r in runs] == [("nbv_x4", 3), ("nearest_frontier_x2", 3)]
    for r in runs:
        assert r["exit_code"] == 0 and r["ok"], r
        assert r["terrain_share"] is not None and 0.0 <= r["terrain_share"] <= 1.0
        assert r["coverage"] > 0.2 and r["distance_m"] > 0.5, r
        assert len(r["curve"]["coverage"]) >= 2
        # the curve ends at the known share (any label); coverage is the usable share
        assert r["curve"]["coverage"][-1] == pytest.approx(r["known_share"])
        assert r["coverage"] <= r["known_share"]
    # each run is a complete run directory with its own report, its grass cost and its start
    cfg = (tmp_path / "seed3_nbv_x4" / "config.toml").read_text()
    assert 'class_costs = ["grass=4.0"]' in cfg and 'layout = "3drms"' in cfg
    baseline = (tmp_path / "seed3_nearest_frontier_x2" / "config.toml").read_text()
    assert 'strategy = "nearest_frontier"' in baseline
    x, y, _ = exp.exploration.pick_spawn(3, 6.0)
    assert f"spawn = [{x}, {y}," in cfg
    assert (tmp_path / "seed3_nbv_x4" / "report.md").is_file()
    assert (tmp_path / "exploration_terrain_share.png").stat().st_size > 1000
    text = (tmp_path / "exploration_summary.md").read_text()
    assert text.splitlines()[2].startswith("**Quick run**: 1 seed of 20 s in a 6 m garden")
    assert "WARNING" not in text and "(n = 1, no interval) | inconclusive |" in text
    assert "| claim | paper |" in text
    assert "| nbv_x4 | 1 (0) |" in text
