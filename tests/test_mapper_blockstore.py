"""The unloaded-block store (services/mapper/blockstore.py): a drive with far blocks on disk makes
the map and the navigation graph an unbounded run makes, and its resident blocks stay bounded
while the map grows."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import NavgraphConfig
from smana.lab.data.longdrive import Drive, DriveWorld
from smana.services.mapper.blockstore import BlockStore
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.navgraph.graph import NavGraph


def _map():
    return SemanticMap("octree-max", resolution_m=0.2, max_range_m=8.0, class_table="rellis3d")


def _content(m) -> tuple[np.ndarray, dict]:
    """Every block's key and voxel columns, in block-key order (the storage order aside)."""
    grid = m._core.grid
    keys = grid.block_keys[: grid.n_blocks]
    order = np.argsort(keys)
    v = grid.voxels_per_block
    rows = (order[:, None] * v + np.arange(v)).ravel()
    return keys[order], {k: grid.used(k)[rows] for k in grid.cols}


def _sorted_delta(d):
    order = np.lexsort(d.keys.T[::-1])
    return d.keys[order], d.labels[order], d.occupied[order], d.values[order]


def test_store_gives_the_unbounded_map_and_graph(tmp_path):
    # lanes 12 m apart, 8 m range: each lane sees the last one's blocks, so regions are written
    # out along a lane and read back on the next
    world = DriveWorld(seed=2, side_m=60.0, lane_spacing_m=12.0, cell_m=4.0, density=0.5)
    drive = Drive(world, speed_mps=6.0, beams=16, columns=256)
    classes = ClassTable.load("rellis3d")
    cfg = NavgraphConfig(bounds_min_xy=[-45.0, -45.0], bounds_max_xy=[45.0, 45.0])
    plain, paged = _map(), _map()
    store = BlockStore(paged, tmp_path / "store", keep_radius_m=12.0, region_m=6.4, check_every=3)
    g_plain, g_paged = NavGraph(classes, cfg), NavGraph(classes, cfg)
    for k in range(drive.n_scans(0.3)):
        pts, lab, origin = drive.scan(k)
        d1 = plain.integrate(pts, lab, origin=origin)
        store.before(origin)
        d2 = paged.integrate(pts, lab, origin=origin)
        store.after(origin)
        for a, b in zip(_sorted_delta(d1), _sorted_delta(d2), strict=True):
            assert np.array_equal(a, b), k
        g_plain.integrate(d1.centres, d1.labels, d1.occupied, map_resolution_m=0.2)
        g_paged.integrate(d2.centres, d2.labels, d2.occupied, map_resolution_m=0.2)
    s = store.stats()
    assert s["regions_written"] > 0 and s["regions_read"] > 0, s  # both ways were exercised
    assert s["resident_blocks"] < plain._core.grid.n_blocks
    keys_a, cols_a = _content(plain)
    keys_b, cols_b = _content(store.full_map())
    assert np.array_equal(keys_a, keys_b)
    for k in cols_a:
        assert np.array_equal(cols_a[k], cols_b[k]), k
    for a, b in zip(g_plain.export(), g_paged.export(), strict=True):
        assert np.array_equal(a, b, equal_nan=True)


def test_resident_blocks_stay_bounded_on_a_long_drive(tmp_path):
    # 1.2 km of small scans along lanes 40 m apart: the map keeps growing, the resident part not
    world = DriveWorld(seed=5, side_m=300.0)
    drive = Drive(world, speed_mps=15.0, beams=8, columns=128)
    m = _map()
    store = BlockStore(m, tmp_path / "store", keep_radius_m=16.0, region_m=6.4)
    resident = []
    for k in range(drive.n_scans(1.2)):
        pts, lab, origin = drive.scan(k)
        store.before(origin)
        m.integrate(pts, lab, origin=origin)
        store.after(origin)
        resident.append(store.stats()["resident_blocks"])
    s = store.stats()
    total = s["resident_blocks"] + s["stored_blocks"]
    late = max(resident[len(resident) // 4 :])
    early = max(resident[: len(resident) // 4])
    assert total > 8 * late, (total, late)  # most of the map is on disk
    assert late <= 1.5 * early, (early, late)  # and what is resident does not grow with distance


def test_keep_radius_must_exceed_the_sensor_reach(tmp_path):
    with pytest.raises(ValueError, match="keep_radius_m"):
        BlockStore(_map(), tmp_path, keep_radius_m=8.0)


def _strip_map():
    """Ground along x over 0..24 m: blocks in four regions of 6.4 m."""
    m = _map()
    rng = np.random.default_rng(3)
    for x0 in range(0, 24, 2):
        pts = np.c_[rng.uniform(x0 - 2, x0 + 2, 300), rng.uniform(-2, 2, 300), np.zeros(300)]
        m.integrate(pts.astype(np.float32), np.full(300, 1, np.uint16), origin=(x0, 0.0, 1.0))
    return m


@pytest.mark.parametrize(
    "damage", ["truncated", "flipped", "nan", "foreign_blocks", "missing_column", "not_a_file"]
)
def test_a_damaged_region_file_costs_that_region_only(tmp_path, damage):
    from smana.lab import fuzz_journals as fj
    from smana.services.mapper.blockstore import _block_xy

    plain, paged = _strip_map(), _strip_map()
    store = BlockStore(paged, tmp_path / "store", keep_radius_m=12.0, region_m=6.4)
    assert store.after((300.0, 0.0), force=True) >= 3  # every region on disk
    bad = (1, 0)  # the region under (12, 0), read back below
    bad_path = store.stored[bad][0]
    fj.region_file(bad_path, damage, bad_path.read_bytes())
    store.before((12.0, 0.0))  # reads back what is within reach, the damaged one among them
    assert store.stats()["regions_damaged"] == 1 and bad not in store.stored, store.problems
    assert str(bad_path) in store.problems[0]
    # the damaged file is kept, renamed; every region still stored still has its file
    kept = bad_path.with_name(bad_path.name + ".damaged")
    assert kept.exists() or (damage == "not_a_file" and bad_path.is_dir())
    assert all(p.is_file() for p, _, _ in store.stored.values())
    # the reference: the plain map's blocks less those of the damaged region, in plain Python
    keys_a, cols_a = _content(plain)
    bx, by = _block_xy(keys_a)
    keep = np.array(
        [
            (int(x) // store.region_blocks, int(y) // store.region_blocks) != bad
            for x, y in zip(bx, by, strict=True)
        ]
    )
    keys_b, cols_b = _content(store.full_map())
    assert np.array_equal(keys_a[keep], keys_b)
    v = plain._core.grid.voxels_per_block
    rows = (np.flatnonzero(keep)[:, None] * v + np.arange(v)).ravel()
    for k in cols_a:
        assert np.array_equal(cols_a[k][rows], cols_b[k]), k
