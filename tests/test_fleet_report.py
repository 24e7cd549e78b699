"""A fleet run's report on a fabricated run directory (the layout `smana up --robots N` leaves):
the fleet section's numbers, the overlap of the members' maps against a slow reference, the
coverage curve against a slow reference, and the warnings (a contact, a member without state)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.config import SmanaConfig
from smana.deploy import report
from smana.lab import evaluation as ev
from smana.services.mapper.semantic_map import SemanticMap

ROBOTS = ("r1", "r2")


def _save_map(path, points, labels):
    m = SemanticMap("octree-max", 0.1, 8.0, 0.05)
    # short rays (5 cm): what the map observed is (nearly) the points themselves
    for k in range(0, len(points), 500):
        p = points[k : k + 500]
        m.integrate(p, labels[k : k + 500], origin=tuple(p.mean(axis=0) + [0, 0, 0.2]))
    path.parent.mkdir(parents=True, exist_ok=True)
    m.save(path)


def _csv(path, rows, header):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, delimiter=",", header=header, comments="")


HISTORIES = {
    # (t_s, explored_m2, frontier_size, distance_m): shared simulated time
    "r1": [[0.0, 5.0, 10, 0.0], [10.0, 20.0, 5, 2.0], [20.0, 30.0, 0, 4.0]],
    "r2": [[5.0, 8.0, 9, 0.0], [15.0, 40.0, 3, 3.0]],
}


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("fleet")
    cfg = SmanaConfig.load(
        None,
        [
            "sim.garden.size_m=6.0",
            "sim.seed=3",
            'sim.garden.layout="classic"',
            'fleet.robots=["r1", "r2"]',
        ],
    )
    cfg.write(run / "config.toml")
    world = ev.world_from_config(cfg)
    gp, gl = world.gt_cloud(0.1)
    gl = gl.astype(np.uint16)
    # r1 saw x < 0.5, r2 x > -0.5: they share the strip between
    _save_map(run / "robots" / "r1" / "map.npz", gp[gp[:, 0] < 0.5], gl[gp[:, 0] < 0.5])
    _save_map(run / "robots" / "r2" / "map.npz", gp[gp[:, 0] > -0.5], gl[gp[:, 0] > -0.5])
    _save_map(run / "map.npz", gp, gl)
    x0, y0, _ = world.spawn_pose(0.4)
    t = np.arange(0, 20, 0.5)
    for k, r in enumerate(ROBOTS):
        d = run / "robots" / r
        # r1 drives 0.2 m east, r2 0.2 m north (from 0.1 m south of the spawn point)
        dx, dy = (0.01 * t, 0 * t) if k == 0 else (0 * t, -0.1 + 0.01 * t)
        truth = np.column_stack([t, x0 + dx, y0 + dy, 0 * t, 0 * t])
        _csv(d / "trajectory_truth.csv", truth, "t_s,x_m,y_m,z_m,yaw_rad")
        state = {
            "done_reason": "no_frontier",
            "distance_m": 0.2,
            "explored_m2": HISTORIES[r][-1][1],
            "n_goals": 2 + k,
            "elapsed_s": 20.0,
            "wall_time_s": 30.0,
            "path_queries": 3,
            "path_ok": 3,
            "history": HISTORIES[r],
        }
        (d / "explorer").mkdir(parents=True)
        (d / "explorer" / "state.json").write_text(json.dumps(state))
        # the shared graph: every node known
        np.savez(
            d / "explorer" / "graph.npz",
            origin_xy=np.array([-3.5, -3.5]),
            resolution_m=0.2,
            labels=np.full((35, 35), 2, np.uint16),
            heights=np.zeros((35, 35), np.float32),
            flags=np.ones((35, 35), np.uint8),
        )
    sim = {
        "robots": list(ROBOTS),
        "robot_contacts": {"r1-r2": 0},
        "robot_contacts_total": 0,
        "min_separation_m": {"r1-r2": 0.1},
        "sim_time_s": 20.0,
    }
    (run / "sim.json").write_text(json.dumps(sim))
    (run / "logs").mkdir()
    (run / "logs" / "sim@fleet.log").write_text("ok\n")
    path = report.write_report(run, cfg, explored=True)
    return run, cfg, world, path


def _overlap_reference(run, cfg, world):
    """Slow and obvious: per reachable cell, which members hold a voxel in the map column over
    its centre."""
    traj = np.loadtxt(run / "robots" / "r1" / "trajectory_truth.csv", delimiter=",", skiprows=1)
    trav, _, reach = report.reachable_area(world, traj[:, [0, 1, 2, 4]], 0.4)
    columns = {}
    for r in ROBOTS:
        m = SemanticMap.load(run / "robots" / r / "map.npz")
        v = m.resolution_m
        voxels = report.observed_voxels(m).centres
        columns[r] = {(int(x // v), int(y // v)) for x, y, _ in voxels}
    seen = several = 0
    xs, ys = trav.cell_centres()
    for i, j in zip(*np.nonzero(reach), strict=True):
        col = (int(np.floor(xs[i] / v + 1e-6)), int(np.floor(ys[j] / v + 1e-6)))
        n = sum(col in c for c in columns.values())
        seen += n >= 1
        several += n >= 2
    return several / seen


def test_fleet_section_measures_the_run(fleet_run):
    run, cfg, world, path = fleet_run
    m = json.loads((run / "metrics.json").read_text())
    f = m["fleet"]
    assert f["robots"] == ["r1", "r2"] and m["warnings"] == []
    assert f["coverage"] == pytest.approx(1.0)  # the shared graph knows every node
    for k, r in enumerate(ROBOTS):
        mm = f["members"][r]
        assert mm["distance_m"] == pytest.approx(0.195)
        assert mm["n_goals"] == 2 + k and mm["collisions"] == 0
        assert mm["robot_time_s"] == pytest.approx(19.5) and mm["wall_time_s"] == 30.0
    assert f["total_distance_m"] == pytest.approx(0.39)
    # fleet curve: explored 5, 8, 20, 40, 40 at t 0, 5, 10, 15, 20; distance 0, 0, 2, 5, 7
    assert f["time_to_95_s"] == 15.0 and f["distance_to_95_m"] == 5.0
    assert f["sim"]["robot_contacts_total"] == 0 and f["sim"]["min_separation_overall_m"] == 0.1
    # the overlap: the strip -0.5 < x < 0.5 of a 6 m garden, about a sixth of what was seen
    assert f["overlap"] == pytest.approx(_overlap_reference(run, cfg, world), abs=1e-9)
    assert 0.1 < f["overlap"] < 0.35
    shares = f["observed_share_per_member"]
    assert 0.5 < shares["r1"] < 0.8 and 0.5 < shares["r2"] < 0.8
    # maps: the merged one and each member's own, scored against the same ground truth
    assert set(f["map"]) == {"merged", "r1", "r2"}
    merged = f["map"]["merged"]
    assert merged["n_points"] > f["map"]["r1"]["n_points"]
    assert merged["reconstruction_error_mean_m"] < 0.05
    assert merged["classification_ratio"] > 0.8
    assert m["map"]["n_points"] == merged["n_points"]  # the run's map is the merged map
    # the summary table and report.md carry the fleet
    rows = dict(report.summary_rows(m))
    assert rows["fleet"] == "2 members: r1, r2" and "r2" in rows
    assert rows["to 95 % known (any label)"].startswith("15 s robot time, 5.0 m")
    text = path.read_text()
    assert "## Fleet" in text and "| merged map |" in text
    for name in ("fleet_map", "graph", "fleet_progress"):
        assert (run / m["files"]["plots"][name]).stat().st_size > 1000
    assert (run / "graph.npz").is_file()


def test_a_contact_and_a_member_without_state_are_warnings(fleet_run, tmp_path):
    run, cfg, _, _ = fleet_run
    import shutil

    other = tmp_path / "run"
    shutil.copytree(run, other)
    (other / "metrics.json").unlink()
    sim = json.loads((other / "sim.json").read_text())
    sim["robot_contacts"], sim["robot_contacts_total"] = {"r1-r2": 2}, 2
    (other / "sim.json").write_text(json.dumps(sim))
    (other / "robots" / "r2" / "explorer" / "state.json").unlink()
    (other / "robots" / "r2" / "trajectory_truth.csv").unlink()
    report.write_report(other, cfg, explored=True)
    m = json.loads((other / "metrics.json").read_text())
    w = m["warnings"]
    assert any("2 robot-robot contact(s) (r1-r2 x2)" in x for x in w), w
    assert any(x.startswith("r2: the explorer left no state") for x in w), w
    assert any(x.startswith("r2: the robot did not move") for x in w), w
    assert not any(x.startswith("r1:") for x in w), w
    assert report.summary_lines(m)[0] == "smana up: FAILED"
    # no sim.json: contacts unknown, a warning when a simulator ran, none on real robots
    fleet = dict(m["fleet"], sim={"summary": None})
    assert any("no sim.json" in w for w in report.fleet_warnings(fleet))
    assert not any("sim.json" in w for w in report.fleet_warnings(dict(fleet, simulated=False)))
    assert (other / "report.md").read_text().index("## Warnings") < 40


def test_fleet_coverage_curve_against_a_slow_reference():
    rng = np.random.default_rng(4)
    for _ in range(20):
        hist = {}
        for r in ("a", "b", "c")[: rng.integers(1, 4)]:
            n = int(rng.integers(1, 6))
            t = np.sort(rng.choice(np.arange(0, 30, 2.5), n, replace=False))
            hist[r] = np.column_stack(
                [t, rng.uniform(0, 50, n), np.zeros(n), np.cumsum(rng.uniform(0, 3, n))]
            ).tolist()
        t, d, cov = report.fleet_coverage_curve(hist, 0.9)
        times = sorted({row[0] for h in hist.values() for row in h})
        expl = [max(row[1] for h in hist.values() for row in h if row[0] <= x) for x in times]
        dist = [
            sum(
                max((row for row in h if row[0] <= x), key=lambda r: r[0])[3]
                for h in hist.values()
                if any(row[0] <= x for row in h)
            )
            for x in times
        ]
        assert t.tolist() == pytest.approx([x - times[0] for x in times])
        assert d.tolist() == pytest.approx(dist)
        assert cov.tolist() == pytest.approx([min(1.0, e / expl[-1] * 0.9) for e in expl])
    assert report.fleet_coverage_curve({"a": []}, 0.9)[0].size == 0


def test_map_overlap_by_hand():
    reach = np.ones((2, 3), bool)
    reach[1, 2] = False
    a = np.array([[1, 1, 0], [0, 0, 1]], bool)
    b = np.array([[0, 1, 1], [1, 0, 1]], bool)
    c = np.array([[0, 1, 0], [0, 0, 0]], bool)
    # reachable cells seen: (0,0) a; (0,1) a b c; (0,2) b; (1,0) b -> 1 of 4 by two or more
    out = report.map_overlap({"a": a, "b": b, "c": c}, reach, 0.25)
    assert out["overlap"] == 0.25 and out["observed_reachable_area_m2"] == 1.0
    assert report.map_overlap({}, reach, 0.25)["overlap"] is None
