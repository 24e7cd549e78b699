"""The README's "the replay warns otherwise": a replay whose class table or input topic is not
the stack's says which `--set` makes them agree, and says nothing when they already do. The
service is built in process (its warnings come before any zenoh session)."""

from __future__ import annotations

import logging

import pytest

from smana.common.config import SmanaConfig
from smana.lab.data import synthetic as syn
from smana.services.replay.service import ReplayService


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    params = syn.SyntheticConfig(n_scans=2, beams=4, columns=16, noise_m=0.0)
    return syn.write_rellis_sequence(tmp_path_factory.mktemp("synthetic"), params)


def replay_warnings(caplog, *overrides: str) -> list[str]:
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="smana.replay"):
        ReplayService(SmanaConfig.load(None, list(overrides)))
    return [r.getMessage() for r in caplog.records if r.name == "smana.replay"]


def test_a_replay_warns_when_the_stack_reads_other_labels_or_another_topic(sequence, caplog):
    dataset = f'replay.dataset="{sequence}"'
    warned = replay_warnings(caplog, dataset)  # the defaults: garden table, mapper reads clouds
    assert any("--set general.class_table=rellis3d" in w for w in warned), warned
    assert any("--set mapper.inputs='[\"scan\"]'" in w for w in warned), warned
    agreed = replay_warnings(
        caplog, dataset, 'general.class_table="rellis3d"', 'mapper.inputs=["scan"]'
    )
    assert agreed == []
