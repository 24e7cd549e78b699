"""`smana bench mapper --quick`: runs in seconds and reports every figure the issue asks for."""

from __future__ import annotations

import json

import pytest

from smana.lab.bench import mapper as bench


def test_quick_bench_reports_all_backends(capsys):
    assert bench.cli(["--quick", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    ours = [r for r in report["results"] if r["kind"] == "ours"]
    assert {(r["backend"], r["ray_m"]) for r in ours} == {
        ("octree-max", 1.0),
        ("octree-max", None),
        ("octree-bayes", 1.0),
        ("octree-bayes", None),
        ("tsdf", None),
    }
    for r in ours:
        assert "error" not in r, r
        assert r["median_ms"] > 0 and r["p95_ms"] >= r["median_ms"] * 0.5
        assert r["us_per_point"] > 0 and r["voxel_updates_per_s"] > 0
        assert r["voxels_observed"] > 0 and r["peak_rss_mb"] > 0
        if r["backend"] != "tsdf":
            assert r["bytes_per_allocated_voxel"] <= 32
    # full-ray octree-max walks the same voxels as the full-ray OctoMap
    full = next(r for r in ours if r["backend"] == "octree-max" and r["ray_m"] is None)
    pytest.importorskip("pyoctomap")
    om = next(r for r in report["results"] if r["kind"] == "octomap")
    assert om["voxels_observed"] == full["voxels_observed"]
    assert report["checks"]["octomap_agreement"] == 1.0
