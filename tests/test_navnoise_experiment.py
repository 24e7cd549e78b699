"""`smana experiment navnoise` (beyond the paper): its arms, its rules decided on synthetic rows,
its outputs from faked runs, the report's generated section, and (multi-process, slow) the quick
form of the whole stack under label and pose noise."""

from __future__ import annotations

import json

import pytest

from smana.lab import experiments as exp
from smana.lab import stats
from smana.lab.experiments import exploration as ex
from smana.lab.experiments import navnoise as nn
from smana.lab.experiments import report


def _rows(true_drop=0.01, cov_drop=0.0, tsdf_gain=0.0, seeds=(3, 4, 5, 6, 7)):
    """Synthetic rows: per seed a base share, the noisy arms `true_drop` lower (plus a small
    per-seed wobble), tsdf's noisy arm `tsdf_gain` above octree-max's."""
    rows = []
    for c in nn.CONDITIONS:
        for s in seeds:
            share = 0.80 + 0.02 * (s - 5)
            cov = 0.99
            if c.perception == "noisy":
                share -= true_drop + 0.002 * (s % 2)
                cov -= cov_drop
                if c.backend == "tsdf":
                    share += tsdf_gain + 0.001 * s
            rows.append(
                {"seed": s, "arm": c.name, "backend": c.backend, "perception": c.perception,
                 "ok": True,
                 "terrain_share_true": share, "coverage": cov, "time_to_95_s": 30.0}
            )  # fmt: skip
    return rows


def test_the_arms_are_the_two_backends_with_and_without_the_papers_noise():
    sets = {a.name: a.all_sets for a in nn.ARMS}
    assert list(sets) == ["octree_max_clean", "octree_max_noisy", "tsdf_clean", "tsdf_noisy"]
    assert all(a.grass_cost_factor == 4.0 and a.strategy == "nbv" for a in nn.ARMS)
    # p = 0.7 is the sim's "high" level; the pose noise is the noise experiment's highest
    from smana.services.sim.degrade import NOISE_LEVELS

    assert NOISE_LEVELS[nn.LABEL_NOISE] == 0.7
    assert nn.POSE_NOISE[nn.POSE_LEVEL] == max(nn.POSE_NOISE.values())
    assert sets["tsdf_noisy"] == (
        'mapper.backend="tsdf"',
        'sim.noise="high"',
        "sim.pose_noise_xy_m=0.1",
        "sim.pose_noise_yaw_rad=0.02",
    )
    assert 'sim.noise="none"' in sets["octree_max_clean"]
    # one noise at a time: arms that `--arms` adds, to tell which noise did what
    extra = {c.name: c.arm().all_sets for c in nn.EXTRA_CONDITIONS}
    assert extra["tsdf_label"][1:] == ('sim.noise="high"', *sets["tsdf_clean"][2:])
    assert extra["tsdf_pose"][1:] == ('sim.noise="none"', *sets["tsdf_noisy"][2:])
    # each run's robot is named exp<pid>-s<seed>-<arm> (exploration.py), a key chunk of at most
    # 32 characters: it fits with the largest pid Linux gives and a two-digit seed
    from smana.common.keys import check_name

    for c in (*nn.CONDITIONS, *nn.EXTRA_CONDITIONS):
        check_name(f"exp{2**22}-s99-{c.name}")
    args = type("Args", (), {"arms": "octree_max_pose, tsdf_clean"})()
    assert [a.name for a in nn._arms(args)] == ["octree_max_pose", "tsdf_clean"]
    assert "sim.pose_noise_xy_m=0.0" in sets["octree_max_clean"]
    # every arm's overrides load as a config (a typo would fail every run)
    from smana.common.config import SmanaConfig

    for a in nn.ARMS:
        cfg = SmanaConfig.load(overrides=[*ex.WORLD_SETS, *a.all_sets])
        assert cfg.mapper.backend in nn.BACKENDS


