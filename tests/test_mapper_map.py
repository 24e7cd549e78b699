"""SemanticMap around the back-ends: exact save/load round trip, PLY export, queries, the class
table's ignored classes, statistics."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.services.mapper.backends import BACKENDS
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.mapper.voxel_ply import read_ply


def cloud(seed, n=800):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    labels = rng.choice(np.array([0, 1, 2, 4, 5, 6, 7, 8]), n)
    conf = rng.uniform(0.3, 1.0, n).astype(np.float32)
    return pts, labels, conf, rng.uniform(-0.2, 0.2, 3)


def columns(m: SemanticMap) -> dict:
    g = m._core.grid
    out = {k: g.used(k).copy() for k in g.cols}
    out["block_keys"] = g.block_keys[: g.n_blocks].copy()
    return out


def delta_rows(d):
    order = np.lexsort(d.keys.T)
    return [getattr(d, f)[order] for f in ("keys", "labels", "confidences", "occupied", "values")]


@pytest.mark.parametrize("backend", BACKENDS)
def test_save_load_round_trip_is_exact(backend, tmp_path):
    m = SemanticMap(backend, 0.2, 4.0, 1.0)
    for s in (1, 2):
        m.integrate(*cloud(s))
    path = m.save(tmp_path / "map.npz")
    n = SemanticMap.load(path)
    assert (n.backend, n.resolution_m, n.max_range_m, n.raycast_range_m) == (backend, 0.2, 4.0, 1.0)
    a, b = columns(m), columns(n)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # the loaded map goes on exactly as the original
    da, db = m.integrate(*cloud(3)), n.integrate(*cloud(3))
    for x, y in zip(delta_rows(da), delta_rows(db), strict=True):
        np.testing.assert_array_equal(x, y)
    q = cloud(4)[0]
    qa, qb = m.query(q), n.query(q)
    np.testing.assert_array_equal(qa.labels, qb.labels)
    np.testing.assert_array_equal(qa.values, qb.values)
    assert m.stats()["voxels_observed"] == n.stats()["voxels_observed"]


def test_load_rejects_other_files(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a map")
    with pytest.raises(ValueError, match="not a smana map"):
        SemanticMap.load(bad)
    m = SemanticMap("octree-max", 0.2)
    m.integrate(*cloud(1))
    path = m.save(tmp_path / "m.npz")
    other = ClassTable.from_dict(
        {
            "name": "two",
            "class": [
                {"id": 0, "name": "unknown", "kind": "unknown"},
                {"id": 1, "name": "ground", "kind": "traversable", "cost": 1.0},
            ],
        }
    )
    with pytest.raises(ValueError, match="class table"):
        SemanticMap.load(path, other)


def test_export_ply_opens_with_labels_and_colours(tmp_path):
    table = ClassTable.load("garden3drms")
    m = SemanticMap("octree-max", 0.2, 5.0, 0.0, class_table=table)
    m.integrate(*cloud(7))
    n = m.export_ply(tmp_path / "map.ply")
    v = read_ply(tmp_path / "map.ply")
    occ = m.occupied_voxels()
    assert n == len(v) == len(occ) > 0
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), occ.centres)
    np.testing.assert_array_equal(v["label"], occ.labels)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    np.testing.assert_array_equal(rgb, table.colour_lut[occ.labels])
    header = (tmp_path / "map.ply").read_bytes()[:400].decode("ascii", "replace")
    assert "element vertex" in header and "property int label" in header  # Open3D drops ushort


def test_query_and_box():
    m = SemanticMap("octree-max", 0.1, 10.0, 0.0)
    pts = np.array([[1.05, 0.05, 0.05], [0.05, 1.05, 0.05]], np.float32)
    m.integrate(pts, np.array([1, 4]), np.array([0.9, 0.8], np.float32), (0.05, 0.05, 0.05))
    q = m.query(np.array([[1.06, 0.04, 0.09], [0.5, 0.05, 0.05], [5.0, 5.0, 5.0]]))
    assert q.known.tolist() == [True, True, False]
    assert q.occupied.tolist() == [True, False, False]
    assert q.labels[0] == 1 and np.isnan(q.values[2])
    everything = m.occupied_voxels()
    assert len(everything) == 2
    box = m.occupied_voxels(((0.5, -1, -1), (2, 1, 1)))
    assert box.labels.tolist() == [1]
    with pytest.raises(ValueError):
        m.occupied_voxels(((0, 0), (1, 1)))


def test_ignored_classes_never_reach_the_map():
    table = ClassTable.from_dict(
        {
            "name": "sky",
            "class": [
                {"id": 0, "name": "unknown", "kind": "unknown"},
                {"id": 1, "name": "ground", "kind": "traversable", "cost": 1.0},
                {"id": 2, "name": "wall", "kind": "obstacle"},
                {"id": 9, "name": "sky", "kind": "ignored"},
            ],
        }
    )
    m = SemanticMap("octree-bayes", 0.2, 10.0, 0.0, class_table=table)
    pts = np.array([[1.0, 0.1, 0.1], [0.1, 1.0, 0.1]], np.float32)
    m.integrate(pts, np.array([9, 2]), None, (0.1, 0.1, 0.1))
    q = m.query(pts)
    assert q.known.tolist() == [False, True]
    assert m.stats()["points"] == 1


def test_stats_count_memory_honestly():
    m = SemanticMap("octree-max", 0.1, 5.0, 1.0)
    m.integrate(*cloud(5, 3000))
    s = m.stats()
    assert s["voxels_allocated"] == s["blocks"] * 512
    assert 0 < s["voxels_occupied"] <= s["voxels_observed"] <= s["voxels_allocated"]
    assert s["bytes_per_voxel_field"] == 11  # log-odds f4, label u2, confidence f4, flags u1
    assert s["bytes_used"] >= s["voxels_allocated"] * 11
    assert s["bytes_reserved"] >= s["bytes_used"] - 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_running_counts_match_a_full_scan(backend):
    """stats() reads counters the kernels keep; they must equal a scan of the columns."""
    m = SemanticMap(backend, 0.2, 3.0, 1.0)
    for s in range(4):
        m.integrate(*cloud(s))
        core = m._core
        assert core.n_observed == len(core.observed_index())
        assert core.n_occupied == len(core.occupied_index())
