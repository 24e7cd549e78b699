"""The fleet mapper (`mapper --robot fleet --set mapper.source=fleet`) in-process on the fake zenoh
(tests/support/fake_zenoh.py): two members' mappers fed clouds, the fleet mapper merging their
deltas, and an unchanged navgraph run as `--robot fleet` building one graph from it. The fleet
mapper starts after the members mapped (it fills in from their snapshots), follows their delta
streams, and resyncs a member from its own map when deltas of it were lost."""

from __future__ import annotations

import numpy as np
import pytest

from smana.common import keys
from smana.common.config.mapper import MapperConfig
from smana.common.messages import GraphPatch, MapDelta, SemanticCloud, encode
from smana.common.query import request
from smana.services.mapper.fleet import FleetMap
from tests.conftest import kernels_ready, wait_for

RES = 0.2
AREAS = {"r1": 0.0, "r2": 5.0}  # each member maps a 3 m box from this x on
MEMBERS = '["r1","r2"]'


def make_cloud(member: str, seq: int) -> SemanticCloud:
    rng = np.random.default_rng(100 * seq + int(member[1:]))
    x0 = AREAS[member]
    n = 400
    pts = np.column_stack(
        [rng.uniform(x0, x0 + 3, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-0.4, 0.0, n)]
    ).astype(np.float32)
    return SemanticCloud(
        stamp_s=float(seq),
        seq=seq,
        points=pts,
        labels=rng.choice(np.array([1, 2, 4, 8], np.uint16), n),
        confidences=rng.uniform(0.3, 1.0, n).astype(np.float32),
        sensor_position=np.array([x0 + 0.3 * seq, 0.0, 1.2]),
    )


def as_dict(d) -> dict:
    k = np.floor(d.centres / RES).astype(np.int64)
    return {tuple(a): (float(v), int(lab)) for a, v, lab in zip(k, d.values, d.labels)}


def merge_of(maps: dict) -> dict:
    """What the fleet map must be: every member's whole map (a SemanticMap or its observed
    snapshot) merged by a FleetMap fed only those, one replace per member."""
    fm = FleetMap(MapperConfig(resolution_m=RES), list(maps))
    for name, m in maps.items():
        d = m.observed_voxels() if hasattr(m, "observed_voxels") else m
        fm.replace(name, d.centres, d.labels, d.confidences, d.values)
    return as_dict(fm.observed_voxels())


def books_add_up(session, robot: str, service: str) -> None:
    st = request(session, keys.status(robot, service))
    assert st.books_add_up(), st


