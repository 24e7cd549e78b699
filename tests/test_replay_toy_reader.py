"""A dataset reader from the test folder (tests/support/toy_reader.py), registered with one line
and replayed through the stack: the replay service publishes its scans to the real mapper, both
in-process on the fake zenoh (tests/support/fake_zenoh.py), and the map holds what it showed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.messages import MapDelta
from smana.services.replay import readers
from tests.support.toy_reader import HEDGE, TERRAIN, ToyReader, write_toy_dataset

N_SCANS = 4
SPEC = "tests.support.toy_reader:ToyReader"


@pytest.fixture
def toy(tmp_path, monkeypatch):
    monkeypatch.setattr(readers, "READERS", readers.READERS.copy())  # the registration is undone
    readers.register("toy", SPEC)
    folder = tmp_path / "toy"
    write_toy_dataset(folder, [(0.1 * i, 0.5 * i, 0.0, 0.0) for i in range(N_SCANS)])
    return folder


def test_a_registered_reader_opens_by_name_and_by_spec(toy):
    assert readers.reader_class("toy") is ToyReader
    assert readers.reader_class(SPEC) is ToyReader
    with readers.open_dataset(toy, "toy") as reader:
        assert len(reader) == N_SCANS and reader.info().format == "toy"
        assert set(reader.scan(0).labels.tolist()) == {TERRAIN, HEDGE}
    with pytest.raises(ValueError, match="expected package.module:Class"):
        readers.register("bad", "tests.support.toy_reader")
    with pytest.raises(ValueError, match="not a DatasetReader"):
        readers.reader_class("tests.support.toy_reader:write_toy_dataset")


def test_a_toy_reader_replays_into_the_mapper(fake_stack, toy):
    sets = ["--set", 'mapper.inputs=["scan"]', "--set", "mapper.autosave_period_s=0"]
    fake_stack.service("mapper", *sets)
    fake_stack.wait_alive("mapper")
    run_dir = fake_stack.tmp / "run"
    replay = fake_stack.service(
        "replay", str(toy), "--lockstep", "--run-dir", str(run_dir), "--set", "replay.format=toy"
    )
    assert replay.wait(timeout=60) == 0, fake_stack.log("replay")
    summary = json.loads((run_dir / "replay.json").read_text())
    assert summary["published"] == summary["acknowledged"] == N_SCANS and summary["lost"] == 0
    assert fake_stack.query("mapper", "stats")["clouds"] == N_SCANS
    snap = fake_stack.query("mapper", "snapshot")
    assert isinstance(snap, MapDelta)
    hedge = snap.centres[snap.labels == HEDGE]
    # the hedge stood 2 m ahead of each of the sensor's four poses (x = 0, 0.5, 1, 1.5)
    assert len(hedge) > 0 and np.all((hedge[:, 0] > 1.8) & (hedge[:, 0] < 3.8))
