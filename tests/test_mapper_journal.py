"""The mapper's journal (services/mapper/journal.py), in-process: a map followed through its
journal equals the original voxel for voxel, in every column of every back-end, and goes on
exactly as the original; a record cut short is counted and cut off; a rotation after an autosave
is followed; replaying a record twice changes nothing."""

from __future__ import annotations

import os

import numpy as np
import pytest

from smana.services.mapper.backends import BACKENDS
from smana.services.mapper.journal import JournalReader, JournalWriter, journal_path
from smana.services.mapper.semantic_map import SemanticMap
from tests.test_mapper_map import cloud, delta_rows


def all_voxels(m: SemanticMap) -> dict:
    """Every allocated voxel's columns, keyed by voxel key (block order is the map's own)."""
    grid = m._core.grid
    n = grid.n_blocks * grid.voxels_per_block
    keys = grid.coords(np.arange(n))
    order = np.lexsort(keys.T)
    out = {"keys": keys[order]}
    for k in grid.cols:
        out[k] = grid.used(k)[order]
    return out


def assert_same_voxels(a: SemanticMap, b: SemanticMap) -> None:
    """Same columns at every voxel either map allocated (a voxel one of them never allocated
    must hold the defaults in the other: zeros)."""
    va, vb = all_voxels(a), all_voxels(b)
    ga, gb = b._core.grid.lookup(va["keys"]), a._core.grid.lookup(vb["keys"])
    for k in a._core.grid.cols:
        ca, cb = a._core.grid.cols[k], b._core.grid.cols[k]
        got_a = a._core.grid.lookup(va["keys"])
        np.testing.assert_array_equal(
            ca[got_a][ga >= 0], cb[ga[ga >= 0]], err_msg=f"{k}: voxels both maps hold"
        )
        assert not ca[got_a][ga < 0].any(), f"{k}: a voxel only the original holds is not blank"
        got_b = b._core.grid.lookup(vb["keys"])
        assert not cb[got_b][gb < 0].any(), f"{k}: a voxel only the copy holds is not blank"
    assert a.stats()["voxels_observed"] == b.stats()["voxels_observed"]
    assert a.stats()["voxels_occupied"] == b.stats()["voxels_occupied"]


def integrate_and_log(m, writer, seeds):
    for s in seeds:
        d = m.integrate(*cloud(s))
        writer.append(d.keys, {"n_integrations": m.n_integrations, "cloud": s})


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_map_replayed_from_its_journal_equals_the_original_and_goes_on_the_same(
    backend, tmp_path
):
    m = SemanticMap(backend, 0.2, 4.0, 1.0)
    path = journal_path(tmp_path / "map.npz")
    writer = JournalWriter(path, m, {"cloud": -1})
    integrate_and_log(m, writer, range(1, 6))
    reader = JournalReader(path)
    reader.attach(SemanticMap(backend, 0.2, 4.0, 1.0))  # no autosave yet: an empty map
    assert reader.finish() == os.path.getsize(path)
    copy = reader.map
    copy.recount()
    assert reader.books.records == 5 and reader.books.torn_bytes == 0
    assert reader.books.service == {"n_integrations": 5, "cloud": 5}
    assert_same_voxels(m, copy)
    # the back-end's whole state came back (label distributions, weights), not only the
    # delta's columns: the next cloud is fused the same way
    da, db = m.integrate(*cloud(9)), copy.integrate(*cloud(9))
    for x, y in zip(delta_rows(da), delta_rows(db), strict=True):
        np.testing.assert_array_equal(x, y)
    assert_same_voxels(m, copy)


