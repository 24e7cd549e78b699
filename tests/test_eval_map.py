"""`smana eval map` and the evaluation helpers on hand-made maps whose figures are known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.lab import evaluation as ev
from smana.services.mapper.voxel_ply import write_ply
from smana.services.sim.labelled_ply import write_labelled_ply

NAMES = {1: "grass", 2: "terrain", 4: "hedge"}


def _plane(n=10):
    """GT: a 1 m grid on z = 0; x < 5 is grass, the rest hedge."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    labels = np.where(pts[:, 0] < 5, 1, 4)
    return pts, labels


def test_known_error_and_ratio():
    gp, gl = _plane()
    # map: every GT point raised by 0.1 (half of them) or 0.3 (other half): mean 0.2, std 0.1
    mp = gp.copy()
    mp[::2, 2] += 0.1
    mp[1::2, 2] += 0.3
    ml = gl.copy()
    ml[:10] = 2  # ten grass points (x = 0) called terrain
    s = ev.evaluate_map(mp, ml, gp, gl, NAMES)
    assert s["n_points"] == 100
    assert s["reconstruction_error_mean_m"] == pytest.approx(0.2)
    assert s["reconstruction_error_std_m"] == pytest.approx(0.1)
    assert s["classification_ratio"] == pytest.approx(0.9)
    assert s["per_class"]["terrain"]["classification_ratio"] == 0.0
    assert s["per_class"]["terrain"]["n_points"] == 10
    assert s["per_class"]["grass"]["classification_ratio"] == 1.0
    assert s["per_class"]["hedge"]["n_points"] == 50
    assert s["per_true_class"]["grass"]["classification_ratio"] == pytest.approx(0.8)
    assert s["per_true_class"]["hedge"]["classification_ratio"] == 1.0
    assert "terrain" not in s["per_true_class"]


def test_matches_brute_force_on_random_clouds():
    rng = np.random.default_rng(0)
    gp = rng.uniform(0, 5, (400, 3))
    gl = rng.integers(1, 3, 400)
    mp = rng.uniform(0, 5, (150, 3))
    ml = rng.integers(1, 3, 150)
    d = np.linalg.norm(mp[:, None, :] - gp[None, :, :], axis=2)
    nearest = d.argmin(axis=1)
    err = d.min(axis=1)
    s = ev.evaluate_map(mp, ml, gp, gl)
    assert s["reconstruction_error_mean_m"] == pytest.approx(err.mean())
    assert s["reconstruction_error_std_m"] == pytest.approx(err.std())
    assert s["classification_ratio"] == pytest.approx((ml == gl[nearest]).mean())
    for c in (1, 2):
        sel = ml == c
        assert s["per_class"][str(c)]["error_mean_m"] == pytest.approx(err[sel].mean())


def test_precision_completeness_and_f_score_match_brute_force():
    """Every pair's distance, by numpy broadcasting: the obvious computation."""
    rng = np.random.default_rng(4)
    gp = rng.uniform(0, 1, (300, 3))
    mp = np.concatenate([gp[:120] + rng.normal(0, 0.03, (120, 3)), rng.uniform(0, 1, (40, 3))])
    d = np.linalg.norm(mp[:, None, :] - gp[None, :, :], axis=2)
    for t in (0.02, 0.05, 0.1):
        s = ev.evaluate_map(mp, np.ones(len(mp)), gp, np.ones(len(gp)), threshold_m=t)
        p = (d.min(axis=1) <= t).mean()
        c = (d.min(axis=0) <= t).mean()
        assert s["precision"] == pytest.approx(p) and s["completeness"] == pytest.approx(c)
        assert s["f_score"] == pytest.approx(2 * p * c / (p + c))
        assert s["threshold_m"] == t
        assert ev.surface_completeness(mp, gp, t) == pytest.approx(c)


def test_an_accurate_map_of_half_the_surface_is_half_complete():
    gp, gl = _plane()
    half = gp[gp[:, 0] < 5] + [0.0, 0.0, 0.01]  # the grass half, 1 cm off: accurate
    s = ev.evaluate_map(half, np.ones(len(half)), gp, gl)
    assert s["reconstruction_error_mean_m"] == pytest.approx(0.01)
    assert s["precision"] == 1.0 and s["completeness"] == 0.5
    assert s["f_score"] == pytest.approx(2 / 3)
    # a point exactly at the threshold counts as matched
    assert ev.surface_completeness([[0.0, 0.0, 0.05]], [[0.0, 0.0, 0.0]], 0.05) == 1.0


def test_bad_input_is_a_clear_error():
    gp, gl = _plane()
    with pytest.raises(ValueError, match="points"):
        ev.evaluate_map(np.zeros((3, 2)), [1, 1, 1], gp, gl)
    with pytest.raises(ValueError, match="labels"):
        ev.evaluate_map(np.zeros((3, 3)), [1, 1], gp, gl)
    with pytest.raises(ValueError, match="NaN"):
        ev.evaluate_map(np.full((1, 3), np.nan), [1], gp, gl)
    with pytest.raises(ValueError, match="empty"):
        ev.evaluate_map(np.zeros((1, 3)), [1], np.zeros((0, 3)), [])
    empty = ev.evaluate_map(np.zeros((0, 3)), [], gp, gl)
    assert empty["n_points"] == 0 and empty["classification_ratio"] is None
    assert empty["completeness"] == 0.0 and empty["f_score"] is None
    with pytest.raises(ValueError, match="threshold_m"):
        ev.evaluate_map(gp, gl, gp, gl, threshold_m=0.0)