def test_verdicts_follow_the_rules_declared_before_the_run():
    small = {v["claim"].split(",")[0] + v["rule"]: v for v in nn.verdicts(_rows(true_drop=0.01))}
    assert len(nn.verdicts(_rows())) == 5
    # a drop of about 1 point, tight over 5 seeds: within the 5-point margin, met
    assert small["octree-maxnot worse"]["verdict"] == stats.REPRODUCED
    # a drop of 20 points: wholly beyond the margin, not met
    big = nn.verdicts(_rows(true_drop=0.20))
    assert [v["verdict"] for v in big[:2]] == [stats.NOT_REPRODUCED] * 2
    # coverage: unchanged is met; the back-end comparison with no difference is not "better"
    assert [v["verdict"] for v in big[2:4]] == [stats.REPRODUCED] * 2
    assert nn.verdicts(_rows(cov_drop=0.3))[2]["verdict"] == stats.NOT_REPRODUCED
    better = nn.verdicts(_rows(tsdf_gain=0.05))[4]
    assert better["verdict"] == stats.REPRODUCED and better["rule"] == "above 0"
    worse = nn.verdicts(_rows(tsdf_gain=-0.05))[4]
    assert worse["verdict"] == stats.NOT_REPRODUCED
    # the single-noise arms (--arms) change no verdict
    rows = _rows(true_drop=0.01)
    extra = [
        {**r, "arm": f"{r['backend'].replace('-', '_')}_{p}", "perception": p,
         "terrain_share_true": 0.1, "coverage": 0.1}
        for r in rows if r["perception"] == "noisy" for p in ("label", "pose")
    ]  # fmt: skip
    assert nn.verdicts(rows + extra) == nn.verdicts(rows)
    # paired per seed: the difference's interval, not the arms' overlapping intervals
    d = nn.paired(_rows(true_drop=0.01), "terrain_share_true", ("tsdf", "clean"), ("tsdf", "noisy"))
    assert d.n == 5 and d.hi < 0 and d.lo > -0.05


def test_a_seed_missing_in_one_arm_is_left_out_of_the_pair_and_one_seed_is_inconclusive():
    rows = _rows()
    for r in rows:
        if r["seed"] == 7 and r["arm"] == "tsdf_noisy":
            r["terrain_share_true"] = None  # no true trajectory in that run
    d = nn.paired(rows, "terrain_share_true", ("tsdf", "clean"), ("tsdf", "noisy"))
    assert d.n == 4
    one = nn.verdicts(_rows(seeds=(3,)))
    assert {v["verdict"] for v in one} == {stats.INCONCLUSIVE}


def test_the_true_share_comes_only_from_the_true_trajectory():
    m = {"exploration": {"trajectory_source": "ground truth", "terrain_share": 0.9,
                         "terrain_share_map": 0.95, "collisions": 1, "close_calls": 2,
                         "distance_m": 5.0}}  # fmt: skip
    got = nn.ground_truth_fields(m)
    assert got["terrain_share_true"] == 0.9 and got["terrain_share_map"] == 0.95
    assert got["collisions"] == 1 and got["close_calls"] == 2 and got["moved"]
    # a robot that stood still has no path to score, whatever node it stood on
    m["exploration"]["distance_m"] = 0.05
    got = nn.ground_truth_fields(m)
    assert got["terrain_share_true"] is None and not got["moved"]
    m["exploration"]["distance_m"] = 5.0
    # the report fell back to the published (noisy) pose: no true share, said so
    m["exploration"]["trajectory_source"] = "published pose"
    got = nn.ground_truth_fields(m)
    assert got["terrain_share_true"] is None and got["trajectory_source"] == "published pose"