def test_a_record_cut_short_is_counted_and_cut_off_and_the_new_writer_goes_on(tmp_path):
    m = SemanticMap("octree-bayes", 0.2, 4.0, 1.0)
    path = journal_path(tmp_path / "map.npz")
    writer = JournalWriter(path, m, {})
    integrate_and_log(m, writer, range(1, 4))
    whole = os.path.getsize(path)
    before = SemanticMap.load(m.save(tmp_path / "before.npz"))  # the map with 3 clouds
    integrate_and_log(m, writer, [4])
    size = os.path.getsize(path)
    os.truncate(path, size - (size - whole) // 2)  # kill -9 in the middle of the 4th write
    reader = JournalReader(path)
    reader.attach(SemanticMap("octree-bayes", 0.2, 4.0, 1.0))
    offset = reader.finish()
    assert offset == whole and reader.books.records == 3
    assert reader.books.torn_bytes == (size - whole) - (size - whole) // 2
    reader.map.recount()
    assert_same_voxels(before, reader.map)
    # the mapper that takes over appends after the last whole record
    w2 = JournalWriter(path, reader.map, {}, offset=offset)
    d = reader.map.integrate(*cloud(5))
    w2.append(d.keys, {"cloud": 5})
    again = JournalReader(path)
    again.attach(SemanticMap("octree-bayes", 0.2, 4.0, 1.0))
    again.finish()
    assert again.books.records == 4 and again.books.torn_bytes == 0
    again.map.recount()
    assert_same_voxels(reader.map, again.map)


def test_a_follower_goes_through_an_autosave_and_its_rotation(tmp_path):
    m = SemanticMap("tsdf", 0.2, 4.0, 1.0)
    save = tmp_path / "map.npz"
    path = journal_path(save)
    writer = JournalWriter(path, m, {})
    integrate_and_log(m, writer, [1, 2])
    reader = JournalReader(path)  # the spare: open the journal, then load the autosave
    reader.attach(SemanticMap("tsdf", 0.2, 4.0, 1.0))
    assert reader.poll() == 2
    integrate_and_log(m, writer, [3])
    m.save(save)  # the autosave, then a fresh journal
    writer.rotate({"saved": True})
    integrate_and_log(m, writer, [4, 5])
    assert reader.poll() == 3  # the old file's last record, then the new one's two
    assert reader.books.files == 2
    reader.finish()
    reader.map.recount()
    assert_same_voxels(m, reader.map)


def test_replaying_a_journal_over_the_autosave_that_holds_it_changes_nothing(tmp_path):
    # a crash between the autosave and the journal's rotation: the map file holds every record
    m = SemanticMap("octree-max", 0.2, 4.0, 1.0)
    save = tmp_path / "map.npz"
    writer = JournalWriter(journal_path(save), m, {})
    integrate_and_log(m, writer, range(1, 5))
    m.save(save)
    reader = JournalReader(journal_path(save))
    reader.attach(SemanticMap.load(save))
    reader.finish()
    reader.map.recount()
    assert reader.books.records == 4
    assert_same_voxels(m, reader.map)


def test_a_journal_of_another_map_is_skipped(tmp_path):
    m = SemanticMap("octree-max", 0.2, 4.0, 1.0)
    path = journal_path(tmp_path / "map.npz")
    integrate_and_log(m, JournalWriter(path, m, {}), [1])
    reader = JournalReader(path)
    reader.attach(SemanticMap("octree-max", 0.1, 4.0, 1.0))
    reader.finish()
    assert reader.books.records == 0 and "0.2 m" in reader.books.skipped
    assert reader.map.stats()["voxels_observed"] == 0


def test_voxel_state_checks_its_input():
    m = SemanticMap("octree-max", 0.2, 4.0, 1.0)
    d = m.integrate(*cloud(1))
    cols = m.voxel_state(d.keys)
    with pytest.raises(ValueError, match="no allocated block"):
        m.voxel_state(np.array([[30000, 0, 0]]))
    with pytest.raises(ValueError, match="do not fit"):
        m.set_voxel_state(d.keys, {"flags": cols["flags"]})
    with pytest.raises(ValueError, match="column"):
        m.set_voxel_state(d.keys[:1], cols)
