"""`smana bench mapper --quick`: runs in seconds and reports every figure the issue asks for."""

from __future__ import annotations

import importlib
import json
import re

from smana.lab.bench import mapper as bench
from smana.lab.bench import mapper_report as mr


def importable(module: str) -> bool:
    """As the bench decides: installed and loading (open3d also needs the system's libusb)."""
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def test_quick_bench_reports_all_backends(capsys, tmp_path):
    assert bench.cli(["--quick", "--out", str(tmp_path / "r.json")]) == 0
    text = capsys.readouterr().out
    report = json.loads((tmp_path / "r.json").read_text())
    assert set(report["scenes"]) == {"garden", "short"}
    assert report["scenes"]["short"]["beyond_range"] == 0
    for scene in ("garden", "short"):
        ours = [r for r in report["results"] if r["kind"] == "ours" and r["scene"] == scene]
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
            assert r["bytes_per_allocated_voxel"] <= 32 and len(r["load"]) == 2
        assert re.search(rf"^tsdf +{scene} ", text, re.M)
    pairs = {(p["pair"], p["scene"]) for p in report["pairs"]}
    for name, module in (
        ("octree-max full / OctoMap C++", "pyoctomap"),
        ("tsdf band / Open3D VBG", "open3d"),
    ):
        if not importable(module):
            continue  # an optional peer: its rows are skipped with a hint
        assert {(name, "garden"), (name, "short")} <= pairs
        assert re.search(rf"^{re.escape(name)} +short ", text, re.M)
    if importable("pyoctomap"):
        # full-ray octree-max walks the same voxels as the full-ray OctoMap
        for scene in ("garden", "short"):
            full = mr.find(report["results"], "ours", "octree-max", ray=None, scene=scene)
            om = mr.find(report["results"], "octomap", scene=scene)
            assert om["voxels_observed"] == full["voxels_observed"]
        assert report["checks"]["octomap_agreement"] == 1.0
    for p in report["pairs"]:
        assert p["ratio"] > 0 and p["ratio_cpu"] > 0 and len(p["load"]) == 4
    assert "wall x" in text and "load average" in text and not report["failed"]


def test_the_spread_of_each_comparison_over_its_variants():
    pairs = [
        {
            "pair": "octree-max full / OctoMap C++",
            "scene": s,
            "res": r,
            "ratio": w,
            "ratio_cpu": c,
            "load": [1.0, ld, 2.0, 2.5],
        }
        for s, r, w, c, ld in (
            ("garden", 0.1, 0.2, 0.1, 3.0),
            ("short", 0.1, 0.3, 0.4, 1.5),
            ("near", 0.3, 0.6, 0.2, 0.5),
        )
    ]
    (g,) = bench.spread(pairs)
    assert g["variants"] == ["garden 0.1 m", "short 0.1 m", "near 0.3 m"]
    assert g["wall"] == [0.3, 0.2, 0.6] and g["cpu"] == [0.2, 0.1, 0.4]
    assert g["load"] == [0.5, 3.0]


def test_the_near_scene_has_shorter_rays_and_the_report_its_spread(capsys, tmp_path):
    args = ["--quick", "--scenes", "short", "near", "--backends", "octree-max", "--no-open3d"]
    assert bench.cli([*args, "--out", str(tmp_path / "r.json")]) == 0
    text = capsys.readouterr().out
    report = json.loads((tmp_path / "r.json").read_text())
    near, short = report["scenes"]["near"], report["scenes"]["short"]
    assert near["mean_range_m"] < short["mean_range_m"] and near["points_per_scan"] > 0
    assert "spread over the variants" in text
    if importable("pyoctomap"):
        (g,) = report["spread"]
        assert g["pair"] == "octree-max full / OctoMap C++"
        assert g["variants"] == ["near 0.3 m", "short 0.3 m"]