def test_outputs_from_faked_runs_warn_count_and_write_the_data_file(tmp_path, monkeypatch):
    def fake_run(out, seed, arm, s, spawn=None):
        if seed == 4 and arm.name == "tsdf_noisy":
            return 1, {}, {}, 1.0, 2.0  # crashed: non-zero exit, no metrics
        noisy = "noisy" in arm.name
        source = "published pose" if (seed == 4 and arm.name == "octree_max_noisy") else None
        # seed 3, octree-max under noise: the robot never moves; `smana up` exits 1 for that
        still = seed == 3 and arm.name == "octree_max_noisy"
        e = {
            "terrain_share": 0.7 if noisy else 0.8,
            "terrain_share_map": 0.9,
            "coverage": 0.98,
            "distance_m": 0.03 if still else 12.0,
            "trajectory_source": source or "ground truth",
            "collisions": 1 if noisy else 0,
            "close_calls": 2,
        }
        run_dir = out / ex.run_name(seed, arm)
        run_dir.mkdir(parents=True)
        m = {"exploration": e, "warnings": ["the robot did not move (0.03 m travelled)"] * still}
        (run_dir / "metrics.json").write_text(json.dumps(m))
        return int(still), m, {}, 1.0, 2.0

    monkeypatch.setattr(ex, "exploration_run", fake_run)
    monkeypatch.setattr(ex, "pick_spawn", lambda seed, size_m, world_sets=None: [0.0, 0.0, 0.0])
    s = nn.experiment_config()
    s.seeds = (3, 4)
    rows = ex.run_exploration(s, tmp_path, log=lambda _: None, write=nn.write_outputs)
    assert ex.finish(rows, tmp_path, "navnoise") == 1
    lines = (tmp_path / "navnoise_summary.md").read_text().splitlines()
    assert lines[2].startswith("**WARNING: 1 of 8 runs failed**") and "seed4_tsdf_noisy" in lines[2]
    assert lines[4].startswith("**WARNING: 1 run(s) have no true trajectory**")
    assert "published pose" in lines[4]
    data = json.loads((tmp_path / "data" / "navnoise.json").read_text())
    by = {(r["seed"], r["arm"]): r for r in data["rows"]}
    assert by[(3, "tsdf_noisy")]["terrain_share_true"] == 0.7
    assert by[(3, "tsdf_noisy")]["backend"] == "tsdf"
    assert by[(3, "tsdf_noisy")]["perception"] == "noisy"
    assert by[(3, "tsdf_noisy")]["label_noise"] == "high"
    assert by[(4, "octree_max_noisy")]["terrain_share_true"] is None
    # a robot that never moved is a result (counted, no path to score), not a failed run
    still = by[(3, "octree_max_noisy")]
    assert still["ok"] and still["exit_code"] == 1 and not still["moved"]
    assert still["terrain_share_true"] is None and still["coverage"] == 0.98
    assert "| seed3_octree_max_noisy | 1 | ground truth | - |" in "\n".join(lines)
    v = nn.verdicts(rows)[0]
    assert "the robot did not move in 1 of 2 noisy runs" in v["evidence"]
    assert by[(3, "octree_max_clean")]["pose_noise_xy_m"] == 0.0
    # the arm table: contacts added over the arm's runs, true share beside the map's
    table = "\n".join(nn.arm_table(rows))
    # octree-max under noise: seed 3 stood still (a failure: 0 true share, 0 coverage), seed 4
    # has no true trajectory
    still_row = next(r for r in table.splitlines() if r.startswith("| octree-max, noisy |"))
    assert still_row.startswith(
        "| octree-max, noisy | 2 (0) | 0.0 % (n = 1, no interval) | - (n = 0) | 49.0 % ["
    )
    assert "| 2 (1) | 70.0 % (n = 1, no interval) |" in table  # tsdf noisy: seed 4 crashed
    # octree-max noisy: 1 FAILED, 1 stood still, 2 contacts, 4 calls
    assert still_row.endswith("| 1 | 1 | 2 | 4 |")
    assert (tmp_path / "navnoise_terrain_share.png").stat().st_size > 1000


