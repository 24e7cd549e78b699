"""The experiments: the fixed trajectory, `smana experiment noise --quick`, and the exploration
experiment's tables and plot (its runs of the whole stack are in test_e2e_*)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.lab import evaluation as ev
from smana.lab import experiments as exp


def test_fixed_trajectory_is_long_smooth_and_clear_of_obstacles():
    from smana.services.sim.worlds.garden import generate

    world = generate(3, size_m=12.0)
    poses = exp.fixed_trajectory(world, length_m=44.0, spacing_m=0.25)
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert steps.sum() == pytest.approx(44.0, abs=0.5)
    assert steps.max() < 0.3
    top = world.top_class()
    obstacle = ~world.classes.traversable_lut[top.data]
    clear = ev.clearance_along(poses[:, :2], obstacle, top.origin_xy, top.resolution_m)
    assert clear.min() > 0.3
    assert np.isfinite(poses[:, 2]).all()
    # the same world gives the same trajectory
    assert np.array_equal(poses, exp.fixed_trajectory(world, 44.0, 0.25))


def test_noise_quick(tmp_path):
    assert exp.cli(["noise", "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "noise_results.json").read_text())
    rows = data["rows"]
    assert {r["backend"] for r in rows} == set(exp.BACKENDS)
    assert len(rows) == 3 * 3  # label none, label high, pose high
    for b in exp.BACKENDS:
        by = {(r["sweep"], r["level"]): r for r in rows if r["backend"] == b}
        assert by[("label", "none")]["classification_ratio"] > 0.9
        # more label noise, fewer right labels; more pose noise, a larger error
        assert (
            by[("label", "high")]["classification_ratio"]
            < by[("label", "none")]["classification_ratio"]
        )
        assert by[("pose", "high")]["error_mean_m"] > by[("label", "none")]["error_mean_m"]
    assert set(data["label_loss"]) == set(exp.BACKENDS)
    for name in (
        "noise_results.csv",
        "noise_summary.md",
        "fig6_pose_noise_error.png",
        "fig6_pose_noise_ratio.png",
        "fig7_label_noise_ratio.png",
    ):
        assert (tmp_path / name).stat().st_size > 100
    assert "Classification loss" in (tmp_path / "noise_summary.md").read_text()


def test_exploration_outputs_from_rows(tmp_path):
    rows = []
    for seed in (3, 4):
        for f, share in ((1.0, 0.55), (2.0, 0.7), (4.0, 0.85)):
            rows.append(
                {
                    "seed": seed,
                    "grass_cost_factor": f,
                    "exit_code": 0,
                    "terrain_share": share + 0.01 * seed,
                    "coverage": 0.95,
                    "explored_area_m2": 50.0,
                    "distance_m": 40.0 + seed,
                    "min_clearance_m": 0.4,
                    "done_reason": "no_frontier",
                    "wall_time_s": 200.0,
                }
            )
    rows.append({**rows[0], "seed": 5, "terrain_share": None, "exit_code": 1})
    exp.write_exploration_outputs(rows, exp.ExplorationExperimentConfig(seeds=(3, 4, 5)), tmp_path)
    summary = json.loads((tmp_path / "exploration_results.json").read_text())["summary"]
    x1 = summary[0]
    assert x1["runs"] == 3 and x1["terrain_share_mean"] == pytest.approx(0.585)
    assert summary[2]["paper_terrain_share"] == 0.88
    text = (tmp_path / "exploration_summary.md").read_text()
    assert "reproduced" in text and "NOT" not in text
    assert (tmp_path / "exploration_terrain_share.png").stat().st_size > 1000
