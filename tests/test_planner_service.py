"""navgraph and planner fed recorded map deltas. As separate processes over an isolated zenoh
router: the graph reaches the planner (also one started late), an obstacle that moves away is
cleared end to end, and every error reply comes back as a PathReply in the query's encoding.
In-process on the fake zenoh: spoofed patch numbers neither freeze nor wipe the planner."""

from __future__ import annotations

import json
import subprocess
import sys

import msgpack
import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import GraphPatch, MapDelta, PathReply, PathRequest, decode, encode
from smana.common.query import QueryError, request
from tests.conftest import wait_for

RES = 0.1
TERRAIN, GRASS, HEDGE, OBSTACLE = 2, 1, 4, 7
CONFIG = [
    "--set",
    "navgraph.bounds_min_xy=[0.0, 0.0]",
    "--set",
    "navgraph.bounds_max_xy=[10.0, 10.0]",
    "--set",
    "navgraph.robot_radius_m=0.4",
    "--set",
    "planner.graph_sync_timeout_s=3.0",
]


def vox(ix, iy, iz):
    return [(ix + 0.5) * RES, (iy + 0.5) * RES, (iz + 0.5) * RES]


def delta(seq, voxels, labels, occupied) -> MapDelta:
    n = len(voxels)
    occ = np.broadcast_to(np.asarray(occupied, np.uint8), (n,)).copy()
    return MapDelta(
        stamp_s=float(seq),
        seq=seq,
        cloud_seq=seq,
        backend="octree-max",
        resolution_m=RES,
        centres=np.asarray(voxels, np.float32).reshape(-1, 3),
        labels=np.broadcast_to(np.asarray(labels, np.uint16), (n,)).copy(),
        confidences=np.ones(n, np.float32),
        occupied=occ,
        values=np.where(occ == 1, 2.0, -2.0).astype(np.float32),
    )


def recorded_deltas():
    """An 8 x 8 m garden inside 10 x 10 m bounds: terrain with a grass patch; a hedge along
    x = 4 m from y = 0 to 6 m; a closed hedge ring round (6.5, 2.5); a person standing in the gap
    at x = 4 m, y 6..8 m; then the map clearing the person's voxels (it walked away)."""
    ground = [vox(i, j, 0) for i in range(80) for j in range(80)]
    ground_lab = [
        GRASS if 10 <= i < 30 and 10 <= j < 30 else TERRAIN for i in range(80) for j in range(80)
    ]
    hedge = [vox(40, j, k) for j in range(60) for k in range(1, 8)]
    ring = []
    for a in np.linspace(0, 2 * np.pi, 120, endpoint=False):
        ix, iy = int(65 + 12 * np.cos(a)), int(25 + 12 * np.sin(a))
        ring += [vox(ix, iy, k) for k in range(1, 6)]
    person = [vox(i, j, k) for i in (40, 41) for j in range(60, 80) for k in range(1, 17)]
    return [
        delta(1, ground, ground_lab, 1),
        delta(2, hedge + ring, HEDGE, 1),
        delta(3, person, OBSTACLE, 1),
        delta(4, person, OBSTACLE, 0),
    ]


def stats(stack, service):
    return request(stack.session, keys.query(stack.robot, service, "stats"), timeout_s=5)


def plan(stack, start, goal, as_json=False, **kw) -> PathReply:
    req = PathRequest(
        request_id="t", start=np.array(start, float), goal=np.array(goal, float), **kw
    )
    reply = request(stack.session, keys.path_query(stack.robot), req, 10.0, as_json=as_json)
    assert isinstance(reply, PathReply), reply
    return reply


def raw_query(stack, key, payload: bytes, encoding):
    replies = list(stack.session.get(key, payload=payload, encoding=encoding, timeout=10.0))
    assert replies and replies[0].ok is not None
    return replies[0].ok.payload.to_bytes()


