"""The replay's core, without zenoh: scans read ahead on a thread, and the pacing rules.

`ScanFeed` reads, filters and encodes scans on a background thread while the mapper integrates the
previous one, so reading never adds to the lockstep cycle. `Pacer` decides when the next scan
goes out and keeps the books:

- lockstep: a scan goes out once the mapper's MapDelta for the previous one (`cloud_seq` = its
  seq) has arrived; none is lost. A scan unacknowledged after `ack_timeout_s` is sent again
  (the mapper may have restarted), at most `max_resends` times, then counted lost
  (`unacknowledged`): a failure of the run.
- realtime: scan k goes out at start + (stamp_k - stamp_0) / rate_factor whether or not the
  mapper has finished; with `prime`, the clock starts once the first scan's MapDelta is back.
  A scan published more than one period after its due time is `late_published` (the replay
  itself could not keep up); one whose MapDelta arrives more than one period after publication
  is `late_integrated`. One the mapper never integrated is lost, by design rather than by
  failure: `overtaken` when a newer scan was integrated first (the mapper's latest-wins input
  replaced it, its books count it `stale`; or the DROP link lost it on the way, which the
  replay cannot tell apart), `unacknowledged` when no MapDelta came within `ack_timeout_s`.

`lost` = `overtaken` + `unacknowledged`, in both modes. Scans are known by the seq their
cloud carries (`FeedItem.seq`), set when the cloud is made: a scan with nothing left to publish
(its pose still goes out) takes no number, so the MapDelta's `cloud_seq` always names the scan.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from smana.common.classes import ClassTable
from smana.common.geometric import GeometricLabeller
from smana.common.messages import Pose, SemanticCloud, encode

from .prepare import PreparedCloud, prepare_scan
from .readers.base import DatasetReader, Scan


@dataclass
class FeedItem:
    """One scan ready to go: encoded messages, or why it could not be read."""

    index: int
    name: str
    stamp_s: float
    cloud: bytes | None = None  # None: nothing left after filtering (pose still published)
    pose: bytes | None = None
    prepared: PreparedCloud | None = None
    error: str = ""
    seq: int = 0  # the seq the cloud carries (1, 2, ... over the clouds), 0 without a cloud
    pose_row: tuple[float, float, float, float, float] | None = None  # t, x, y, z, yaw


END = object()


class ScanFeed:
    """Read and prepare scans [start, start + count) on a thread, a few ahead of the publisher."""

    def __init__(
        self,
        reader: DatasetReader,
        table: ClassTable,
        max_range_m: float,
        min_range_m: float,
        source: str,
        start: int = 0,
        count: int = 0,
        ahead: int = 3,
        keep_prepared: bool = False,
        labeller: GeometricLabeller | None = None,
    ):
        n = len(reader)
        if start >= n:
            raise ValueError(f"start scan {start} is past the end ({n} scans)")
        self.indices = range(start, n if count <= 0 else min(n, start + count))
        self.reader, self.table, self.source = reader, table, source
        self.max_range_m, self.min_range_m = max_range_m, min_range_m
        self.keep_prepared = keep_prepared
        self.labeller = labeller  # labels scans that come without (prepare_scan)
        self._queue: queue.Queue = queue.Queue(maxsize=ahead)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay-feed", daemon=True)

    def __len__(self) -> int:
        return len(self.indices)

    def start(self) -> ScanFeed:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        while True:  # unblock a producer waiting on a full queue
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        self._thread.join(timeout=5)

    def get(self, timeout: float = 0.0):
        """The next FeedItem, END after the last one, or None if none is ready yet."""
        try:
            return self._queue.get(timeout=timeout) if timeout > 0 else self._queue.get_nowait()
        except queue.Empty:
            return None

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _iter_scans(self) -> Iterable[tuple[int, Scan | Exception]]:
        if not self.reader.sequential:
            for i in self.indices:
                try:
                    yield i, self.reader.scan(i)
                except Exception as exc:  # noqa: BLE001 - reported as a skipped scan
                    yield i, exc
            return
        # Streams (bags) are read forward; a failure ends the generator, so start again and
        # fast-forward past what was already read.
        done = self.indices.start
        while done < self.indices.stop:
            try:
                for i in range(done, self.indices.stop):
                    scan = self.reader.scan(i)
                    done = i + 1
                    yield i, scan
            except Exception as exc:  # noqa: BLE001 - reported as a skipped scan
                yield done, exc
                done += 1

    def _run(self) -> None:
        poses = clouds = 0  # each stream numbered without gaps: a gap means a loss on the way
        for i, scan in self._iter_scans():
            if self._stop.is_set():
                return
            if isinstance(scan, Exception):
                item = FeedItem(i, f"scan {i}", float("nan"), error=f"{scan}")
            else:
                try:
                    item = self._prepare(scan, poses + 1, clouds + 1)
                except ValueError as exc:
                    item = FeedItem(i, scan.name, scan.stamp_s, error=str(exc))
                else:
                    poses += 1
                    clouds += item.cloud is not None
            if not self._put(item):
                return
        self._put(END)

    def _prepare(self, scan: Scan, pose_seq: int, cloud_seq: int) -> FeedItem:
        pc = prepare_scan(scan, self.table, self.max_range_m, self.min_range_m, self.labeller)
        pose = Pose(
            stamp_s=scan.stamp_s,
            seq=pose_seq,
            position=pc.sensor_position,
            orientation_xyzw=pc.sensor_orientation_xyzw,
        )
        item = FeedItem(scan.index, scan.name, scan.stamp_s, pose=encode(pose))
        x, y, z = (float(v) for v in pose.position)
        item.pose_row = (float(scan.stamp_s), x, y, z, float(pose.yaw))
        if pc.n_out:
            item.seq = cloud_seq
            cloud = SemanticCloud(
                stamp_s=scan.stamp_s,
                seq=cloud_seq,
                points=pc.points,
                labels=pc.labels.astype(np.uint16),
                confidences=pc.confidences,
                sensor_position=pc.sensor_position,
                sensor_orientation_xyzw=pc.sensor_orientation_xyzw,
                source=self.source,
            )
            item.cloud = encode(cloud)
        # Counts only (the arrays are in the encoded cloud) unless a caller wants them.
        item.prepared = pc if self.keep_prepared else _counts_only(pc)
        return item


def _counts_only(pc: PreparedCloud) -> PreparedCloud:
    empty = np.zeros(0, np.float32)
    return PreparedCloud(
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.uint16),
        empty,
        pc.sensor_position,
        pc.sensor_orientation_xyzw,
        pc.n_in,
        pc.n_nonfinite,
        pc.n_out_of_range,
        pc.n_ignored,
        pc.n_unclaimed,
        pc.n_out,
    )


@dataclass
class InFlight:
    seq: int
    index: int
    sent_at: float
    payload: bytes
    resends: int = 0


@dataclass
class Pacer:
    """Publication timing and acknowledgement books (see the module docstring)."""

    mode: str  # "lockstep" | "realtime"
    rate_factor: float = 1.0
    ack_timeout_s: float = 30.0
    max_resends: int = 3
    clock: Callable[[], float] = time.monotonic
    t0_wall: float | None = None
    t0_stamp: float | None = None
    in_flight: dict[int, InFlight] = field(default_factory=dict)
    published: int = 0
    acked: int = 0
    lost: int = 0  # never integrated: overtaken + unacknowledged
    overtaken: int = 0  # realtime: a newer scan was integrated first
    unacknowledged: int = 0  # no MapDelta within ack_timeout_s (after max_resends in lockstep)
    resends: int = 0
    late_published: int = 0
    late_integrated: int = 0
    latencies_s: list[float] = field(default_factory=list)
    latency_by_seq: dict[int, float] = field(default_factory=dict)
    period_s: float = 0.1  # nominal scan period at the replay rate (set from the dataset)
    # realtime: the first scan primes the stack (kernels load on a process's first integration)
    # and the recorded clock starts when its MapDelta is back, as on a robot whose stack was up
    # before it drove off. Needs a mapper to answer; the service turns it on when one is alive.
    prime: bool = False
    priming_seq: int | None = None
    _priming_stamp: float = 0.0

    def __post_init__(self):
        if self.mode not in ("lockstep", "realtime"):
            raise ValueError(f"mode must be lockstep or realtime, got {self.mode!r}")
        if not self.rate_factor > 0:
            raise ValueError("rate_factor must be > 0")

    def due_at(self, stamp_s: float) -> float:
        """Wall time (clock) at which a scan stamped `stamp_s` should go out (realtime)."""
        if self.t0_wall is None:
            return self.clock()
        return self.t0_wall + (stamp_s - self.t0_stamp) / self.rate_factor

    def ready(self, stamp_s: float) -> bool:
        """May the scan stamped `stamp_s` go out now?"""
        if self.mode == "lockstep":
            return not self.in_flight
        if self.priming_seq is not None:
            return False
        return self.t0_wall is None or self.clock() >= self.due_at(stamp_s)

    def start_clock(self, stamp_s: float) -> None:
        """The first scan out fixes the mapping from recorded stamps to wall time."""
        if self.t0_wall is None:
            self.t0_wall, self.t0_stamp = self.clock(), stamp_s

    def on_published(
        self, seq: int, index: int, stamp_s: float, payload: bytes, sent_at: float | None = None
    ) -> None:
        """A scan went out. `sent_at`: the clock just before the put (the mapper may receive and
        start integrating while a large put is still returning), else now."""
        now = self.clock() if sent_at is None else sent_at
        if self.t0_wall is None and self.mode == "realtime" and self.prime and not self.published:
            self.priming_seq, self._priming_stamp = seq, stamp_s
        elif self.t0_wall is None:
            self.start_clock(stamp_s)
        elif self.mode == "realtime" and now - self.due_at(stamp_s) > self.period_s:
            self.late_published += 1
        self.published += 1
        self.in_flight[seq] = InFlight(seq, index, now, payload)

    def on_ack(self, cloud_seq: int) -> float | None:
        """A MapDelta for `cloud_seq` arrived: the scan's integration latency, or None if the
        seq is not waiting (a second delta chunk, or a scan already given up)."""
        f = self.in_flight.pop(cloud_seq, None)
        if f is None:
            return None
        # The mapper integrates in order: anything older still waiting was dropped by its
        # latest-wins input (realtime) and will never be acknowledged.
        for seq in [s for s in self.in_flight if s < cloud_seq]:
            del self.in_flight[seq]
            self.lost += 1
            self.overtaken += 1
        latency = self.clock() - f.sent_at
        self.acked += 1
        self.latencies_s.append(latency)
        self.latency_by_seq[cloud_seq] = latency
        if cloud_seq == self.priming_seq:
            self._end_priming()
        elif self.mode == "realtime" and latency > self.period_s:
            self.late_integrated += 1
        return latency

    def _end_priming(self) -> None:
        self.priming_seq = None
        self.start_clock(self._priming_stamp)

    def overdue(self) -> list[InFlight]:
        """Lockstep: scans to send again (their timers restart); gives up after max_resends."""
        now = self.clock()
        out = []
        for seq, f in list(self.in_flight.items()):
            if now - f.sent_at < self.ack_timeout_s:
                continue
            if self.mode == "realtime" or f.resends >= self.max_resends:
                del self.in_flight[seq]
                self.lost += 1
                self.unacknowledged += 1
                if seq == self.priming_seq:
                    self._end_priming()
            else:
                f.resends += 1
                f.sent_at = now
                self.resends += 1
                out.append(f)
        return out

    def give_up_waiting(self) -> int:
        """End of the replay: whatever is still unacknowledged is lost."""
        n = len(self.in_flight)
        self.lost += n
        self.unacknowledged += n
        self.in_flight.clear()
        return n

    def latency_summary(self) -> dict:
        lat = np.asarray(self.latencies_s) * 1000.0
        if lat.size == 0:
            return {"mean_ms": None, "p95_ms": None, "max_ms": None}
        return {
            "mean_ms": float(lat.mean()),
            "p95_ms": float(np.percentile(lat, 95)),
            "max_ms": float(lat.max()),
        }
