"""The experiments: the fixed trajectory, `smana experiment noise --quick`, and the exploration
experiment's tables and plot (its runs of the whole stack are in test_e2e_*)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from smana.lab import evaluation as ev
from smana.lab import experiments as exp
from smana.lab import stats
from smana.lab.experiments import exploration_report as exr


def test_fixed_trajectory_is_long_smooth_and_clear_of_obstacles():
    from smana.services.sim.worlds.garden import generate

    world = generate(3, size_m=12.0)
    poses = exp.fixed_trajectory(world, length_m=44.0, spacing_m=0.25)
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    # cut at 44 m; smoothing the raster path can leave a tour a few per cent shorter
    assert 0.95 * 44.0 <= steps.sum() <= 44.0
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
    # a quick run says so first: its verdicts test the tooling, not the paper
    assert lines[2].startswith("> **Quick run**")
    assert lines[4] == "| claim | paper | smana mean [95 % CI] (n) | verdict |"
    verdicts = [ln.rsplit("|", 2)[1].strip() for ln in lines[6:11]]
    assert len(verdicts) == 5 and set(verdicts) <= set(stats.VERDICTS)
    assert "(n = 2)" in lines[6] and "WARNING" not in text
    assert "Classification loss" in text and "CPU time per seed" in text
    # the data file records the command that made it, how long it took and when
    meta = json.loads((tmp_path / "data" / "noise.json").read_text())["meta"]
    assert meta["command"] == "smana experiment noise --quick --out <out>"  # no path of a machine
    assert meta["jobs"] >= 1 and meta["wall_s"] > 0 and len(meta["date"]) == 10
    # the compact raw rows docs/experiments/data/ would hold, one per seed, back-end and level
    compact = json.loads((tmp_path / "data" / "noise.json").read_text())["rows"]
    assert len(compact) == len(rows) and {"f_score", "completeness"} <= set(compact[0])


def _noise_rows(losses, added):
    """Rows of a noise run: per seed, the tsdf and octree-max classification ratio loss over the
    label sweep and reconstruction error added over the pose sweep."""
    rows = []
    for seed, (loss, add) in enumerate(zip(losses, added, strict=True)):
        for b, k in (("tsdf", 0), ("octree-max", 1)):
            base = {"seed": seed, "backend": b, "n_points": 100, "error_std_m": 0.01}
            rows += [
                {**base, "sweep": "label", "level": "none", "classification_ratio": 0.95,
                 "error_mean_m": 0.03, "f_score": 0.9},
                {**base, "sweep": "label", "level": "high",
                 "classification_ratio": 0.95 - loss[k], "error_mean_m": 0.03, "f_score": 0.9},
                {**base, "sweep": "pose", "level": "high", "classification_ratio": 0.9,
                 "error_mean_m": 0.03 + add[k], "f_score": 0.9 - 10 * add[k]},
            ]  # fmt: skip
    return rows


def test_noise_claims_are_decided_by_intervals_over_seeds():
    from smana.lab.experiments import noise_report as noise

    losses = [(0.10, 0.31), (0.12, 0.29), (0.11, 0.30), (0.105, 0.305)]
    added = [(0.002, 0.010), (0.003, 0.012), (0.001, 0.011), (0.002, 0.013)]
    c = {k: v for k, v in enumerate(noise.claims(_noise_rows(losses, added)))}
    assert [c[k]["verdict"] for k in range(5)] == [stats.REPRODUCED] * 5
    # against the obvious computation: the interval of the per-seed values
    ref = stats.mean_ci([a[1] - a[0] for a in added])
    assert c[4]["smana"].mean == pytest.approx(ref.mean)
    assert c[4]["smana"].lo == pytest.approx(ref.lo)
    assert c[0]["smana"].mean == pytest.approx(np.mean([x[0] for x in losses]))
    # (b) and (c) are paired per seed too: octree-max's loss minus tsdf's
    assert c[2]["smana"].mean == pytest.approx(np.mean([x[1] - x[0] for x in losses]))
    assert c[3]["smana"].mean == pytest.approx(np.mean([10 * (a[1] - a[0]) for a in added]))
    assert c[3]["claim"].startswith("(c) tsdf more robust") and "F-score" in c[3]["claim"]
    # a TSDF that gains accuracy by leaving surface out is not more robust: (c) follows F
    pruned = _noise_rows(losses, added)
    for r in pruned:
        if r["backend"] == "tsdf" and r["sweep"] == "pose":
            r["f_score"] = 0.5
    c = noise.claims(pruned)
    assert c[3]["verdict"] == stats.NOT_REPRODUCED and c[4]["verdict"] == stats.REPRODUCED
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
    import dataclasses

    from smana.lab.experiments import noise

    # seed -1: the garden's SeedSequence refuses a negative seed, so that worker raises at once
    # (the command line refuses it before running: a misuse, status 2)
    with pytest.raises(SystemExit) as refused:
        exp.cli(["noise", "--quick", "--first-seed", "-1", "--out", str(tmp_path / "no")])
    assert refused.value.code == 2 and not (tmp_path / "no").exists()
    settings = dataclasses.replace(_tiny(), seeds=(-1, 0))
    run = noise.run_noise(settings, tmp_path, jobs=2)
    assert set(run.failures) == {-1}
    text = (tmp_path / "noise_summary.md").read_text()
    assert text.splitlines()[2].startswith("> **WARNING: 1 of 2 seeds failed**")
    assert "seed -1: ValueError" in text
    data = json.loads((tmp_path / "noise_results.json").read_text())
    assert {r["seed"] for r in data["rows"]} == {0}
    # one seed left: no interval, so no claim can be decided
    assert {c["verdict"] for c in data["claims"]} == {stats.INCONCLUSIVE}


def _run(seed, arm, share=0.6, dist=40.0, reach_at=None, code=0, n=11):
    """A synthetic exploration row: coverage rises linearly with distance to 0.97 at `dist`
    (or to 0.9 and never 95 % with reach_at=False)."""
    from smana.lab.experiments import exploration as ex

    end = 0.97 if reach_at is not False else 0.9
    hist = [(10.0 * k, 5.0 * k, 3, dist * k / (n - 1)) for k in range(n)]
    m = {
        # the curve ends at the known share; the usable coverage (`coverage`) a little under it
        "exploration": {
            "terrain_share": share,
            "coverage": end - 0.05,
            "known_reachable_share": end,
            "distance_m": dist,
        },
        "explorer": {
            "explored_m2": hist[-1][1],
            "done_reason": "no_frontier",
            "elapsed_s": 100.0,
            "wall_time_s": 125.0,
        },
    }
    if code:
        m = {}
    return ex.make_row(seed, arm, code, m, {"history": hist} if not code else {}, 50.0, 60.0)


def test_coverage_curve_is_rescaled_to_ground_truth_and_censored():
    from smana.lab.experiments import exploration as ex

    hist = [(100.0, 0.0, 5, 0.0), (110.0, 10.0, 4, 5.0), (120.0, 20.0, 0, 9.0)]
    t, d, cov = ex.coverage_curve(hist, 20.0, 0.96)
    # slow reference: each row's count over the final count, times the ground-truth end
    assert cov.tolist() == pytest.approx([r[1] / 20.0 * 0.96 for r in hist])
    assert t.tolist() == [0.0, 10.0, 20.0] and d.tolist() == [0.0, 5.0, 9.0]
    assert ex.first_reach(d, cov) == 9.0
    assert ex.first_reach(d, np.minimum(cov, 0.94)) is None  # censored, not a number
    assert all(len(a) == 0 for a in ex.coverage_curve(hist, 20.0, None))
    row = _run(3, ex.nbv(2.0), reach_at=False)
    assert row["distance_to_95_m"] is None and row["time_to_95_s"] is None
    row = _run(3, ex.nbv(2.0), dist=40.0)
    # 0.97 * k / 10 >= 0.95 first at k = 10 (0.97 * 0.9 = 0.873)
    assert row["distance_to_95_m"] == pytest.approx(40.0) and row["time_to_95_s"] == 100.0
    assert row["real_time_factor"] == 0.8


def test_mean_curve_holds_the_last_value_and_gives_a_band():
    from smana.lab.experiments import exploration as ex

    rows = [_run(s, ex.nbv(2.0), dist=d) for s, d in ((3, 20.0), (4, 40.0))]
    grid, mean, lo, hi = exr.mean_curve(rows, "distance_m", n_points=5)
    assert grid.tolist() == [0.0, 10.0, 20.0, 30.0, 40.0]
    ref = [
        np.mean([np.interp(x, r["curve"]["distance_m"], r["curve"]["coverage"]) for r in rows])
        for x in grid
    ]
    assert mean.tolist() == pytest.approx(ref)
    assert mean[-1] == pytest.approx(0.97)  # the short run keeps its final coverage
    assert np.all(lo[1:-1] < mean[1:-1]) and np.all(hi[1:-1] > mean[1:-1])


def _verdict(table, start):
    (v,) = [v for v in table if v["claim"].startswith(start)]
    return v["verdict"]


def test_exploration_verdicts_from_synthetic_rows(tmp_path):
    from smana.lab import stats
    from smana.lab.experiments import exploration as ex

    rows = []
    for seed in (3, 4, 5):
        for f, share in ((1.0, 0.60), (2.0, 0.70), (4.0, 0.88)):
            rows.append(_run(seed, ex.nbv(f), share + 0.01 * (seed - 4), dist=30.0 + seed))
        rows.append(_run(seed, ex.BASELINE, 0.65, dist=60.0 + seed))
    table = exr.verdicts(rows)
    assert _verdict(table, "terrain share at grass x1") == stats.REPRODUCED
    assert _verdict(table, "terrain share rises") == stats.REPRODUCED
    assert _verdict(table, "NBV reaches") == stats.REPRODUCED
    # the baseline is better: not reproduced; far from the paper: not reproduced
    worse = [
        {**r, "distance_to_95_m": 200.0 + r["seed"]} if r["strategy"] == "nbv" else r for r in rows
    ]
    assert _verdict(exr.verdicts(worse), "NBV reaches") == stats.NOT_REPRODUCED
    far = [{**r, "terrain_share": 0.2 + 0.01 * r["seed"]} for r in rows]
    assert _verdict(exr.verdicts(far), "terrain share at grass x4") == stats.NOT_REPRODUCED
    # baseline runs that never reached 95 % are kept: not reached within the budget, censored
    # beyond every distance: still decided, not dropped
    few = [
        {**r, "distance_to_95_m": None}
        if r["strategy"] == "nearest_frontier" and r["seed"] > 3
        else r
        for r in rows
    ]
    v = next(v for v in exr.verdicts(few) if v["claim"].startswith("NBV reaches"))
    assert v["verdict"] == stats.REPRODUCED and v["p_tests"] == "NBV sooner"
    assert "log-rank p = " in v["smana"] and "two-sided; the data lean to NBV sooner" in v["smana"]
    assert "NBV first in 3 of 3 seeds whose order is known" in v["smana"]
    # runs that stopped early (after 5 m) without reaching it never count as reaching it later:
    # censored beyond every distance, not at the 5 m they drove
    early = [{**r, "distance_m": 5.0} if r["distance_to_95_m"] is None else r for r in few]
    assert _verdict(exr.verdicts(early), "NBV reaches") == stats.REPRODUCED
    # a robot that did not move counts as not reached even if its camera saw 95 % from its start
    still = [{**r, "moved": False} if r["strategy"] == "nbv" else r for r in rows]
    assert ex.time_to_event(still[0], "distance_to_95_m", math.inf) == (math.inf, True)
    assert _verdict(exr.verdicts(still), "NBV reaches") == stats.NOT_REPRODUCED
    # the rise is tested for its size: +28 points with a 10-point tolerance, not only > 0
    small = [
        {**r, "terrain_share": r["terrain_share"] - 0.25}
        if r["grass_cost_factor"] == 4.0 and r["strategy"] == "nbv"
        else r
        for r in rows
    ]
    assert _verdict(exr.verdicts(small), "terrain share rises") == stats.NOT_REPRODUCED
    # the world's own routes rule the paper's x1 share out: said so, with the evidence
    routes = {1.0: stats.Interval(0.85, 0.82, 0.88, 3)}
    (x1,) = [v for v in exr.verdicts(rows, routes) if "x1," in v["claim"]]
    assert x1["verdict"] == stats.NOT_REPRODUCIBLE_HERE and x1["evidence"].startswith("routes")

    s = ex.ExplorationExperimentConfig(seeds=(3, 4, 5))
    exr.write_exploration_outputs(rows, s, tmp_path)
    text = (tmp_path / "exploration_summary.md").read_text()
    assert text.splitlines()[2].startswith("| claim | paper | smana mean [95 % CI] (n) |")
    assert "WARNING" not in text
    data = json.loads((tmp_path / "exploration_results.json").read_text())
    x1 = data["summary"][0]
    compact = json.loads((tmp_path / "data" / "exploration.json").read_text())["rows"]
    assert len(compact) == len(rows) and "curve" not in compact[0]
    assert x1["arm"] == "nbv_x1" and x1["terrain_share"]["mean"] == pytest.approx(0.60)
    assert x1["reached_95"] == 3
    assert x1["km_median_distance_to_95_m"] == pytest.approx(34.0)  # of 33, 34, 35 m
    assert "distance_to_95_m" not in x1  # no mean over the runs that reached it
    assert x1["km_time_to_95_s"]["rmst"]["horizon"] == s.budget_s
    # two of three never reach 95 %: kept as not reached within the budget; no median
    arm = ex.nbv(2.0)
    runs = [_run(3, arm, dist=20.0)] + [_run(s, arm, reach_at=False) for s in (4, 5)]
    (d,) = exr.summarise_exploration(runs)
    assert d["reached_95"] == 1 and d["km_median_distance_to_95_m"] is None
    (d,) = exr.summarise_exploration(runs[:2] + [_run(5, arm, dist=30.0)])
    assert d["km_median_distance_to_95_m"] == pytest.approx(30.0)  # 20, 30 reached; 1 not
    assert exr.format_km(d["km_distance_to_95_m"]).startswith("30.0 [")
    assert exr.format_km(exr.summarise_exploration(runs)[0]["km_distance_to_95_m"]) == (
        "not reached by half (n = 3)"
    )
    for name in ("terrain_share", "coverage_distance", "coverage_time"):
        assert (tmp_path / f"exploration_{name}.png").stat().st_size > 1000


def test_a_failed_run_is_counted_warned_at_the_top_and_exits_non_zero(tmp_path, monkeypatch):
    from smana.lab.experiments import exploration as ex

    arms = (ex.nbv(1.0), ex.nbv(4.0))

    def fake_run(out, seed, arm, s, spawn=None):
        if seed == 4 and arm.grass_cost_factor == 4.0:
            return 1, {}, {}, 1.0, 2.0  # crashed: non-zero exit, no metrics
        r = _run(seed, arm, 0.6 if arm.grass_cost_factor == 1 else 0.8)
        m = {"exploration": {k: r[k] for k in ("terrain_share", "coverage", "distance_m")}}
        m["exploration"]["known_reachable_share"] = r["known_share"]
        return 0, m, {}, 1.0, 2.0

    monkeypatch.setattr(ex, "exploration_run", fake_run)
    monkeypatch.setattr(ex, "pick_spawn", lambda seed, size_m, sets: [0.0, 0.0, 0.0])
    s = ex.ExplorationExperimentConfig(seeds=(3, 4), arms=arms, jobs=2)
    rows = ex.run_exploration(s, tmp_path, log=lambda _: None)
    assert sum(not r["ok"] for r in rows) == 1
    assert ex.finish(rows, tmp_path, "exploration") == 1
    lines = (tmp_path / "exploration_summary.md").read_text().splitlines()
    assert lines[2].startswith("**WARNING: 1 of 4 runs failed**")
    assert "seed4_nbv_x4 (exit 1)" in lines[2]
    summary = json.loads((tmp_path / "exploration_results.json").read_text())["summary"]
    assert [(d["arm"], d["runs"], d["failed"]) for d in summary] == [
        ("nbv_x1", 2, 0),
        ("nbv_x4", 2, 1),
    ]


def test_pick_spawn_is_a_reachable_free_cell_and_depends_on_the_seed():
    from smana.lab.experiments import exploration as ex
    from smana.services.sim.worlds.garden import generate

    a, b = ex.pick_spawn(3, 6.0), ex.pick_spawn(4, 6.0)
    assert a == ex.pick_spawn(3, 6.0) and a != b
    world = generate(3, size_m=6.0, layout="3drms")  # the experiment's world
    trav = world.traversability(ex.SPAWN_CLEARANCE_M)
    assert trav.data[trav.index_of(a[0], a[1])]
    assert -np.pi <= a[2] <= np.pi


def test_ablation_outputs_from_synthetic_rows(tmp_path):
    from smana.lab.experiments import ablation
    from smana.lab.experiments import exploration as ex

    arms = ablation.weight_arms(4.0, (0.0, 1.0))
    assert arms[1].all_sets == (f"{ex.WEIGHT_KEY}=1.0",)
    rows = [_run(s, a, 0.7 + 0.1 * a.path_cost_weight, dist=30.0) for a in arms for s in (3, 4)]
    s = ex.ExplorationExperimentConfig(seeds=(3, 4))
    ablation.write_ablation_outputs(rows, s, tmp_path, wall_s=600.0)
    text = (tmp_path / "ablation_summary.md").read_text()
    assert "| 0 | x4 | 2 (0) | 70.0 %" in text and "| 1 | x4 | 2 (0) | 80.0 %" in text
    assert (tmp_path / "ablation.png").stat().st_size > 1000
    # the compact rows the doc's table is generated from: the same table, from the data alone
    from smana.lab.experiments import report

    data = report.load_data(tmp_path / "data")["ablation"]
    assert set(data["rows"][0]) == set(ablation.DATA_KEYS)
    assert data["meta"]["budget_s"] == s.budget_s and data["meta"]["wall_s"] == 600.0
    doc = report.sections({"ablation": data})["ablation"]
    table = [ln for ln in text.splitlines() if ln.startswith("| ")]
    assert table and all(ln in doc.splitlines() for ln in table)
    assert "seeds 3, 4" in doc and "10 min 0 s wall" in doc and "none failed" in doc
    # a failed run is said, and left out of the intervals
    rows[0] = _run(3, arms[0], code=1)
    ablation.write_ablation_outputs(rows, s, tmp_path)
    doc = report.ablation_section(report.load_data(tmp_path / "data")["ablation"])
    assert "**1 failed**" in doc and "| 0 | x4 | 2 (1) | 70.0 % (n = 1, no interval)" in doc


def test_noise_backend_variants_and_sweeps():
    """A variant changes the back-end's config section (an ablation on the same frames); a bad
    spec is one line naming what is wrong."""
    from smana.lab.experiments import noise
    from smana.services.mapper.backends.tsdf import TsdfConfig

    assert noise.parse_backend("octree-max") == ("octree-max", None)
    name, cfg = noise.parse_backend("tsdf@truncation_voxels=4+min_weight=2")
    assert name == "tsdf" and cfg == TsdfConfig(truncation_voxels=4.0, min_weight=2.0)
    assert noise.parse_backend("tsdf@use_weight_dropoff=false")[1].use_weight_dropoff is False
    # octree-max's earlier same-label rule, as a variant beside the default
    assert noise.parse_backend("octree-max@max_fusion=gain")[1].max_fusion == "gain"
    for bad, words in (
        ("nope", "unknown back-end"),
        ("tsdf@nope=1", "KEY=VALUE"),
        ("tsdf@max_weight=x", "takes a float"),
        ("tsdf@truncation_voxels=0", "truncation_voxels"),
        ("octree-max@max_fusion=nope", "max_fusion"),
    ):
        with pytest.raises(ValueError, match=words):
            noise.parse_backend(bad)
    # a pose sweep alone still maps "none" once (as the label row both sweeps share)
    assert noise._configs(("none", "high"), ("pose",)) == [
        ("label", "none", "none", "none"),
        ("pose", "high", "none", "high"),
    ]
    assert [c[1] for c in noise._configs(noise.LEVELS, ("label",))] == list(noise.LEVELS)
    order = sorted(["tsdf@min_weight=2", "octree-max", "tsdf"], key=noise.backend_order)
    assert order == ["octree-max", "tsdf", "tsdf@min_weight=2"]


def test_route_terrain_share_takes_the_cheapest_branch():
    """A one-cell-wide ring of 5 x 5 cells, from corner (0, 0) to corner (4, 0): up the left side
    (3 grass cells, then a terrain one) or round the right (10 terrain steps, two of them
    diagonal). Each step pays its length plus 0.8 x the class cost x 0.1 / 0.2. Grass x1: left
    2.0 against right 5.08; grass x4: left 3 x 1.7 + 0.5 = 5.6, so the terrain detour wins."""
    from smana.lab.experiments import routes

    reach = np.zeros((5, 5), bool)
    reach[0, :] = reach[4, :] = reach[:, 0] = reach[:, 4] = True  # the ring
    top = np.full((5, 5), routes.TERRAIN, np.uint16)
    top[1:4, 0] = routes.GRASS  # the left side
    shares = {}
    for factor in (1.0, 4.0):
        cost = np.where(top == routes.GRASS, factor, 1.0)
        g, cells = routes._graph(reach, cost, 0.1, 0.8, 0.2)
        node = {tuple(c): k for k, c in enumerate(cells)}
        shares[factor] = routes.route_shares(g, cells, top, [node[(0, 0)]], [[node[(4, 0)]]])
    # x1: cells entered (1,0) (2,0) (3,0) grass, (4,0) terrain -> 1 of 4 on terrain
    assert shares[1.0] == pytest.approx(0.25)
    assert shares[4.0] == pytest.approx(1.0)  # round the right: terrain only


def test_grid_graph_matches_a_loop_over_cells():
    """ev.grid_graph (the noise tour's and the routes' graph) against a plain loop."""
    import math

    mask = np.random.default_rng(5).random((9, 7)) < 0.6
    offsets = ((0, 1), (1, 0), (1, 1), (1, -1), (0, -1), (-1, 0), (-1, -1), (-1, 1))
    cost = np.random.default_rng(6).random(mask.shape)
    g, cells, idx = ev.grid_graph(mask, offsets, lambda b, step: step + cost[b[:, 0], b[:, 1]])
    want = {}
    for i, j in zip(*np.nonzero(mask), strict=True):
        for di, dj in offsets:
            a, b = i + di, j + dj
            if 0 <= a < mask.shape[0] and 0 <= b < mask.shape[1] and mask[a, b]:
                want[(idx[i, j], idx[a, b])] = math.hypot(di, dj) + cost[a, b]
    coo = g.tocoo()
    got = {(int(r), int(c)): v for r, c, v in zip(coo.row, coo.col, coo.data, strict=True)}
    assert got.keys() == want.keys()
    assert all(got[k] == pytest.approx(want[k]) for k in want)
    assert [tuple(c) for c in cells] == [tuple(c) for c in np.argwhere(mask)]