@pytest.mark.multiprocess
def test_navgraph_and_planner_over_zenoh(zenoh_stack):
    import zenoh

    stack = zenoh_stack
    deltas = recorded_deltas()
    navgraph = stack.service("navgraph", *CONFIG)
    planner = stack.service("planner", *CONFIG)
    stack.wait_alive("navgraph")
    stack.wait_alive("planner")

    # No graph yet.
    r = plan(stack, (1, 1), (2, 3))
    assert not r.ok and r.error == "no_graph"

    pub = stack.publisher(keys.map_delta(stack.robot))
    for d in deltas[:3]:
        pub.put(encode(d))
    assert wait_for(lambda: stats(stack, "navgraph")["deltas"] == 3)
    n_patches = stats(stack, "navgraph")["patch_seq"]
    assert n_patches == 3

    # A planner started after the patches were published gets the graph from navgraph.
    assert stack.stop(planner) == 0
    stack.procs = [(n, p) for n, p in stack.procs if p is not planner]  # its log stays
    planner = stack.service("planner", *CONFIG)
    stack.wait_alive("planner")
    st = stats(stack, "planner")
    assert st["syncs"] == 1 and st["last_patch_seq"] == n_patches and st["nodes_known"] > 0

    ok = plan(stack, (1, 1), (2, 3))
    assert ok.ok and ok.request_id == "t" and len(ok.path) > 5
    assert ok.cost_total == pytest.approx(
        ok.cost_distance + ok.cost_height + ok.cost_traversability
    )
    assert set(ok.label_share) <= {"terrain", "grass"}
    # The person stands in the only gap in the hedge: the far side is unreachable...
    r = plan(stack, (1, 1), (7, 5))
    assert not r.ok and r.error == "unreachable"
    # ...until the map clears the person's voxels.
    pub.put(encode(deltas[3]))
    assert wait_for(lambda: stats(stack, "planner")["last_patch_seq"] == n_patches + 1)
    r = plan(stack, (1, 1), (7, 5))
    assert r.ok and r.path[:, 1].max() > 6.0, r.message

    # Every error reply.
    r = plan(stack, (1, 1), (6.5, 2.5))  # inside the closed ring
    assert r.error == "unreachable"
    r = plan(stack, (4.05, 2.0), (1, 1))
    assert r.error == "start_blocked" and "obstacle" in r.message and len(r.nearest_free) == 2
    r = plan(stack, (1, 1), (3.85, 2.0))
    assert r.error == "goal_blocked" and "safety zone" in r.message
    assert abs(r.nearest_free[0] - 4.05) >= 0.4  # outside the safety zone
    r = plan(stack, (1, 1), (9.0, 1.0))  # in bounds, never mapped
    assert r.error == "goal_blocked" and "unknown" in r.message
    assert plan(stack, (1, 1), (9.0, 1.0), allow_unknown=True).ok
    r = plan(stack, (1, 1), (12.0, 1.0))
    assert r.error == "out_of_bounds" and "goal" in r.message
    r = plan(stack, (1, 1), (2, 3), class_costs={HEDGE: 1.0})
    assert r.error == "malformed"
    key = keys.path_query(stack.robot)
    body = raw_query(stack, key, b"\xc1 not msgpack", zenoh.Encoding("application/msgpack"))
    bad = decode(body)
    assert isinstance(bad, PathReply) and bad.error == "malformed"
    body = raw_query(stack, key, b'{"start": [1]}', zenoh.Encoding.APPLICATION_JSON)
    bad = json.loads(body)
    assert bad["ok"] is False and bad["error"] == "malformed"

    # JSON from any zenoh tool: only start and goal, and a JSON reply.
    body = raw_query(
        stack, key, b'{"start": [1, 1], "goal": [2, 3]}', zenoh.Encoding.APPLICATION_JSON
    )
    good = json.loads(body)
    assert good["ok"] is True and good["cost_total"] == pytest.approx(ok.cost_total)
    assert plan(stack, (1, 1), (2, 3), as_json=True).ok
    # ...or selector parameters only, e.g. `z_get -s 'smana/r1/planner/path?start=1,1;goal=2,3'`.
    replies = list(stack.session.get(f"{key}?start=1,1;goal=2,3;format=json", timeout=10.0))
    good = json.loads(replies[0].ok.payload.to_bytes())
    assert good["ok"] is True and good["cost_total"] == pytest.approx(ok.cost_total)

    # Graph queries on navgraph.
    g = request(stack.session, keys.query(stack.robot, "navgraph", "graph"), {"box": [3, 0, 5, 2]})
    # Nodes 15..25 x 0..10: the box's corners are inside the nodes that hold them.
    assert isinstance(g, GraphPatch) and len(g.cells) == 11 * 11
    assert g.cells[:, 0].min() == 15 and g.cells[:, 1].max() == 10
    node = request(stack.session, keys.query(stack.robot, "navgraph", "node"), {"x": 4.05, "y": 1})
    assert node["obstacle"] and node["class"] == "hedge" and len(node["column"]) == 4 + 2 * 7
    with pytest.raises(QueryError):
        request(stack.session, keys.query(stack.robot, "navgraph", "node"), {"x": 40, "y": 1})

    st = stats(stack, "planner")
    assert st["outcomes"]["malformed"] >= 3 and st["outcomes"]["ok"] >= 4

    # `smana plan` prints the path (exit 0), the planner's error (1), or that nobody answered (2).
    def smana_plan(*args):
        argv = [
            sys.executable,
            "-m",
            "smana.deploy.cli",
            "plan",
            *stack.zenoh_args(),
            "--robot",
            stack.robot,
            *args,
        ]
        return subprocess.run(argv, capture_output=True, text=True, timeout=60)

    out = smana_plan("--from", "1,1", "--to", "7,5", "--cost", "grass=4", "--path")
    assert out.returncode == 0, out.stderr
    assert "cost" in out.stdout and "traversability" in out.stdout and "terrain" in out.stdout
    out = smana_plan("--from", "1,1", "--to", "3.85,2")
    assert out.returncode == 1 and "goal_blocked" in out.stdout and "nearest free" in out.stdout

    # navgraph restarts (with no mapper to resume from): the planner drops the old graph...
    assert stack.stop(navgraph) == 0
    stack.procs = [(n, p) for n, p in stack.procs if p is not navgraph]
    navgraph = stack.service("navgraph", *CONFIG)
    stack.wait_alive("navgraph")
    assert wait_for(lambda: stats(stack, "planner")["syncs"] == 2)
    assert plan(stack, (1, 1), (2, 3)).error == "no_graph"
    # ...and follows the new one from its first patch.
    pub.put(encode(deltas[0]))
    assert wait_for(lambda: stats(stack, "planner")["last_patch_seq"] == 1)
    assert plan(stack, (1, 1), (2, 3)).ok
    assert stack.stop(planner) == 0 and stack.stop(navgraph) == 0
    out = smana_plan("--from", "1,1", "--to", "2,3", "--timeout", "2")
    assert out.returncode == 2 and "no service answered" in out.stderr