def test_report_generates_the_navnoise_section_and_its_claims(tmp_path):
    doc = tmp_path / "experiments.md"
    doc.write_text(
        "# page\n\n<!-- generated: verdicts -->\n<!-- end generated: verdicts -->\n\n"
        "<!-- generated: navnoise -->\nold\n<!-- end generated: navnoise -->\n"
    )
    # no data: the section says so, and no claim is made up
    text, changed = report.regenerate(doc.read_text(), {})
    assert changed == ["verdicts", "navnoise"]
    assert "No raw results of `smana experiment navnoise` are committed yet" in text
    assert "navnoise:" not in text
    report.write_data(tmp_path, "navnoise", _rows())
    assert exp.cli(["report", "--doc", str(doc), "--data", str(tmp_path / "data")]) == 0
    text = doc.read_text()
    assert "Generated from docs/experiments/data/navnoise.json (seeds [3, 4, 5, 6, 7]" in text
    assert "| octree-max, noise-free | 5 (0) |" in text
    assert text.count("| navnoise: ") == 5 and "Holm-adjusted p" in text
    assert exp.cli(["report", "--check", "--doc", str(doc), "--data", str(tmp_path / "data")]) == 0
    assert "quick run" not in text
    # a quick run's data says so on top of the section
    report.write_data(tmp_path, "navnoise", _rows(), {"is_quick": True})
    text, _ = report.regenerate(doc.read_text(), report.load_data(tmp_path / "data"))
    assert "**A quick run's data** (`--quick`)" in text


def test_bad_arms_or_set_is_one_line_and_exit_2(tmp_path, capsys):
    from smana.common.cli import run_command

    for argv in (["--arms", "octree_max_clean,nope"], ["--set", 'sim.noise="loud"']):
        argv = ["navnoise", "--quick", "--out", str(tmp_path / "no"), *argv]
        assert run_command("experiment", exp.cli, argv) == 2
        assert not (tmp_path / "no").exists()
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err
        assert err.startswith("smana experiment: ")


@pytest.mark.multiprocess
@pytest.mark.slow
def test_navnoise_quick(tmp_path):
    # one seed, two arms at once: whole `smana up` runs in the 6 m garden. The two cover both
    # back-ends and both perceptions (what an arm sets); the four arms' verdicts and outputs are
    # tested on faked runs above, and each arm's settings are loaded by the config test
    arms = ["octree_max_clean", "tsdf_noisy"]
    argv = ["navnoise", "--quick", "--seeds", "1", "--arms", ",".join(arms)]
    assert exp.cli([*argv, "--out", str(tmp_path)]) == 0
    runs = json.loads((tmp_path / "navnoise_results.json").read_text())["runs"]
    assert [r["arm"] for r in runs] == arms
    for r in runs:
        # a noisy run may end with the robot standing still (exit 1, a navigation outcome)
        noisy = r["perception"] == "noisy"
        assert r["ok"] and r["exit_code"] in ((0, 1) if noisy else (0,)), r
        # measured on the recorder's true trajectory, not the published (noisy) pose
        assert r["trajectory_source"] == "ground truth", r
        assert r["collisions"] is not None and r["coverage"] > 0.2, r
        if r["moved"] or not noisy:
            assert 0.0 <= r["terrain_share_true"] <= 1.0 and r["distance_m"] > 0.1, r
        else:
            assert r["terrain_share_true"] is None and "did not move" in r["run_warnings"], r
    cfg = (tmp_path / "seed3_tsdf_noisy" / "config.toml").read_text()
    assert 'backend = "tsdf"' in cfg and 'noise = "high"' in cfg
    assert "pose_noise_xy_m = 0.1" in cfg and 'class_costs = ["grass=4.0"]' in cfg
    metrics = json.loads((tmp_path / "seed3_tsdf_noisy" / "metrics.json").read_text())
    assert metrics["config"]["label_noise"] == "high"
    assert metrics["config"]["pose_noise_yaw_rad"] == 0.02
    data = json.loads((tmp_path / "data" / "navnoise.json").read_text())
    assert len(data["rows"]) == 2 and data["experiment"] == "navnoise"
    text = (tmp_path / "navnoise_summary.md").read_text()
    assert text.splitlines()[2].startswith("**Quick run**: 1 seed of 20 s in a 6 m garden")
    assert "WARNING" not in text
