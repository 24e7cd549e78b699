"""The mapper service. In-process on the fake zenoh (tests/support/fake_zenoh.py): clouds in,
deltas out, queries, bad input counted without touching the map. As a process over an isolated
loopback zenoh: the map saved on shutdown, and a new process resuming from it with --load."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import MapDelta, SemanticCloud, decode, encode
from smana.common.query import QueryError, request
from smana.services.mapper.semantic_map import SemanticMap

RES = 0.2


def make_cloud(seq: int, n: int = 600) -> SemanticCloud:
    rng = np.random.default_rng(seq)
    pts = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    pts[:, 2] = rng.uniform(-1, 0.5, n)
    return SemanticCloud(
        stamp_s=float(seq),
        seq=seq,
        points=pts,
        labels=rng.choice(np.array([1, 2, 4, 8], np.uint16), n),
        confidences=rng.uniform(0.3, 1.0, n).astype(np.float32),
        sensor_position=np.array([0.1 * seq, 0.0, 0.8]),
    )


class DeltaInbox:
    """The mapper's deltas, from a subscriber the stack has passed on (`subscriber`): a delta
    published after this returns reaches it."""

    def __init__(self, stack, key):
        self.items: list[MapDelta] = []
        self.cv = threading.Condition()
        self.sub = stack.subscriber(key, self._on)

    def _on(self, sample):
        msg = decode(sample.payload.to_bytes(), MapDelta)
        with self.cv:
            self.items.append(msg)
            self.cv.notify_all()

    def wait_for(self, cloud_seq: int, timeout_s: float = 60.0) -> MapDelta:
        deadline = time.monotonic() + timeout_s
        with self.cv:
            while True:
                for d in self.items:
                    if d.cloud_seq == cloud_seq:
                        return d
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no MapDelta for cloud {cloud_seq}")
                self.cv.wait(left)


def wait_stats(session, robot, pred, timeout_s=20.0):
    key = keys.query(robot, "mapper", "stats")
    deadline = time.monotonic() + timeout_s
    while True:
        s = request(session, key)
        if pred(s) or time.monotonic() > deadline:
            return s
        time.sleep(0.1)


def mapper_args(map_file):
    return (
        "--set",
        f"mapper.resolution_m={RES}",
        "--set",
        "mapper.autosave_period_s=0",
        "--save",
        str(map_file),
    )


def test_mapper_service_end_to_end(fake_stack, tmp_path):
    st = fake_stack
    map_file = tmp_path / "map.npz"
    args = mapper_args(map_file)
    proc = st.service("mapper", *args)
    st.wait_alive("mapper")
    s, r = st.session, st.robot
    inbox = DeltaInbox(st, keys.map_delta(r))

    reference = SemanticMap("octree-max", RES, 10.0, 1.0)
    clouds = [make_cloud(i) for i in range(1, 4)]
    for c in clouds:
        s.put(keys.cloud(r), encode(c))
        got = inbox.wait_for(c.seq)
        want = reference.integrate(c.points, c.labels, c.confidences, c.sensor_position)
        assert got.backend == "octree-max" and got.resolution_m == RES
        assert len(got.centres) == len(want) > 0
        order_got, order_want = np.lexsort(got.centres.T), np.lexsort(want.centres.T)
        np.testing.assert_array_equal(got.centres[order_got], want.centres[order_want])
        np.testing.assert_array_equal(got.values[order_got], want.values[order_want])
        np.testing.assert_array_equal(got.labels[order_got], want.labels[order_want])
    before = request(s, keys.query(r, "mapper", "stats"))
    assert before["clouds"] == 3
    assert before["voxels_observed"] == reference.stats()["voxels_observed"]

    # bad input: garbage, inconsistent lengths, another frame -> rejected, map untouched
    # latest wins: each bad cloud is handled before the next is sent, or it would be dropped stale
    s.put(keys.cloud(r), b"\x93garbage")
    assert st.drained("mapper")
    bad = make_cloud(50)
    bad.labels = bad.labels[:-5]
    s.put(keys.cloud(r), encode(bad))
    assert st.drained("mapper")
    other = make_cloud(51)
    other.frame_id = "camera"
    s.put(keys.cloud(r), encode(other))
    assert st.drained("mapper")
    after_bad = wait_stats(s, r, lambda x: x["clouds"] == 3)
    assert after_bad["voxels_observed"] == before["voxels_observed"]
    assert after_bad["clouds"] == 3

    # NaN points are dropped and counted, unknown labels become 0 and are counted; the rest maps
    nan_cloud = make_cloud(60)
    # stamped just after cloud 3: the stream's clock may run at most 100x wall time, and no
    # pause is left here to let stamp 60 come true (common/plausibility.py)
    nan_cloud.stamp_s = 4.0
    nan_cloud.points[:7] = np.nan
    nan_cloud.labels[10:13] = 3  # id 3 is not in the garden table
    s.put(keys.cloud(r), encode(nan_cloud))
    d = inbox.wait_for(60)
    assert len(d.centres) > 0
    status = request(s, keys.status(r, "mapper"))
    for kind in ("malformed", "length", "frame"):
        assert status.rejected.get(kind, 0) >= 1, (kind, status.rejected)
    for kind in ("nonfinite_points", "unknown_labels"):
        assert status.events.get(kind, 0) >= 1, (kind, status.events)
    assert status.state == "running" and status.books_add_up(), status
    stats = request(s, keys.query(r, "mapper", "stats"))
    assert stats["points_dropped_nonfinite"] == 7 and stats["labels_replaced"] == 3

    # queries: point, snapshot in a box, bad query answered with an error
    occ = request(s, keys.query(r, "mapper", "snapshot"))
    assert isinstance(occ, MapDelta) and len(occ.centres) == stats["voxels_occupied"]
    boxed = request(s, keys.query(r, "mapper", "snapshot"), {"box": [-1, -1, -1, 1, 1, 1]})
    assert 0 < len(boxed.centres) < len(occ.centres)
    assert (np.abs(boxed.centres) <= 1).all()
    q = request(s, keys.query(r, "mapper", "point"), {"points": occ.centres[:5].tolist()})
    assert all(q["known"]) and all(q["occupied"])
    with pytest.raises(QueryError) as err:
        request(s, keys.query(r, "mapper", "point"), {"points": [[1, 2]]})
    assert err.value.kind == "value"
    for name in ("../escape.npz", "config.toml"):  # nor a file of the run dir but a map
        with pytest.raises(QueryError):
            request(s, keys.query(r, "mapper", "save"), {"name": name})

    inbox.sub.undeclare()
    assert st.stop(proc) == 0


def test_a_full_journal_brings_the_autosave_forward(fake_stack, tmp_path, monkeypatch):
    # autosave only on shutdown, and a journal that is full after one record: the next tick
    # saves the map and starts a new journal, so its disk use stays bounded
    from smana.services.mapper import service as mapper_service

    monkeypatch.setattr(mapper_service, "JOURNAL_MAX_BYTES", 1)
    map_file = tmp_path / "map.npz"
    fake_stack.service("mapper", *mapper_args(map_file))
    fake_stack.wait_alive("mapper")
    s, r = fake_stack.session, fake_stack.robot
    s.put(keys.cloud(r), encode(make_cloud(1)))
    stats = wait_stats(s, r, lambda x: x["clouds"] == 1 and x["last_save_s"] > 0)
    assert stats["last_save_s"] > 0 and map_file.exists()
    assert stats["journal"]["records"] == 0, stats["journal"]
    assert map_file.with_suffix(".journal").stat().st_size == stats["journal"]["bytes"]


@pytest.mark.multiprocess
def test_mapper_saves_on_shutdown_and_resumes(zenoh_stack, tmp_path):
    st = zenoh_stack
    map_file = tmp_path / "map.npz"
    args = mapper_args(map_file)
    proc = st.service("mapper", *args)
    st.wait_alive("mapper")
    s, r = st.session, st.robot
    inbox = DeltaInbox(st, keys.map_delta(r))
    for c in [make_cloud(i) for i in range(1, 4)]:
        s.put(keys.cloud(r), encode(c))
        inbox.wait_for(c.seq)
    stats = request(s, keys.query(r, "mapper", "stats"))

    # shutdown saves; a new process resumes from the file with the same map
    n_voxels = stats["voxels_observed"]
    assert st.stop(proc) == 0
    st.procs = [(n, p) for n, p in st.procs if p is not proc]  # wait_alive must not see it
    assert map_file.is_file()
    assert SemanticMap.load(map_file).stats()["voxels_observed"] == n_voxels
    st.service("mapper", *args, "--load", str(map_file))
    st.wait_alive("mapper")
    resumed = wait_stats(s, r, lambda x: True)
    assert resumed["voxels_observed"] == n_voxels
    inbox.sub.undeclare()


def test_snapshot_of_a_fresh_map_is_a_valid_empty_delta(fake_stack):
    """Before any cloud the mapper has no cloud number (-1 in its stats): the snapshot must still
    decode (it carries 0), so a navgraph or ros2 started with the mapper syncs at once."""
    st = fake_stack
    st.service("mapper")
    st.wait_alive("mapper")
    snap = request(st.session, keys.query(st.robot, "mapper", "snapshot"))
    assert isinstance(snap, MapDelta) and len(snap.centres) == 0 and snap.cloud_seq == 0
