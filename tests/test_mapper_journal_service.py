"""The mapper service keeps every acknowledged voxel through crashes, restarts, `--load` and clean
stops, and a damaged journal or autosave costs only what is damaged (in-process on the fake zenoh:
tests/support/fake_zenoh.py; a SIGKILL there is a crash: no on_stop, nothing saved). The
multi-process chain of take-overs is tests/test_takeover_chain.py."""

from __future__ import annotations

import os
import signal

import pytest

from smana.common import keys
from smana.common.messages import encode
from smana.lab import fuzz_journals as fj
from smana.services.mapper.journal import JournalReader
from smana.services.mapper.semantic_map import SemanticMap
from tests.conftest import wait_for
from tests.test_mapper_journal import assert_same_voxels
from tests.test_mapper_service import make_cloud, wait_stats


class Run:
    """The mapper on the fake stack, resuming its run (`mapper.load = auto`)."""

    def __init__(self, st, map_file, *extra, autosave_s: float = 3600.0):
        self.st, self.map_file, self.seq = st, map_file, 0
        self.args = (
            "--set",
            "mapper.resolution_m=0.2",
            "--set",
            f"mapper.autosave_period_s={autosave_s}",
            "--save",
            str(map_file),
            *extra,
        )

    def start(self, *more: str):
        self.proc = p = self.st.service("mapper", *self.args, *more)

        def ready() -> bool:  # this run's (wait_alive would see the killed one's exit)
            assert p.returncode is None, self.st.log("mapper")
            svc = p.service
            return svc is not None and svc.state == "running" and svc.kernels == "ready"

        assert wait_for(ready, 30), self.st.log("mapper")
        return p.service

    def send(self, n: int) -> dict:
        s, r = self.st.session, self.st.robot
        for _ in range(n):
            self.seq += 1
            want = self.stats()["clouds"] + 1
            s.put(keys.cloud(r), encode(make_cloud(self.seq)))
            assert wait_stats(s, r, lambda x, w=want: x["clouds"] >= w)["clouds"] == want
        return self.stats()

    def stats(self) -> dict:
        from smana.common.query import request

        return request(self.st.session, keys.query(self.st.robot, "mapper", "stats"))

    def status(self):
        from smana.common.query import request

        return request(self.st.session, keys.status(self.st.robot, "mapper"))

    def kill(self):
        self.st.stop(self.proc, signal.SIGKILL)

    def stop(self):
        assert self.st.stop(self.proc) == 0


def on_disk(map_file, svc) -> SemanticMap:
    """What a next start would get from the files alone: the autosave, then the journal."""
    m = SemanticMap.load(map_file) if map_file.exists() else None
    reader = JournalReader(map_file.with_suffix(".journal"))
    reader.attach(m if m is not None else SemanticMap.from_config(svc.config.mapper, svc.table))
    reader.finish()
    reader.close()
    reader.map.recount()
    return reader.map


def test_crashes_before_and_after_an_autosave_and_a_clean_stop_keep_every_voxel(
    fake_stack, tmp_path
):
    map_file = tmp_path / "map.npz"
    run = Run(fake_stack, map_file, "--set", "mapper.load=auto")
    first = run.start()
    run.send(3)
    want = first.map
    run.kill()
    # the second mapper replays, and keeps what it replayed in the journal: a second crash
    # before any autosave loses nothing (it used to start a new, empty journal)
    second = run.start()
    assert second.takeover["records_replayed"] == 3
    assert_same_voxels(want, second.map)
    assert_same_voxels(want, on_disk(map_file, second))
    run.send(2)
    want = second.map
    run.kill()
    third = run.start()
    assert third.takeover["records_replayed"] == 5
    assert_same_voxels(want, third.map)
    # a clean stop right after a take-over saves what was replayed (it saved nothing)
    map_file.unlink(missing_ok=True)
    run.stop()
    assert_same_voxels(want, SemanticMap.load(map_file))
    # and after an autosave: the autosave and the journal since then
    fourth = run.start()
    run.send(2)
    fourth.save(map_file)
    fourth._rotate_journal()
    run.send(2)
    want = fourth.map
    run.kill()
    fifth = run.start()
    assert fifth.takeover["records_replayed"] == 2
    assert_same_voxels(want, fifth.map)
    run.stop()
    assert_same_voxels(want, SemanticMap.load(map_file))


