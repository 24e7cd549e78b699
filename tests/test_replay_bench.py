"""The replay benchmark's bookkeeping: patch/delta matching, medians over repeats, the table and
the two figures (the runs themselves are `smana bench replay`, too slow for the suite)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from smana.lab.bench.replay import RunResult, aggregate, match_patches, table_markdown
from smana.lab.paper_figures import figure_11, figure_12


def test_patches_are_matched_by_stamp():
    deltas = {1: (0.1, 10.0), 2: (0.2, 10.2), 3: (0.3, 10.4)}
    # patch for delta 1 arrives after delta 2 (a slow navgraph); delta 3 changed no node
    patches = [(0.2, 10.25), (0.1, 10.3)]
    assert match_patches(deltas, patches) == pytest.approx({1: 300.0, 2: 50.0})


def test_patches_without_delta_stamps_are_matched_by_order():
    deltas = {1: (0.1, 10.0), 2: (0.2, 10.2), 3: (0.3, 10.4), 4: (0.4, 12.0)}
    patches = [(-1.0, 10.05), (-1.0, 10.26), (-1.0, 12.01)]  # delta 3: no patch
    assert match_patches(deltas, patches) == pytest.approx({1: 50.0, 2: 60.0, 4: 10.0})


def run(backend, rep, map_ms, cpu, rss):
    r = RunResult(backend, 0.1, 0.2, rep, scans=3, points_per_scan=1000.0)
    r.map_ms = map_ms
    r.map_us_per_point = [1000.0 * m / 1000.0 for m in map_ms]
    r.graph_ms = [5.0, 5.0, 5.0]
    r.graph_us_per_point = [5.0, 5.0, 5.0]
    r.cpu_map, r.cpu_graph = cpu, [10.0, 20.0]
    r.rss_map_mb, r.rss_graph_mb = rss, 50.0
    return r


def test_aggregate_takes_the_median_over_repeats():
    runs = [
        run("octree-max", 0, [10.0, 20.0, 30.0], [100.0, 100.0], 300.0),  # mean 20 ms
        run("octree-max", 1, [40.0, 40.0, 40.0], [50.0, 150.0], 900.0),  # mean 40 ms
        run("octree-max", 2, [30.0, 30.0, 30.0], [80.0, 80.0], 600.0),  # mean 30 ms
        run("tsdf", 0, [5.0, 5.0, 5.0], [60.0, 60.0], 100.0),
    ]
    rows = {r["backend"]: r for r in aggregate(runs)}
    o = rows["octree-max"]
    assert o["repeats"] == 3
    assert o["map_ms_scan"] == pytest.approx(30.0)
    assert o["map_us_pt"] == pytest.approx(30.0)
    assert o["map_us_pt_std"] == pytest.approx(0.0)  # median of (8.16, 0, 0)
    assert o["cpu_map"] == pytest.approx(100.0) and o["cpu_map_std"] == pytest.approx(0.0)
    assert o["rss_map_mb"] == pytest.approx(600.0)
    assert o["s_per_scan"] == pytest.approx(0.035)
    assert o["s_per_131k"] == pytest.approx((30.0 + 5.0) * 131072 / 1e6)
    assert o["paper_s_per_scan"] == 0.56 and rows["tsdf"]["paper_s_per_scan"] == 7.2
    text = table_markdown(list(rows.values()))
    assert "| octree-max | 0.1 / 0.2 m | 1000 | 30.000 ± 0.000 |" in text


def test_figures_are_written(tmp_path):
    rows = aggregate(
        [run("octree-max", 0, [10.0], [100.0], 300.0), run("tsdf", 0, [5.0], [60.0], 100.0)]
    )
    for f, name in ((figure_11, "f11.png"), (figure_12, "f12.png")):
        img = cv2.imread(str(f(rows, tmp_path / name)))
        assert img is not None and img.shape[0] > 400
        # the map bars are drawn in their colour
        assert np.any(np.all(img == (180, 119, 31), axis=2))
