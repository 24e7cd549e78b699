"""The experiments: the fixed trajectory, `smana experiment noise --quick`, and the exploration
experiment's tables and plot (its runs of the whole stack are in test_e2e_*)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.lab import evaluation as ev
from smana.lab import experiments as exp
from smana.lab import stats


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


def test_fixed_trajectory_from_a_drawn_start_is_clear_and_repeatable():
    from smana.services.sim.worlds.garden import generate

    world = generate(4, size_m=12.0)
    spawn = exp.fixed_trajectory(world, length_m=6.0, spacing_m=0.25)
    drawn = exp.fixed_trajectory(world, 6.0, 0.25, rng=np.random.default_rng(7))
    assert np.hypot(*(drawn[0, :2] - spawn[0, :2])) > 0.2  # another start than the spawn
    top = world.top_class()
    obstacle = ~world.classes.traversable_lut[top.data]
    clear = ev.clearance_along(drawn[:, :2], obstacle, top.origin_xy, top.resolution_m)
    assert clear.min() > 0.3
    again = exp.fixed_trajectory(world, 6.0, 0.25, rng=np.random.default_rng(7))
    assert np.array_equal(drawn, again)


def test_noise_quick(tmp_path):
    assert exp.cli(["noise", "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "noise_results.json").read_text())
    rows = data["rows"]
    assert {r["backend"] for r in rows} == set(exp.BACKENDS)
    assert sorted({r["seed"] for r in rows}) == [3, 4]
    assert len(rows) == 2 * 3 * 3  # 2 seeds x (label none, label high, pose high) x back-ends
    for seed in (3, 4):
        for b in exp.BACKENDS:
            by = {
                (r["sweep"], r["level"]): r for r in rows if r["backend"] == b and r["seed"] == seed
            }
            assert by[("label", "none")]["classification_ratio"] > 0.9
            # more label noise, fewer right labels; more pose noise, a larger error
            assert (
                by[("label", "high")]["classification_ratio"]
                < by[("label", "none")]["classification_ratio"]
            )
            assert by[("pose", "high")]["error_mean_m"] > by[("label", "none")]["error_mean_m"]
    # the two seeds are two worlds and two starts: not one run twice
    first = [r["n_points"] for r in rows if r["seed"] == 3]
    assert first != [r["n_points"] for r in rows if r["seed"] == 4]
    assert set(data["label_loss"]) == set(exp.BACKENDS)
    for a in data["aggregate"]:
        ci = a["classification_ratio"]
        assert ci["n"] == 2 and ci["ci_lo"] <= ci["mean"] <= ci["ci_hi"]
    assert [m["start"] for m in data["meta"]["seeds"]] == ["spawn", "drawn"]
    for name in (
        "noise_results.csv",
        "noise_summary.md",
        "fig6_pose_noise_error.png",
        "fig6_pose_noise_ratio.png",
        "fig7_label_noise_ratio.png",
    ):
        assert (tmp_path / name).stat().st_size > 100
    header = (tmp_path / "noise_results.csv").read_text().splitlines()[0].split(",")
    assert header[0] == "seed"
    text = (tmp_path / "noise_summary.md").read_text()
    lines = text.splitlines()
    # the verdict table opens the summary, one row per claim, each decided by lab/stats.py
    assert lines[2] == "| claim | paper | smana mean [95 % CI] (n) | verdict |"
    verdicts = [ln.rsplit("|", 2)[1].strip() for ln in lines[4:9]]
    assert len(verdicts) == 5 and set(verdicts) <= set(stats.VERDICTS)
    assert "(n = 2)" in lines[4] and "WARNING" not in text
    assert "Classification loss" in text and "CPU time per seed" in text


def _noise_rows(losses, added):
    """Rows of a noise run: per seed, the tsdf and octree-max classification ratio loss over the
    label sweep and reconstruction error added over the pose sweep."""
    rows = []
    for seed, (loss, add) in enumerate(zip(losses, added, strict=True)):
        for b, k in (("tsdf", 0), ("octree-max", 1)):
            base = {"seed": seed, "backend": b, "n_points": 100, "error_std_m": 0.01}
            rows += [
                {**base, "sweep": "label", "level": "none", "classification_ratio": 0.95,
                 "error_mean_m": 0.03},
                {**base, "sweep": "label", "level": "high",
                 "classification_ratio": 0.95 - loss[k], "error_mean_m": 0.03},
                {**base, "sweep": "pose", "level": "high", "classification_ratio": 0.9,
                 "error_mean_m": 0.03 + add[k]},
            ]  # fmt: skip
    return rows


def test_noise_claims_are_decided_by_intervals_over_seeds():
    from smana.lab.experiments import noise

    losses = [(0.10, 0.31), (0.12, 0.29), (0.11, 0.30), (0.105, 0.305)]
    added = [(0.002, 0.010), (0.003, 0.012), (0.001, 0.011), (0.002, 0.013)]
    c = {k: v for k, v in enumerate(noise.claims(_noise_rows(losses, added)))}
    assert [c[k]["verdict"] for k in range(5)] == [stats.REPRODUCED] * 5
    # against the obvious computation: the interval of the per-seed values
    ref = stats.mean_ci([a[1] - a[0] for a in added])
    assert c[4]["smana"].mean == pytest.approx(ref.mean)
    assert c[4]["smana"].lo == pytest.approx(ref.lo)
    assert c[0]["smana"].mean == pytest.approx(np.mean([x[0] for x in losses]))
    # the losses far from the paper's and the effect reversed
    far = noise.claims(_noise_rows([(0.3, 0.1), (0.31, 0.11)], [(0.010, 0.001), (0.0105, 0.0015)]))
    assert [x["verdict"] for x in far] == [stats.NOT_REPRODUCED] * 5
    # one seed: no interval, every claim inconclusive
    one = noise.claims(_noise_rows(losses[:1], added[:1]))
    assert {x["verdict"] for x in one} == {stats.INCONCLUSIVE}


def _tiny():
    from smana.lab.experiments import noise

    return noise.NoiseExperimentConfig(
        seeds=(3, 4),
        size_m=6.0,
        length_m=1.5,
        spacing_m=0.5,
        image_px=64,
        resolution_m=0.1,
        gt_spacing_m=0.08,
        backends=("tsdf",),
        levels=("none", "high"),
    )


def test_noise_rows_do_not_depend_on_the_number_of_jobs(tmp_path):
    from smana.lab.experiments import noise

    one = noise.run_noise(_tiny(), tmp_path / "j1", jobs=1)  # in this process
    two = noise.run_noise(_tiny(), tmp_path / "j2", jobs=2)  # two workers
    assert not one.failures and not two.failures
    assert [r["seed"] for r in one.rows] == [3, 3, 3, 4, 4, 4]

    def strip(rows):  # everything but the timings
        return [{k: v for k, v in r.items() if "cpu" not in k} for r in rows]

    assert strip(one.rows) == strip(two.rows)


def test_noise_a_failed_seed_is_reported_and_the_others_go_on(tmp_path):
    # seed -1: the garden's SeedSequence refuses a negative seed, so that worker raises at once
    argv = ["noise", "--quick", "--first-seed", "-1", "--seeds", "2", "--backends", "tsdf"]
    assert exp.cli([*argv, "--out", str(tmp_path)]) == 1
    text = (tmp_path / "noise_summary.md").read_text()
    assert text.splitlines()[2].startswith("> **WARNING: 1 of 2 seeds failed**")
    assert "seed -1: ValueError" in text
    data = json.loads((tmp_path / "noise_results.json").read_text())
    assert {r["seed"] for r in data["rows"]} == {0}
    # one seed left: no interval, so no claim can be decided
    assert {c["verdict"] for c in data["claims"]} == {stats.INCONCLUSIVE}


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
