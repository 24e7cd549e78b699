"""`smana experiment exploration --quick`: two short runs of the whole stack (grass cost x1 and
x4) and the experiment's table, plot and summary."""

from __future__ import annotations

import json

import pytest

from smana.lab import experiments as exp

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


def test_exploration_quick(tmp_path):
    assert exp.cli(["exploration", "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "exploration_results.json").read_text())
    runs = data["runs"]
    assert [r["grass_cost_factor"] for r in runs] == [1.0, 4.0]
    for r in runs:
        assert r["exit_code"] == 0, r
        assert r["terrain_share"] is not None and 0.0 <= r["terrain_share"] <= 1.0
        assert r["coverage"] > 0.2 and r["distance_m"] > 0.5, r
    # each run is a complete run directory with its own report, and the grass cost reached it
    cfg = (tmp_path / "seed3_grass_x4" / "config.toml").read_text()
    assert 'class_costs = ["grass=4.0"]' in cfg
    assert (tmp_path / "seed3_grass_x1" / "report.md").is_file()
    assert (tmp_path / "exploration_terrain_share.png").stat().st_size > 1000
    assert "| x4 |" in (tmp_path / "exploration_summary.md").read_text()