def test_cli_on_a_run_directory(tmp_path, capsys):
    gp, gl = _plane()
    write_labelled_ply(tmp_path / "gt.ply", gp, gl, np.zeros((len(gp), 3), np.uint8))
    mp = gp + [0.0, 0.0, 0.05]
    ml = gl.copy()
    ml[-25:] = 1  # 25 hedge points called grass
    n = len(mp)
    write_ply(
        tmp_path / "map.ply",
        mp.astype(np.float32),
        np.zeros((n, 3), np.uint8),
        ml.astype(np.uint16),
        np.ones(n, np.float32),
    )
    assert ev.cli(["map", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "classification ratio: 0.750" in out
    assert "within 5 cm: precision " in out  # the default threshold
    # every map point 5 cm off (a hair more in float32): all matched at 6 cm, none at 4 cm
    assert ev.cli(["map", str(tmp_path), "--threshold", "0.06"]) == 0
    assert (
        "within 6 cm: precision 1.000, completeness 1.000, F-score 1.000" in capsys.readouterr().out
    )
    assert ev.cli(["map", str(tmp_path), "--threshold", "0.04", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["completeness"] == 0.0
    saved = json.loads((tmp_path / "eval_map.json").read_text())
    assert saved["reconstruction_error_mean_m"] == pytest.approx(0.05, abs=1e-6)
    assert saved["per_true_class"]["hedge"]["classification_ratio"] == pytest.approx(0.5)
    assert ev.cli(["map", str(tmp_path / "nope")]) == 2
    (tmp_path / "empty").mkdir()
    assert ev.cli(["map", str(tmp_path / "empty"), "--gt", str(tmp_path / "gt.ply")]) == 2


# -- exploration helpers ------------------------------------------------------------------------


def test_coverage_counts_known_nodes_over_reachable_cells():
    grid = {"origin_xy": np.zeros(2), "resolution_m": 1.0, "flags": np.zeros((4, 4), np.uint8)}
    grid["labels"] = np.full((4, 4), 2, np.uint16)  # terrain
    grid["flags"][:2, :] = 1  # x in [0, 2) known
    xs, ys = np.meshgrid(np.arange(8) * 0.5 + 0.25, np.arange(8) * 0.5 + 0.25, indexing="ij")
    cell_xy = np.stack([xs, ys], axis=-1)
    trav = np.ones((8, 8), bool)
    trav[:, 6] = False  # a wall at y = 3.25 cuts off the last row
    reach = ev.reachable_traversable(trav, (0, 0))
    assert reach.sum() == 48
    cov = ev.exploration_coverage(grid, cell_xy, reach, 0.25, np.array([False, True, True]))
    assert cov["reachable_area_m2"] == 12.0
    assert cov["coverage"] == pytest.approx(24 / 48)
    assert not ev.reachable_traversable(trav, (0, 6)).any()


def test_travelled_nodes_terrain_share_and_clearance():
    traj = np.array([[0.1, 0.1], [0.15, 0.1], [0.3, 0.1], [0.5, 0.1], [0.5, 0.3], [0.1, 0.1]])
    cells = ev.travelled_nodes(traj, 0.2)
    assert cells.tolist() == [[0, 0], [1, 0], [2, 0], [2, 1], [0, 0]]
    labels = np.array([2, 2, 1, 2, 2])
    assert ev.terrain_share(labels) == pytest.approx(0.8)
    assert ev.terrain_share(np.array([4, 5])) is None
    assert ev.label_shares(labels, NAMES) == {"grass": 0.2, "terrain": 0.8}
    obstacle = np.zeros((21, 21), bool)
    obstacle[10, 10] = True  # one obstacle cell at (1.0, 1.0) with 0.1 m cells
    c = ev.clearance_along(np.array([[1.0, 1.5], [0.0, 0.0]]), obstacle, (0.0, 0.0), 0.1)
    assert c[0] == pytest.approx(0.5 - 0.1 * np.sqrt(0.5))
    assert c[1] > 1.3


def test_footprint_contacts_follow_the_heading():
    obstacle = np.zeros((41, 41), bool)
    obstacle[20, 24] = True  # a post at (2.0, 2.4) on a 0.1 m raster from (0, 0)
    box = [(0.0, 0.0, 0.28, 0.31)]
    # robot at (2, 2): 0.4 m from the post, beyond its half width (0.31) sideways...
    side = np.array([[2.0, 2.0, 0.0]])
    assert not ev.footprint_contacts(side, obstacle, (0.0, 0.0), 0.1, box)[0]
    # ...0.3 m sideways it touches, 0.3 m ahead (half length 0.28) it does not
    assert ev.footprint_contacts(np.array([[2.0, 2.1, 0.0]]), obstacle, (0, 0), 0.1, box)[0]
    ahead = np.array([[2.0, 2.1, np.pi / 2]])
    assert not ev.footprint_contacts(ahead, obstacle, (0, 0), 0.1, box)[0]
    # the simulated robot: chassis 0.28 x 0.17 and wheels reaching 0.31 sideways at x = 0
    fp = ev.robot_footprint()
    assert ev.footprint_contacts(np.array([[2.0, 2.1, 0.0]]), obstacle, (0, 0), 0.1, fp)[0]
    corner = np.array([[2.0 - 0.25, 2.4 - 0.25, 0.0]])  # the post 0.25 ahead, 0.25 left
    assert not ev.footprint_contacts(corner, obstacle, (0, 0), 0.1, fp)[0]
    assert ev.footprint_contacts(corner, obstacle, (0, 0), 0.1, box)[0]
    assert ev.count_events(np.array([0, 1, 1, 0, 1, 0, 0, 1], bool)) == 3