def test_spoofed_patch_numbers_neither_freeze_nor_wipe_the_planner(fake_stack):
    # Once, one GraphPatch with seq = 2**64-1 froze the planner's graph (every genuine patch
    # after it looked old) and one with seq = 1 wiped it to a single node.
    stack = fake_stack
    deltas = recorded_deltas()
    stack.service("navgraph", *CONFIG)
    stack.service("planner", *CONFIG)
    stack.wait_alive("navgraph")
    stack.wait_alive("planner")
    pub = stack.publisher(keys.map_delta(stack.robot))
    for d in deltas[:3]:
        pub.put(encode(d))
    assert wait_for(lambda: stats(stack, "planner")["last_patch_seq"] == 3)
    assert plan(stack, (1, 1), (7, 5)).error == "unreachable"  # the person in the gap
    real = request(stack.session, keys.query(stack.robot, "navgraph", "graph"))
    assert isinstance(real, GraphPatch) and real.producer
    # genuine patches the planner's start-up sync already held count as `covered`: from here on
    base = status(stack, "planner")
    base_covered = base.dropped.get("covered", 0)
    assert not base.rejected, base

    one_node = GraphPatch(
        seq=1,
        resolution_m=RES * 2,
        origin_xy=np.zeros(2),
        cells=np.array([[5, 5]], np.int32),
        labels=np.array([HEDGE], np.uint16),
        heights=np.zeros(1, np.float32),
        flags=np.array([3], np.uint8),
        producer=real.producer,
    )
    patches = stack.publisher(keys.graph_patch(stack.robot))
    for seq, producer in ((2**63 - 1, real.producer), (1, real.producer), (4, "a stranger")):
        one_node.seq, one_node.producer = seq, producer
        patches.put(encode(one_node))
    wrapped = msgpack.unpackb(encode(one_node))
    wrapped["seq"] = 2**64 - 1  # beyond int64: refused by the codec itself
    patches.put(msgpack.packb(wrapped))

    def settled(st):
        return sum(st.rejected.values()) + st.dropped.get("covered", 0) - base_covered

    assert wait_for(lambda: settled(status(stack, "planner")) >= 4)
    st = status(stack, "planner")
    # far ahead: `sequence`; a stranger: `producer`; beyond int64: `value`; gone back: `sequence`,
    # or `covered` when the resync the first one asked for came before it (then seq 1 is in it)
    assert st.rejected["producer"] == 1 and st.rejected["value"] == 1, st
    assert st.rejected["sequence"] + st.dropped.get("covered", 0) - base_covered == 2, st
    assert st.books_add_up(), st

    # Not wiped: the old graph answers as before; not frozen: the genuine next patch (the person
    # walks away) still gets through.
    assert plan(stack, (1, 1), (2, 3)).ok
    pub.put(encode(deltas[3]))
    assert wait_for(lambda: plan(stack, (1, 1), (7, 5)).ok, 30)
    assert stats(stack, "planner")["last_patch_seq"] == 4


def status(stack, service):
    from smana.common.messages import ServiceStatus

    st = request(stack.session, keys.status(stack.robot, service), timeout_s=5)
    assert isinstance(st, ServiceStatus)
    return st
