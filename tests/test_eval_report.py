"""The run report on a hand-made run directory over a small simulated world."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.config import SmanaConfig
from smana.deploy import report
from smana.lab.evaluation import world_from_config
from smana.services.mapper.voxel_ply import write_ply


@pytest.fixture
def run(tmp_path):
    # the classic garden: its few large objects keep a map raised 2 cm labelled like the nearest
    # ground-truth point (the dense beds of the default layout move that by a few per cent)
    cfg = SmanaConfig.load(
        None, ["sim.garden.size_m=6.0", "sim.seed=3", 'sim.garden.layout="classic"']
    )
    cfg.write(tmp_path / "config.toml")
    world = world_from_config(cfg)
    # explorer outputs: a straight drive from the spawn point, and a graph that knows x < 0
    x0, y0, _ = world.spawn_pose(0.4)
    t = np.arange(0, 10, 0.1)
    traj = np.column_stack([t, x0 + 0.0 * t, y0 + 0.0 * t, 0.0 * t])
    (tmp_path / "explorer").mkdir()
    np.savetxt(
        tmp_path / "explorer" / "trajectory.csv",
        traj,
        delimiter=",",
        header="t_s,x_m,y_m,yaw_rad",
        comments="",
    )
    res = 0.2
    flags = np.zeros((30, 30), np.uint8)
    flags[:15] = 1
    np.savez(
        tmp_path / "explorer" / "graph.npz",
        origin_xy=np.array([-3.0, -3.0]),
        resolution_m=res,
        labels=np.full((30, 30), 2, np.uint16),
        heights=np.zeros((30, 30), np.float32),
        flags=flags,
    )
    state = {
        "done_reason": "no_frontier",
        "distance_m": 0.0,
        "explored_m2": 18.0,
        "n_goals": 2,
        "label_counts": {"1": 3, "2": 9},
        "wall_time_s": 12.0,
        "plans": [{"goal": [1.0, 1.0]}, {"goal": [-1.0, 1.0]}],
        "history": [[0.0, 1.0, 10, 0.0], [5.0, 9.0, 8, 2.0], [9.0, 18.0, 0, 4.0]],
    }
    (tmp_path / "explorer" / "state.json").write_text(json.dumps(state))
    # the map: every 20th ground-truth point, raised 2 cm, a tenth of them mislabelled grass
    gp, gl = world.gt_cloud(0.03)
    mp = gp[::20] + np.array([0, 0, 0.02], np.float32)
    ml = gl[::20].astype(np.uint16)
    wrong = np.arange(len(ml)) % 10 == 0
    ml[wrong] = np.where(ml[wrong] == 1, 2, 1)
    n = len(mp)
    write_ply(tmp_path / "map.ply", mp, np.zeros((n, 3), np.uint8), ml, np.ones(n, np.float32))
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "sim.log").write_text("ok\n")
    return tmp_path, cfg, world


def test_report_measures_a_run(run):
    run_dir, cfg, world = run
    path = report.write_report(run_dir, cfg)
    m = json.loads((run_dir / "metrics.json").read_text())
    ex = m["exploration"]
    # the graph knows x < 0 only, all of it terrain: about half the reachable area, all usable
    assert 0.3 < ex["coverage"] < 0.7
    assert ex["coverage"] == ex["usable_share"] == ex["known_reachable_share"]
    assert ex["false_obstacle_area_m2"] == 0.0
    assert ex["reachable_area_m2"] > 5
    assert ex["distance_m"] == 0.0 and ex["travelled_nodes"] == 1
    assert ex["min_clearance_m"] >= 0.35  # the spawn point has 0.4 m clearance (a cell's slack)
    assert ex["collisions"] == 0 and ex["trajectory_source"] == "published pose"
    mp = m["map"]
    # raised 2 cm: on the ground the nearest GT point is 2 cm away, on walls of objects closer
    assert 0.008 < mp["reconstruction_error_mean_m"] <= 0.02 + 1e-6
    assert mp["classification_ratio"] == pytest.approx(0.9, abs=0.02)
    assert m["explorer"]["map_label_share"] == {"grass": 0.25, "terrain": 0.75}
    for png in m["files"]["plots"].values():
        assert (run_dir / png).stat().st_size > 1000
    text = path.read_text()
    assert "usable coverage: reachable traversable area (ground truth)" in text
    assert "classification ratio" in text and "![graph](plots/graph.png)" in text
    assert (run_dir / "graph.npz").is_file() and (run_dir / "gt.ply").is_file()


def test_report_counts_a_drive_through_a_wall_and_prefers_the_true_trajectory(run):
    run_dir, cfg, world = run
    # the recorder's true trajectory: straight west, through the garden's wall at x = -3
    t = np.arange(0, 6, 0.1)
    truth = np.column_stack([t, -2.0 - 0.3 * t, 0.0 * t, 0.0 * t, np.pi + 0.0 * t])
    np.savetxt(
        run_dir / "trajectory_truth.csv",
        truth,
        delimiter=",",
        header="t_s,x_m,y_m,z_m,yaw_rad",
        comments="",
    )
    report.write_report(run_dir, cfg)
    ex = json.loads((run_dir / "metrics.json").read_text())["exploration"]
    assert ex["trajectory_source"] == "ground truth"
    assert ex["collisions"] >= 1 and ex["collision_time_s"] > 0.5
    assert ex["min_clearance_m"] == 0.0


def test_report_gives_the_maps_terrain_share_of_the_travelled_nodes_beside_the_truth(run):
    # the same travelled nodes read twice: their class in the world (terrain_share) and their
    # label in the explorer's graph (terrain_share_map), what the robot believed it drove on
    run_dir, cfg, world = run
    report.write_report(run_dir, cfg)
    ex = json.loads((run_dir / "metrics.json").read_text())["exploration"]
    truth = ex["terrain_share"]
    assert ex["terrain_share_map"] == 1.0  # the fixture's graph calls every node terrain
    with np.load(run_dir / "explorer" / "graph.npz") as g:
        graph = {k: g[k] for k in g.files}
    graph["labels"] = np.full_like(graph["labels"], 1)  # now grass everywhere
    np.savez(run_dir / "explorer" / "graph.npz", **graph)
    report.write_report(run_dir, cfg)
    ex = json.loads((run_dir / "metrics.json").read_text())["exploration"]
    assert ex["terrain_share_map"] == 0.0 and ex["terrain_share"] == truth


def test_report_of_an_empty_run_dir_still_writes(tmp_path):
    cfg = SmanaConfig.load(None, ["sim.garden.size_m=6.0"])
    path = report.write_report(tmp_path, cfg)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["exploration"]["coverage"] == 0.0
    assert "map" not in m and path.is_file()


def test_report_without_a_simulator_scores_nothing_against_a_world(run):
    """A run with the simulator off (a real robot) has no ground truth: the report says so
    instead of scoring coverage and the map against the config's default simulated world."""
    run_dir, _, _ = run
    cfg = SmanaConfig.load(run_dir / "config.toml", ["deploy.sim.enabled=false"])
    path = report.write_report(run_dir, cfg, explored=True)
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["ground_truth"] == report.NO_SIMULATOR
    assert "exploration" not in m and "map" not in m
    assert not (run_dir / "gt.ply").exists()
    assert m["map_content"]["n_points"] > 0  # what needs no ground truth is still described
    text = path.read_text()
    assert "No ground truth: the simulator was off" in text
    assert "reachable" not in text.split("## Summary")[1].split("##")[0]
    summary = "\n".join(report.summary_lines(m))
    assert "none: the simulator was off" in summary and "of the reachable" not in summary