def test_fleet_mapper_merges_members_and_resyncs_a_lost_stream(fake_stack):
    st, s = fake_stack, fake_stack.session
    common = ("--set", f"mapper.resolution_m={RES}", "--set", "mapper.autosave_period_s=0")
    runs = {m: st.service("mapper", "--robot", m, *common, "--save", f"{m}.npz") for m in AREAS}
    for m in AREAS:
        st.wait_alive("mapper", robot=m)
    sent = dict.fromkeys(AREAS, 0)

    def feed(member: str, n: int = 1) -> None:
        for _ in range(n):
            sent[member] += 1
            before = runs[member].service.clouds
            s.put(keys.cloud(member), encode(make_cloud(member, sent[member])))
            assert wait_for(lambda b=before: runs[member].service.clouds == b + 1, 30)

    for m in AREAS:  # the members map before the fleet mapper is there (a rejoin)
        feed(m, 2)

    fleet_args = ("--robot", "fleet", *common, "--set", "mapper.source=fleet",
                  "--set", f"fleet.robots={MEMBERS}", "--save", "fleet.npz")  # fmt: skip
    fleet_run = st.service("mapper", *fleet_args)
    st.wait_alive("mapper", robot="fleet")
    fleet = fleet_run.service
    assert wait_for(lambda: all(fleet.member_books[m]["resyncs"] == 1 for m in AREAS), 30)
    maps = {m: runs[m].service.map for m in AREAS}
    assert as_dict(fleet.map.observed_voxels()) == merge_of(maps)

    nav = st.service("navgraph", "--robot", "fleet")
    st.wait_alive("navgraph", robot="fleet")
    for m in AREAS:
        feed(m, 1)
    assert wait_for(lambda: fleet.map.deltas_applied == [1, 1], 30)
    assert as_dict(fleet.map.observed_voxels()) == merge_of(maps)
    # one graph for both: known nodes in each member's area
    assert wait_for(lambda: nav.service.patch_seq > 0 and st.drained("navgraph"), 30)
    graph = request(s, keys.query("fleet", "navgraph", "graph"))
    assert isinstance(graph, GraphPatch)
    x = graph.origin_xy[0] + (graph.cells[:, 0] + 0.5) * graph.resolution_m
    for x0 in AREAS.values():
        assert ((x > x0 + 0.5) & (x < x0 + 2.5)).sum() > 20, x0

    # r2's deltas lost on the way (the link dropped them): the next one shows the gap, and the
    # fleet mapper fills it from r2's own map
    lost = {"on": True}
    push = fleet._push

    def lossy_push(item):
        handler = item[1]
        if lost["on"] and item[0] == "sample" and getattr(handler, "__defaults__", None) == ("r2",):
            return
        push(item)

    fleet._push = lossy_push
    feed("r2", 2)
    lost["on"] = False
    feed("r2", 1)
    feed("r1", 1)
    assert wait_for(lambda: fleet.member_books["r2"]["resyncs"] == 2, 30)
    assert wait_for(lambda: st.drained("mapper") and fleet.events["delta_gap"] >= 1, 10)
    assert wait_for(lambda: as_dict(fleet.map.observed_voxels()) == merge_of(maps), 10)

    # the fleet's snapshot and the navgraph agree with it; stats tell per member
    snap = request(s, keys.query("fleet", "mapper", "snapshot"), {"observed": True})
    assert isinstance(snap, MapDelta) and as_dict(snap) == merge_of(maps)
    stats = request(s, keys.query("fleet", "mapper", "stats"))
    assert stats["members"]["r2"]["resyncs"] == 2 and stats["members"]["r1"]["deltas_applied"] == 2
    assert stats["members"]["r2"]["last_seq"] == runs["r2"].service.delta_seq
    assert stats["voxels_observed"] == len(merge_of(maps))

    # a delta at another resolution is refused by its kind, the map untouched
    bad = runs["r1"].service._message(
        runs["r1"].service.map.occupied_voxels(), 99.0, 99, runs["r1"].service.delta_seq + 1
    )
    bad.resolution_m = 0.5
    st.publish(keys.map_delta("r1"), bad)
    assert wait_for(lambda: fleet.books.rejected["resolution"] == 1, 10)
    assert as_dict(fleet.map.observed_voxels()) == merge_of(maps)

    # r2's mapper drops off (its map saved) and comes back resuming it, as a new producer:
    # its token coming back resyncs it, and its new stream is followed
    assert st.stop(runs["r2"]) == 0
    st.procs = [(n, p) for n, p in st.procs if p is not runs["r2"]]  # wait_alive must not see it
    runs["r2"] = st.service("mapper", "--robot", "r2", *common, "--load", "r2.npz")
    st.wait_alive("mapper", robot="r2")
    assert wait_for(lambda: fleet.member_books["r2"]["resyncs"] == 3, 30)
    feed("r2", 1)
    maps["r2"] = runs["r2"].service.map
    assert wait_for(lambda: as_dict(fleet.map.observed_voxels()) == merge_of(maps), 10)
    assert fleet.member_books["r2"]["last_seq"] == 1
    assert wait_for(lambda: st.drained("navgraph"), 10)
    for robot in ("r1", "r2", "fleet"):
        books_add_up(s, robot, "mapper")
    books_add_up(s, "fleet", "navgraph")

    # the fleet mapper saves its layers on shutdown and resumes from them
    applied = fleet.map.deltas_applied
    assert st.stop(fleet_run) == 0
    st.procs = [(n, p) for n, p in st.procs if p is not fleet_run]
    again_run = st.service("mapper", *fleet_args, "--load", "auto")
    st.wait_alive("mapper", robot="fleet")
    again = again_run.service
    assert again.map.deltas_applied == applied
    assert wait_for(lambda: as_dict(again.map.observed_voxels()) == merge_of(maps), 10)


def test_fleet_mapper_refuses_a_tsdf_map(fake_stack):
    run = fake_stack.service(
        "mapper", "--robot", "fleet", "--set", "mapper.source=fleet",
        "--set", "mapper.backend=tsdf", "--set", f"fleet.robots={MEMBERS}",
    )  # fmt: skip
    assert run.wait(10) == 2


def snapshot(session, robot: str) -> MapDelta:
    return request(session, keys.query(robot, "mapper", "snapshot"), {"observed": True})


@pytest.mark.multiprocess
def test_fleet_mapper_fills_in_from_members_that_mapped_before(zenoh_stack):
    """Real processes: the fleet mapper starts after the members mapped (a base that comes up
    late, or a link that returns) and fills in from their snapshots."""
    st, s = zenoh_stack, zenoh_stack.session
    common = ("--set", f"mapper.resolution_m={RES}", "--set", "mapper.autosave_period_s=0")
    for m in AREAS:
        st.service(f"mapper-{m}", "--robot", m, *common, module="smana.services.mapper")
    for m in AREAS:
        assert wait_for(lambda m=m: kernels_ready(s, m, "mapper"), 60), st.log(f"mapper-{m}")
        pub = st.publisher(keys.cloud(m))
        for seq in (1, 2):  # clouds are latest-wins: one at a time
            pub.put(encode(make_cloud(m, seq)))
            assert wait_for(
                lambda m=m, n=seq: request(s, keys.query(m, "mapper", "stats"))["clouds"] == n
            )
        pub.undeclare()

    st.service("mapper", "--robot", "fleet", *common, "--set", "mapper.source=fleet",
               "--set", f"fleet.robots={MEMBERS}")  # fmt: skip
    st.wait_alive("mapper", robot="fleet")

    def merged() -> bool:
        stats = request(s, keys.query("fleet", "mapper", "stats"))
        return all(stats["members"][m]["resyncs"] >= 1 for m in AREAS)

    assert wait_for(merged, 30)
    want = merge_of({m: snapshot(s, m) for m in AREAS})
    assert as_dict(snapshot(s, "fleet")) == want

    st_fleet = request(s, keys.status("fleet", "mapper"))
    assert st_fleet.books_add_up(), st_fleet