def test_load_of_the_autosave_replays_its_journal_and_another_file_keeps_it_aside(
    fake_stack, tmp_path
):
    map_file = tmp_path / "map.npz"
    run = Run(fake_stack, map_file)
    first = run.start()
    run.send(2)
    first.save(map_file)
    first._rotate_journal()
    run.send(2)
    want = first.map
    run.kill()
    journal = map_file.with_suffix(".journal")
    before = journal.read_bytes()
    second = run.start("--load", str(map_file))  # the autosave itself: its journal replayed
    assert second.takeover["records_replayed"] == 2
    assert_same_voxels(want, second.map)
    run.kill()
    other = tmp_path / "other.npz"
    SemanticMap.load(map_file).save(other)
    run.start("--load", str(other))  # another map: the journal is not its, and is kept
    kept = journal.with_name("map.journal.unused-1")
    assert kept.read_bytes().startswith(before[:100]) and len(kept.read_bytes()) >= len(before)
    assert run.status().events.get("journal_kept_aside") == 1
    run.stop()


def _crashed(fake_stack, tmp_path, n_saved=2, n_journal=3):
    """A run killed after an autosave of `n_saved` clouds and `n_journal` journaled ones."""
    map_file = tmp_path / "map.npz"
    run = Run(fake_stack, map_file, "--set", "mapper.load=auto")
    svc = run.start()
    run.send(n_saved)
    svc.save(map_file)
    svc._rotate_journal()
    run.send(n_journal)
    run.kill()
    return run, svc.map


def test_a_damaged_autosave_is_one_warning_and_the_journal_still_replays(fake_stack, tmp_path):
    run, full = _crashed(fake_stack, tmp_path)
    good = run.map_file.read_bytes()
    run.map_file.write_bytes(good[: len(good) // 2])
    svc = run.start()  # not exit 2, not "refused its configuration"
    assert run.status().events.get("autosave_damaged") == 1
    assert svc.takeover["records_replayed"] == 3
    assert (tmp_path / "map.npz.unused-1").read_bytes() == good[: len(good) // 2]
    # the map is what the journal held: every voxel it holds is the full map's
    j = svc.map.stats()
    assert 0 < j["voxels_observed"] <= full.stats()["voxels_observed"]
    run.send(1)  # and it maps on
    run.stop()
    assert SemanticMap.load(run.map_file).stats()["voxels_observed"] >= j["voxels_observed"]


@pytest.mark.parametrize("damage", ["flip", "crafted_nan", "crafted_no_counters", "fifo"])
def test_a_damaged_journal_costs_the_damaged_record_only(fake_stack, tmp_path, damage):
    run, full = _crashed(fake_stack, tmp_path)
    journal = run.map_file.with_suffix(".journal")
    if damage == "fifo":
        journal.unlink()
        os.mkfifo(journal)
    else:
        data = journal.read_bytes()
        reader = JournalReader(journal)  # the spans of its records
        reader.attach(SemanticMap.load(run.map_file))
        spans, at = [], 0
        import struct

        while at < len(data):
            n = struct.unpack_from("<4sII", data, at)[1] + 12
            spans.append((at, at + n))
            at += n
        s, e = spans[2]  # the second voxel record
        if damage == "flip":
            data = data[: s + 20] + bytes([data[s + 20] ^ 4]) + data[s + 21 :]
        else:
            j = fj.Journal(data, spans, [], "")
            import msgpack

            rec = msgpack.unpackb(data[s + 12 : e], raw=False)
            if damage == "crafted_nan":
                k = next(iter(rec["cols"]))
                rec["cols"][k]["dtype"] = "<f8"  # and a dtype the map does not hold
            else:
                rec["service"] = {"clouds": "x"}
            data = fj.with_record(j, 1, rec)
        journal.write_bytes(data)
    svc = run.start()  # live: never a hang, an exit 2 or a crash loop
    st = run.status()
    if damage == "fifo":
        assert st.events.get("journal_kept_aside") == 1
        assert svc.takeover["records_replayed"] == 0
    else:
        assert st.events.get("journal_damaged") == 1, st.events
        assert svc.takeover["records_replayed"] == 2
        # what was replayed was saved before a new journal started
        assert_same_voxels(svc.map, SemanticMap.load(run.map_file))
        assert svc.journal.records == 0
    assert svc.map.stats()["voxels_observed"] <= full.stats()["voxels_observed"]
    run.send(1)
    run.stop()
