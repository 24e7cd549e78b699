"""The fuzz campaign of `smana bench fuzz`, bounded: a few hundred fuzzed inputs over every key the
mapper, navgraph, planner, explorer and coordinator listen to and every query they answer, against
the real services over an isolated loopback zenoh (the campaign's own router on a free port,
multicast and gossip off), and 200 map files, valid and corrupt, through the loaders. The
simulator is left to the bench (PyBullet start-up is heavy).

Checks (see `lab/bench/fuzz.py`): no crash (`internal` rejection or event), no restart, books
that add up to exactly what was sent, structural rejections as the codec predicts, state unchanged
by refused input and equal to references fed exactly the accepted input, clean exit."""

from __future__ import annotations

import pytest

from smana.common import keys
from smana.common.messages import MAX_PAYLOAD_BYTES, ServiceStatus
from smana.common.query import request
from smana.lab.bench.fuzz import Campaign, table
from tests.support import echo_service


@pytest.mark.multiprocess
@pytest.mark.slow
def test_fuzz_every_key_and_query_of_the_stack(tmp_path):
    campaign = Campaign(
        tmp_path / "fuzz",
        inputs=300,
        seed=11,
        services=("mapper", "navgraph", "planner", "explorer", "coordinator"),
        oversize=1,
        startup_timeout_s=600.0,
        settle_timeout_s=120.0,  # counted from readiness / progress
        map_files=200,
    )
    result = campaign.run()
    report = table(result)
    assert result.crashes == 0, report
    assert result.ok, report
    assert set(result.keys) == {t.name for t in campaign.targets}, report
    assert all(k.inputs > 0 for k in result.keys.values()), report
    # refused input of several kinds reached every service
    for name in ("mapper", "navgraph", "planner", "explorer", "coordinator"):
        assert len(result.service_figures[name].rejected) >= 2, report
    # map files: every kind made, each file in exactly one counter, some of each outcome
    from smana.lab.fuzz_maps import MAP_MUTATIONS

    assert set(result.map_files) == set(MAP_MUTATIONS), report
    assert result.map_inputs == 200, report
    assert sum(f.loaded for f in result.map_files.values()) > 0, report
    assert sum(f.refused for f in result.map_files.values()) > 100, report


def test_an_oversize_query_gets_an_error_reply(fake_stack):
    # found by smana bench fuzz: an oversize query was counted and left without any reply
    # (in-process on the fake zenoh: tests/support/fake_zenoh.py)
    st = fake_stack
    st.start("echo", echo_service.cli, "--robot", st.robot)
    st.wait_alive("echo")
    replies = list(
        st.session.get(
            keys.key(st.robot, "echo", "count"), payload=bytes(MAX_PAYLOAD_BYTES + 1), timeout=10.0
        )
    )
    status = request(st.session, keys.status(st.robot, "echo"))
    assert isinstance(status, ServiceStatus) and status.rejected == {"oversize": 1}
    assert replies and replies[0].err is not None
