"""A damaged journal costs the damaged record only (services/mapper/journal.py), against the slow
reference of `lab/fuzz_journals.py`: the journal cut at every offset, one bit flipped in every
frame field and at sampled body bytes, records crafted with a valid checksum over bad content.
Every byte ends counted: applied, refused, skipped as damage or torn at the end."""

from __future__ import annotations

import numpy as np
import pytest

from smana.lab import fuzz_journals as fj
from smana.services.mapper.journal import RECORD_FRAME, JournalReader, JournalWriter


def replay(tmp_path, data: bytes, backend: str = "octree-bayes"):
    path = tmp_path / "map.journal"
    path.write_bytes(data)
    reader = JournalReader(path)
    reader.attach(fj.small_map(backend))
    offset = reader.finish()
    reader.close()
    return reader, offset


@pytest.fixture(scope="module")
def jrn(tmp_path_factory):
    return fj.journal(tmp_path_factory.mktemp("journal"), n_records=4)


def test_the_journal_cut_at_every_offset_keeps_every_whole_record(tmp_path):
    jrn = fj.journal(tmp_path, n_records=3, n_points=5)  # small: every offset is one replay
    ends = [e for _, e in jrn.spans]
    want = {n: fj.expected_state(jrn, set(range(n, 3))) for n in range(4)}
    for at in range(len(jrn.data) + 1):
        reader, offset = replay(tmp_path, fj.truncated(jrn, at))
        whole = sum(1 for e in ends[1:] if e <= at)
        b = reader.books
        assert b.records == whole, at
        assert fj.state_of(reader.map, jrn) == want[whole], at
        last = max([e for e in ends if e <= at], default=0)
        assert (b.torn_bytes, b.damaged_bytes, b.bad_records) == (at - last, 0, 0), at
        assert offset == last, at  # the next writer appends right after the last whole record


def _flip_positions(jrn, rng):
    """Every bit of every frame field (magic, length, checksum) and 200 sampled body bits."""
    for s, _ in jrn.spans:
        for at in range(s, s + RECORD_FRAME.size):
            for bit in range(8):
                yield at, bit
    starts = {s + i for s, _ in jrn.spans for i in range(RECORD_FRAME.size)}
    body = [i for i in range(len(jrn.data)) if i not in starts]
    for at in rng.choice(body, 200, replace=False):
        yield int(at), int(rng.integers(8))


def test_one_flipped_bit_costs_the_record_it_hit_only(jrn, tmp_path):
    for at, bit in _flip_positions(jrn, np.random.default_rng(1)):
        hit = fj.record_at(jrn, at)
        reader, offset = replay(tmp_path, fj.flipped(jrn, at, bit))
        b = reader.books
        lost = set() if hit == 0 else {hit - 1}
        assert fj.state_of(reader.map, jrn) == fj.expected_state(jrn, lost), (at, bit)
        assert b.records == 4 - len(lost), (at, bit, b)
        s, e = jrn.spans[hit]
        # the damaged record's bytes, and only they, are skipped (or torn when it was the last)
        assert b.damaged_bytes + b.torn_bytes == e - s, (at, bit, b)
        assert b.header_missing == (hit == 0), (at, bit)
        if hit < len(jrn.spans) - 1:
            assert b.damaged and offset == len(jrn.data), (at, bit, b)


@pytest.mark.parametrize("name", sorted(fj.CRAFTED))
@pytest.mark.parametrize("i", [0, 2, 3])
def test_a_crafted_record_with_a_valid_checksum_is_refused_whole(jrn, tmp_path, name, i):
    reader, _ = replay(tmp_path, fj.crafted(jrn, i, name))
    b = reader.books
    assert (b.records, b.bad_records, b.damaged_bytes, b.torn_bytes) == (3, 1, 0, 0), b
    assert fj.state_of(reader.map, jrn) == fj.expected_state(jrn, {i})
    assert "record refused" in b.first_problem


def test_a_fifo_or_a_folder_as_journal_is_skipped_at_once(tmp_path):
    import os

    fifo = tmp_path / "fifo.journal"
    os.mkfifo(fifo)
    folder = tmp_path / "dir.journal"
    folder.mkdir()
    for path in (fifo, folder):
        reader = JournalReader(path)  # a FIFO opened for reading would block here
        reader.attach(fj.small_map())
        assert reader.finish() == 0 and not reader.exists
        assert "not a regular file" in reader.books.skipped


def test_the_writer_refuses_a_state_the_reader_would_refuse(tmp_path):
    m = fj.small_map()
    d = m.integrate(*fj.small_cloud(1))
    w = JournalWriter(tmp_path / "m.journal", m, {})
    size = w.bytes
    k = next(k for k, c in m._core.grid.cols.items() if c.dtype.kind == "f")
    g = m._core.grid.lookup(d.keys[:1])
    m._core.grid.cols[k][g] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        w.append(d.keys, {})
    assert w.bytes == size == (tmp_path / "m.journal").stat().st_size


def test_a_follower_that_sleeps_through_a_whole_journal_knows_it(tmp_path):
    # two rotations between two polls (an autosave, then a clean stop's save): the middle
    # file's records reach the follower's map never; it must notice and reload the autosave
    m = fj.small_map()
    path = tmp_path / "map.journal"
    w = JournalWriter(path, m, {"clouds": 0}, generation=3)
    reader = JournalReader(path)
    reader.attach(fj.small_map())
    d = m.integrate(*fj.small_cloud(1))
    w.append(d.keys, {"clouds": 1})
    reader.poll()
    assert not reader.missed and reader.generation == 3
    w.rotate({"clouds": 1})  # one rotation between polls: followed
    reader.poll()
    assert not reader.missed and reader.generation == 4
    w.rotate({"clouds": 1})
    d = m.integrate(*fj.small_cloud(2))
    w.append(d.keys, {"clouds": 2})  # in generation 5, which the follower will never read
    w.rotate({"clouds": 2})
    reader.poll()
    assert reader.missed and reader.generation == 6
