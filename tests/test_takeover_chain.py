"""Ten take-overs of the mapper in a row, at the worst moments, lose no acknowledged voxel.

Mapper processes on an isolated loopback router (tests/conftest.py), each started as a hot spare
the way `smana up` starts one (`SMANA_STANDBY_FD`, a line on stdin to take over), all resuming
the same run (`mapper.load = auto`, an autosave every second). The test feeds clouds itself, one
at a time; a cloud is acknowledged when its MapDelta arrives. Kills (SIGKILL) come while idle,
with a cloud in flight, while an autosave is being written, right after a take-over, during a
take-over's replay and before a fresh spare followed the journal; once a clean stop (SIGINT).
After each, the new mapper's map (every observed voxel of its snapshot) equals a reference map
that integrated the acknowledged clouds in-process, plus the in-flight cloud when the journal held
it: nothing else may differ. At the end a clean stop writes a file equal to the reference in every
column. No simulator: synthetic clouds over zenoh."""

from __future__ import annotations

import signal

import numpy as np
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import encode
from smana.common.query import request
from smana.services.mapper.semantic_map import SemanticMap
from tests.conftest import wait_for
from tests.support.hot_spare import HotSpare, SpareChain
from tests.test_mapper_journal import assert_same_voxels
from tests.test_mapper_service import DeltaInbox
from tests.test_takeover import make_cloud

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

SETS = ["mapper.resolution_m=0.2", "mapper.load=auto", "mapper.autosave_period_s=1.0"]
MOMENTS = [
    "idle",
    "in_flight",
    "during_autosave",
    "right_after_takeover",
    "during_replay",
    "fresh_spare",
    "clean_stop",
    "idle",
    "in_flight",
    "during_autosave",
]


def Spare(stack, map_file) -> HotSpare:  # noqa: N802 - it stands for the class it makes
    """A mapper process standing by (prepared, following the journal) until `go()`."""
    return HotSpare(
        stack, "mapper", [*(a for s in SETS for a in ("--set", s)), "--save", str(map_file)]
    )


class Chain(SpareChain):
    def __init__(self, stack, tmp):
        self.stack, self.map_file = stack, tmp / "map.npz"
        cfg = SmanaConfig.load(overrides=SETS[:1])
        self.ref = SemanticMap.from_config(cfg.mapper, ClassTable.load(cfg.general.class_table))
        self.pub = stack.session.declare_publisher(keys.cloud(stack.robot))
        self.inbox = None
        self.seq = 0
        self.acked = 0  # clouds acknowledged (their delta came), in the reference
        self.in_flight_lost = 0
        super().__init__(lambda: Spare(stack, self.map_file))

    def wait_running(self) -> None:
        super().wait_running()
        if self.inbox is None:
            self.inbox = DeltaInbox(self.stack, keys.map_delta(self.stack.robot))

    def stats(self) -> dict:
        return request(self.stack.session, keys.query(self.stack.robot, "mapper", "stats"))

    def put(self, cloud) -> None:
        self.pub.put(encode(cloud))

    def send(self, n: int) -> None:
        """`n` clouds, each acknowledged (its delta back) before the next."""
        for _ in range(n):
            self.seq += 1
            cloud = make_cloud(self.seq, 600)
            want = self.stats()["clouds"] + 1

            def acked(c=cloud, w=want) -> bool:
                # a put made before the mapper's subscription reached the router is lost: again
                if self.stats()["clouds"] < w:
                    self.put(c)
                return self._delta(c.seq, 2.0)

            assert wait_for(acked, 60, 0.01), self.active.log()
            self.ref.integrate(cloud.points, cloud.labels, cloud.confidences, cloud.sensor_position)
            self.acked += 1

    def _delta(self, seq: int, timeout_s: float) -> bool:
        try:
            self.inbox.wait_for(seq, timeout_s)
        except TimeoutError:
            return False
        return True

    def check(self, moment: str, in_flight=None) -> None:
        """The new mapper's map equals the reference (and the in-flight cloud, if journaled)."""
        s = self.stats()
        if in_flight is not None and s["clouds"] == self.acked + 1:
            c = in_flight  # integrated and journaled before the kill: it is part of the map
            self.ref.integrate(c.points, c.labels, c.confidences, c.sensor_position)
            self.acked += 1
        elif in_flight is not None:
            self.in_flight_lost += 1
        assert s["clouds"] == self.acked, (moment, s, self.acked)
        snap = request(
            self.stack.session,
            keys.query(self.stack.robot, "mapper", "snapshot"),
            {"observed": True},
        )
        want = self.ref.observed_voxels()
        assert len(snap.centres) == len(want.centres), (moment, len(snap.centres), len(want))
        a, b = np.lexsort(snap.centres.T), np.lexsort(want.centres.T)
        for f in ("centres", "labels", "confidences", "occupied", "values"):
            np.testing.assert_array_equal(
                getattr(snap, f)[a], getattr(want, f)[b], err_msg=f"{moment}: {f}"
            )


def test_ten_takeovers_in_a_row_lose_no_acknowledged_voxel(zenoh_stack, tmp_path):
    chain = Chain(zenoh_stack, tmp_path)
    chain.spare()
    chain.take_over()
    chain.wait_running()
    chain.spare()  # the next spare prepares while the first maps
    hits = {"autosave": 0}
    for i, moment in enumerate(MOMENTS):
        chain.send(2)
        in_flight = None
        old = chain.active
        if moment == "in_flight":
            chain.seq += 1
            in_flight = make_cloud(chain.seq, 600)
            chain.put(in_flight)
            old.kill()
        elif moment == "during_autosave":
            tmp = chain.map_file.with_name("map.npz.tmp")
            # the autosave comes within a second of the last cloud: kill while its file is open
            if wait_for(tmp.exists, 5, 0.0005):
                hits["autosave"] += 1
            old.kill()
        elif moment == "clean_stop":
            assert old.kill(signal.SIGINT) == 0, old.log()
            disk = SemanticMap.load(chain.map_file)  # a clean stop: all of it in the file
            assert_same_voxels(chain.ref, disk)
        else:
            old.kill()
        if moment == "during_replay":
            doomed = chain.take_over()
            doomed.kill()  # at once: while it loads the autosave and replays the journal
        if moment == "fresh_spare":  # told to take over before it followed the journal
            chain.spares.insert(0, Spare(zenoh_stack, chain.map_file))
        chain.take_over(prepared=moment != "fresh_spare")
        chain.wait_running()
        chain.check(moment, in_flight)
        if moment == "right_after_takeover":  # once more, before it mapped anything
            chain.spare()
            chain.active.kill()
            chain.take_over()
            chain.wait_running()
            chain.check("after the second take-over")
        while len(chain.spares) < (2 if MOMENTS[(i + 1) % len(MOMENTS)] == "during_replay" else 1):
            chain.spare()
        print(f"take-over {i + 1} ({moment}): {chain.acked} clouds, map equal")
    chain.send(1)
    assert chain.active.kill(signal.SIGINT) == 0
    assert_same_voxels(chain.ref, SemanticMap.load(chain.map_file))
    print(f"in-flight clouds lost: {chain.in_flight_lost}; kills during an autosave: {hits}")
    assert chain.in_flight_lost <= MOMENTS.count("in_flight")
    for s in chain.spares:
        s.kill()
