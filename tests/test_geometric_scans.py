"""The geometric labeller on whole LiDAR scans: a real KITTI scan (tests/data/kitti, no labels
exist for it here) checked for sensible figures, and synthetic RELLIS-3D scans whose true labels
measure its agreement. Figures and the time per scan are printed (`pytest -s`), with the load
average: timings on a shared machine are noisy, so none is asserted."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.geometric import GROUND, OBSTACLE, UNKNOWN, label_geometric
from smana.lab.data import synthetic as syn
from smana.services.replay.readers import open_dataset

KITTI_SCAN = Path(__file__).parent / "data" / "kitti" / "000000.bin"
KITTI_SENSOR_HEIGHT_M = 1.73  # the Velodyne HDL-64E above the road (KITTI setup)


def kitti_points() -> np.ndarray:
    return np.fromfile(KITTI_SCAN, np.float32).reshape(-1, 4)[:, :3]


def timed_ms(fn, repeats=5) -> tuple[float, float]:
    """Best wall and CPU time of `repeats` calls, in ms."""
    fn()  # compiled (or loaded from the cache) before timing
    wall = cpu = np.inf
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall * 1e3, cpu * 1e3


def test_kitti_scan_sensible_figures():
    pts = kitti_points()
    assert pts.shape == (124668, 3)
    # the scan in its sensor frame, taken as the world frame: the car stands level
    labels = label_geometric(pts, [0.0, 0.0, 0.0])
    share = np.bincount(labels, minlength=3) / labels.size
    r = np.hypot(pts[:, 0], pts[:, 1])
    road = (r < 20) & (np.abs(pts[:, 2] + KITTI_SENSOR_HEIGHT_M) < 0.15)
    high = pts[:, 2] > 1.2 - KITTI_SENSOR_HEIGHT_M  # 1.2 m above the road: walls, cars, trees
    near = r < 10
    ground_on_road = float(np.mean(labels[road] == GROUND))
    obstacle_high = float(np.mean(labels[high] == OBSTACLE))
    wall_ms, cpu_ms = timed_ms(lambda: label_geometric(pts, [0.0, 0.0, 0.0]))
    print(
        f"\nKITTI 00/000000 ({len(pts)} points): unknown {share[UNKNOWN]:.3f} ground "
        f"{share[GROUND]:.3f} obstacle {share[OBSTACLE]:.3f}; near the road plane ground "
        f"{ground_on_road:.3f} ({road.sum()} points); higher than 1.2 m obstacle "
        f"{obstacle_high:.3f}; within 10 m ground {np.mean(labels[near] == GROUND):.3f}; "
        f"{wall_ms:.1f} ms wall, {cpu_ms:.1f} ms CPU a scan (best of 5), load average "
        f"{os.getloadavg()[0]:.2f}"
    )
    assert ground_on_road > 0.9
    assert obstacle_high > 0.8
    assert 0.15 < share[OBSTACLE] < 0.6  # buildings, cars, trees on a street
    assert share[UNKNOWN] < 0.15  # sparse far returns only
    assert np.mean(labels[near] == GROUND) > 0.6


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("geom_synthetic")
    params = syn.SyntheticConfig(n_scans=2, beams=64, columns=2048, noise_m=0.01)
    syn.write_rellis_sequence(root, params)
    return open_dataset(root)


def test_synthetic_scans_agree_with_their_true_labels(synthetic):
    """Ground against the table's traversable classes, obstacles against its obstacle classes,
    over the points the replay would publish (30 m, ignored classes dropped), in the world."""
    table = ClassTable.load("rellis3d")
    for i in range(len(synthetic)):
        scan = synthetic.scan(i)
        lab, _ = table.map_dataset_labels(scan.labels)
        rng = np.linalg.norm(scan.points, axis=1)
        keep = ~table.ignored_lut[lab] & (rng > 0.5) & (rng < 30)
        world = (scan.points[keep].astype(np.float64) @ scan.pose[:3, :3].T) + scan.pose[:3, 3]
        labels = label_geometric(world.astype(np.float32), scan.pose[:3, 3])
        trav, obs = table.traversable_lut[lab[keep]], table.obstacle_lut[lab[keep]]
        known = labels != UNKNOWN
        agree = float((((labels == GROUND) & trav) | ((labels == OBSTACLE) & obs))[known].mean())
        ground_recall = float(np.mean(labels[trav] == GROUND))
        ground_precision = float(np.mean(trav[labels == GROUND]))
        print(
            f"\nsynthetic scan {i} ({keep.sum()} points): judged {known.mean():.3f}, agreement "
            f"{agree:.3f}, ground recall {ground_recall:.3f} precision {ground_precision:.3f}, "
            f"obstacle recall {np.mean(labels[obs] == OBSTACLE):.3f}"
        )
        assert known.mean() > 0.9
        assert agree > 0.9
        assert ground_recall > 0.9 and ground_precision > 0.9
