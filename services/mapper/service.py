"""The mapper service: zenoh wiring around `SemanticMap` (the algorithm lives in the core modules).

Inputs: `robot/cloud` and/or `robot/scan` (`mapper.inputs`), latest wins: a scan replaced before
it was integrated is dropped as `stale`. Points with NaN/inf or beyond 1000 km are dropped
(event `nonfinite_points`), labels outside the class table become unknown (`unknown_labels`),
confidences outside [0, 1] are clipped (`confidence_range`); a cloud that is not in the world
frame is rejected (`frame`), and so is one whose stamp does not fit its stream's clock (`stamp`,
see `common/plausibility.py`). A rejected cloud leaves the map as it was. Clouds the sender
numbered but that never arrived (a DROP link) are counted as `clouds_lost_upstream`; a jump of more
than `MAX_SEQ_GAP` numbers is a new numbering (`cloud_seq_jump`), not a loss.

Output: one `MapDelta` on `mapper/delta` per integrated cloud (even an empty one, so a lockstep
simulator can wait for its `cloud_seq`), published reliably with congestion control BLOCK.

Queries (msgpack or JSON, see `common/service.py`; answered in `queries.py`):
- `mapper/stats`: map and service figures;
- `mapper/snapshot`: occupied voxels as a `MapDelta`; optional box
  `{"box": [xmin, ymin, zmin, xmax, ymax, zmax]}` (or `?box=...` in the selector);
  `{"observed": true}` (or `?observed=true`): every observed voxel, free ones too (what a
  consumer that replaces its copy of the map needs: the fleet mapper);
- `mapper/save`: save now to `mapper.save_path` (or `{"name": "file.npz"}` beside it); only by
  its exact key (a wildcard selector is refused, `selector`), and within `mapper.save_max_files`
  and `save_max_mb` (`quota`);
- `mapper/point`: `{"points": [[x, y, z], ...]}` -> known, occupied, labels, confidences, values.

Fleet (`mapper.source = "fleet"`, run under the fleet's name: `--robot fleet`): instead of clouds,
the inputs are the map deltas of every member of `fleet.robots` (`smana/<member>/mapper/delta`,
FIFO), merged into one map by `fleet.py::FleetMap`; the outputs, queries and files are the same,
on the fleet's keys, so a navgraph run as `--robot fleet` builds one graph for all. Each member's
stream is followed per producer (`SequenceFollower`): a gap, a new producer (the member's mapper
restarted), a number that goes back or jumps, or the member's mapper token coming back (a robot
that dropped off the link and rejoined) resyncs that member's layer from its own map
(`smana/<member>/mapper/snapshot` with `{"observed": true}`), at most once every
`RESYNC_MIN_PERIOD_S`; deltas the snapshot already covers are dropped as `covered`. A delta at
another resolution is rejected as `resolution`, one that holds no log-odds as `values_kind`.
Merged deltas go out only when a merged voxel changed.

The map is saved every `mapper.autosave_period_s` (when it changed) and on shutdown, atomically;
`mapper.load` (or `--load FILE`) resumes from a file, "auto" from `save_path` when it exists.
Between two autosaves every integration is appended to the map's journal (`map.journal` beside
`map.npz`, `journal.py`) before its delta goes out: the full state of each voxel it changed. With
`mapper.load = "auto"` (what `smana up` sets) a mapper that starts in a run directory replays
that journal over the autosave, so a take-over after `kill -9` loses no voxel a consumer saw;
what was in flight (the cloud being integrated, a record cut short: `takeover.torn_bytes`) is
counted, and the clouds that went unmapped meanwhile as `clouds_lost_upstream` (the cloud numbers
are in the journal too). A hot spare follows the journal while it stands by (`standing_by`), so
it takes over with the last few records left to read. The fleet mapper keeps no journal: the
members' own maps hold everything, and fill it in at start.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import MapDelta, SemanticCloud
from smana.common.plausibility import APPLY, COVERED, SequenceFollower, StampGate
from smana.common.query import QueryError, request
from smana.common.service import Reject, Service, run_service
from smana.services.mapper.delta import Delta
from smana.services.mapper.fleet import FleetMap
from smana.services.mapper.journal import (
    JournalReader,
    JournalWriter,
    journal_path,
)
from smana.services.mapper.queries import MapperQueries
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.mapper.takeover import MapperTakeover, resolve_save_path

MAX_SEQ_GAP = 1000  # a larger jump in a sender's cloud numbers is a new numbering, not a loss
RESYNC_MIN_PERIOD_S = 1.0  # the fleet mapper asks a member for its snapshot at most this often
# a journal this large brings the next autosave forward (and starts a new journal): the disk it
# takes stays bounded, with `autosave_period_s = 0` (only on shutdown) too
JOURNAL_MAX_BYTES = 256 << 20


class MapperService(MapperQueries, MapperTakeover, Service):
    name = "mapper"
    prepare_in_background = True  # prepare() only compiles kernels: live meanwhile
    tick_period_s = 0.5

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        self.table = ClassTable.load(config.general.class_table)
        self.map: SemanticMap | None = None  # built (or loaded) in warm_up
        self.save_path = resolve_save_path(config)
        self.delta_seq = 0
        self.last_cloud_seq = -1
        self.last_stamp_s = 0.0
        g = config.general
        self.gates = {
            name: StampGate(g.stamp_window_s, g.max_time_rate) for name in config.mapper.inputs
        }
        self.input_seq: dict[str, int] = {}
        self.clouds = 0
        self.points_dropped = 0
        self.labels_replaced = 0
        self.times_ms: list[float] = []
        self.dirty = False
        self.last_save_s = 0.0
        self._last_save_bytes = 0
        self._next_save = time.monotonic() + config.mapper.autosave_period_s
        # the fleet mapper: per member, its stream, its counters and a pending resync's reason
        self.fleet = config.mapper.source == "fleet"
        self.members = list(config.fleet.robots) if self.fleet else []
        self.followers = {m: SequenceFollower() for m in self.members}
        self.member_books = {m: {"covered": 0, "resyncs": 0, "last_seq": -1} for m in self.members}
        self._resync_why = dict.fromkeys(self.members, "")
        self._next_resync = dict.fromkeys(self.members, 0.0)
        self._member_down = dict.fromkeys(self.members, False)
        # the journal since the last autosave (none for the fleet mapper, nor without a file)
        use_journal = self.save_path is not None and not self.fleet
        self.journal_path = journal_path(self.save_path) if use_journal else None
        self.journal: JournalWriter | None = None
        self._reader: JournalReader | None = None  # followed while a hot spare stands by
        self.takeover: dict = {}  # what the replay at start found (stats()["takeover"])
        self._generation: int | None = None  # of the journal file replayed last

    def prepare(self) -> None:
        # (Compile or) load the kernels before the token says we are ready.
        self.startup_step = "loading (or compiling) the numba kernels"
        t0 = time.perf_counter()
        warm = SemanticMap.from_config(self.config.mapper, self.table)
        pts = np.array([[1.0, 0.1, 0.1], [0.1, 1.0, 0.2], [20.0, 0.1, 0.1]], np.float32)
        lab = np.array([warm.class_ids[0], 0, 0], np.uint16)
        d = warm.integrate(pts, lab, np.ones(3, np.float32), (0.0, 0.0, 0.0))
        warm.query(pts.astype(np.float64))
        warm.occupied_voxels()
        if self.fleet:
            fm = FleetMap(self.config.mapper, self.members, self.config.fleet, self.table)
            fm.apply(self.members[0], d.centres, d.labels, d.confidences, d.values)
            fm.replace(self.members[0], d.centres, d.labels, d.confidences, d.values)
        self.log.info("kernels ready in %.1f s", time.perf_counter() - t0)

    def setup(self) -> None:
        r = self.robot
        self.delta_pub = self.publisher(keys.map_delta(r), reliable_block=True)
        for m in self.members:
            self.subscribe(keys.map_delta(m), lambda d, m=m: self.on_member_delta(m, d), MapDelta)
            self._declared.append(
                self.session.liveliness().declare_subscriber(
                    keys.alive(m, "mapper"), lambda s, m=m: self._on_member_token(m, s)
                )
            )
            self._resync_why[m] = "start"  # whatever the member mapped before we came
        for name in [] if self.fleet else self.config.mapper.inputs:
            key = keys.cloud(r) if name == "cloud" else keys.scan(r)
            self.subscribe_latest(
                key, lambda c, n=name: self.on_cloud(c, n), SemanticCloud, drop_nonfinite=True
            )
        self.queryable(keys.query(r, "mapper", "stats"), lambda req: self.stats())
        self.queryable(keys.query(r, "mapper", "snapshot"), self.on_snapshot)
        self.queryable(keys.query(r, "mapper", "save"), self.on_save)
        self.queryable(keys.query(r, "mapper", "point"), self.on_point)
        if self.save_path is None:
            self.log.warning("no mapper.save_path and no run dir: the map is not saved")

    # -- the cloud path ----------------------------------------------------------------------

    def on_cloud(self, cloud: SemanticCloud, input_name: str = "cloud") -> None:
        # Everything that can refuse the cloud comes before anything that changes state.
        if cloud.frame_id != "world":
            raise Reject("frame", f"cloud {cloud.seq} is in {cloud.frame_id!r}, not world")
        verdict = self.gates[input_name].check(cloud.stamp_s)
        if not verdict.ok:
            raise Reject(verdict.kind, f"{input_name} {cloud.seq}: {verdict.reason}")
        last = self.input_seq.get(input_name)
        lost = 0 if last is None else cloud.seq - last - 1 - self.stale_before
        if last is not None and cloud.seq > last + MAX_SEQ_GAP:
            # a new numbering (a restarted sender), not clouds lost: a peer's number must not
            # become a count (2**63 twice no longer fits the status message)
            self.note("cloud_seq_jump", f"{input_name} numbering jumped from {last} to {cloud.seq}")
        elif lost > 0:
            self.note(
                "clouds_lost_upstream",
                f"{lost} {input_name}s numbered before "
                f"{cloud.seq} never arrived (dropped on the way)",
                lost,
            )
        self.input_seq[input_name] = cloud.seq
        if cloud.n_dropped_nonfinite:
            n = cloud.n_dropped_nonfinite
            self.points_dropped += n
            self.note("nonfinite_points", f"cloud {cloud.seq}: {n} NaN/inf or far points dropped")
        labels, n_bad = self.table.sanitise(cloud.labels)
        if n_bad:
            self.labels_replaced += n_bad
            self.note(
                "unknown_labels",
                f"cloud {cloud.seq}: {n_bad} labels not in the class "
                f"table {self.table.name}, mapped to unknown",
            )
        conf = cloud.confidences
        if conf.size and (conf.min() < 0 or conf.max() > 1):
            self.note("confidence_range", f"cloud {cloud.seq}: confidences outside [0, 1]")
            conf = np.clip(conf, 0.0, 1.0)
        t0 = time.perf_counter()
        delta = self.map.integrate(cloud.points, labels, conf, cloud.sensor_position)
        self.times_ms.append((time.perf_counter() - t0) * 1e3)
        del self.times_ms[:-100]
        self.clouds += 1
        self.dirty = True
        self.last_cloud_seq = cloud.seq
        self.last_stamp_s = cloud.stamp_s
        self.delta_seq += 1
        if self.journal is not None:  # before the delta goes out: what a consumer saw survives
            try:
                self.journal.append(delta.keys, self._counters())
            except (OSError, ValueError) as exc:  # disk full: the map goes on, a take-over loses
                self.note("journal_failed", f"journal {self.journal_path}: {exc}")
        self.delta_pub.put(self._message(delta, cloud.stamp_s, cloud.seq, self.delta_seq))

    # -- the fleet path ----------------------------------------------------------------------

    def on_member_delta(self, member: str, delta: MapDelta):
        # Checks first: a refused delta changes nothing (and leaves a gap that asks a resync).
        if delta.values_kind != self.map.values_kind:
            raise Reject("values_kind", f"{member} delta {delta.seq}: {delta.values_kind} values")
        if not math.isclose(delta.resolution_m, self.map.resolution_m, rel_tol=1e-6):
            raise Reject(
                "resolution",
                f"{member} delta {delta.seq}: {delta.resolution_m} m voxels, the fleet map's "
                f"are {self.map.resolution_m} m",
            )
        follower, books = self.followers[member], self.member_books[member]
        action, why = follower.check(delta.producer, delta.seq)
        if action == COVERED:
            books["covered"] += 1
            return ("dropped", "covered")
        if action != APPLY:
            raise Reject(action, f"{member} map delta {delta.seq}: {why}; resync asked")
        t0 = time.perf_counter()
        d = self.map.apply(member, delta.centres, delta.labels, delta.confidences, delta.values)
        self.times_ms.append((time.perf_counter() - t0) * 1e3)
        del self.times_ms[:-100]
        follower.advance(delta.producer, delta.seq)
        books["last_seq"] = delta.seq
        if why:  # applied across a gap; the resync fills it
            self.note("delta_gap", f"{member} map deltas: {why}")
        self._publish_merged(d, delta.stamp_s, delta.cloud_seq)

    def _on_member_token(self, member: str, sample) -> None:
        # A zenoh callback: only flags; tick() does the work on the main loop.
        import zenoh

        if sample.kind == zenoh.SampleKind.DELETE:
            self._member_down[member] = True
        elif self._member_down[member] or not self.member_books[member]["resyncs"]:
            # back, or there for the first time since we started (it may have resumed a map)
            self._member_down[member] = False
            self._resync_why[member] = "its mapper is back (restart or link drop)"

    def _fleet_tick(self) -> None:
        now = time.monotonic()
        for m, follower in self.followers.items():
            if follower.want_resync and not self._resync_why[m]:
                self._resync_why[m] = follower.want_resync
            if self._resync_why[m] and now >= self._next_resync[m]:
                self._next_resync[m] = now + RESYNC_MIN_PERIOD_S
                why, self._resync_why[m] = self._resync_why[m], ""
                self.resync_member(m, why)

    def resync_member(self, member: str, reason: str) -> bool:
        """Replace `member`'s layer with its mapper's whole map; publish what changed."""
        try:
            snap = request(
                self.session, keys.query(member, "mapper", "snapshot"), {"observed": True}, 5.0
            )
        except QueryError as exc:
            self.log.info("%s: no snapshot for a resync (%s): %s", member, reason, exc.kind)
            if exc.kind == "warming_up":  # a mapper live before its kernels: ask again
                self._resync_why[member] = self._resync_why[member] or reason
            return False
        if not (
            isinstance(snap, MapDelta)
            and snap.values_kind == self.map.values_kind
            and math.isclose(snap.resolution_m, self.map.resolution_m, rel_tol=1e-6)
        ):
            self.note("bad_snapshot", f"{member}: its snapshot is not a log-odds MapDelta")
            return False
        d = self.map.replace(member, snap.centres, snap.labels, snap.confidences, snap.values)
        self.followers[member].synced(snap.producer, snap.seq)
        books = self.member_books[member]
        books["resyncs"] += 1
        books["last_seq"] = snap.seq
        self.log.info(
            "%s: layer resynced from its snapshot (%s): %d voxels, %d merged voxels changed",
            member,
            reason,
            len(snap.centres),
            len(d),
        )
        self._publish_merged(d, snap.stamp_s, snap.cloud_seq)
        return True

    def _publish_merged(self, d: Delta, stamp_s: float, cloud_seq: int) -> None:
        self.dirty = True
        if not len(d):
            return  # no merged voxel changed: nothing to tell
        self.last_cloud_seq = cloud_seq
        self.last_stamp_s = max(self.last_stamp_s, stamp_s)
        self.delta_seq += 1
        self.delta_pub.put(self._message(d, stamp_s, cloud_seq, self.delta_seq))

    def _message(self, d: Delta, stamp_s: float, cloud_seq: int, seq: int) -> MapDelta:
        return MapDelta(
            stamp_s=stamp_s,
            seq=seq,
            cloud_seq=cloud_seq,
            backend=self.map.backend,
            resolution_m=self.map.resolution_m,
            centres=d.centres,
            labels=d.labels,
            confidences=d.confidences,
            occupied=d.occupied,
            values=d.values,
            producer=self.producer,
            values_kind=self.map.values_kind,
            alt_labels=d.alt_labels,
            alt_confidences=d.alt_confidences,
        )

    # -- saving ------------------------------------------------------------------------------

    def tick(self) -> None:
        if self.fleet:
            self._fleet_tick()
        period = self.config.mapper.autosave_period_s
        full = self.journal is not None and self.journal.bytes > JOURNAL_MAX_BYTES
        if full or (period > 0 and time.monotonic() >= self._next_save):
            self._next_save = time.monotonic() + period
            if self.dirty and self.save_path is not None:
                self.save(self.save_path)
                self._rotate_journal()

    def _rotate_journal(self) -> None:
        """The autosave holds the journal's records now: start a new one."""
        if self.journal is not None:
            try:
                self.journal.rotate(self._counters())
            except OSError as exc:
                self.note("journal_failed", f"journal {self.journal_path}: {exc}")

    def save(self, path: Path) -> dict:
        t0 = time.perf_counter()
        path.parent.mkdir(parents=True, exist_ok=True)
        self.map.save(path)
        self._last_save_bytes = path.stat().st_size
        if path == self.save_path:  # a copy under another name leaves the autosave behind
            self.dirty = False
        self.last_save_s = time.time()
        ms = (time.perf_counter() - t0) * 1e3
        self.log.info("map saved to %s (%.0f ms)", path, ms)
        return {
            "ok": True,
            "path": str(path),
            "bytes": path.stat().st_size,
            "time_ms": ms,
            "voxels_observed": self.map.stats()["voxels_observed"],
        }

    def on_stop(self) -> None:
        if self.map is None:
            return  # stopped while warming up: nothing was mapped, an autosave is still there
        if self.save_path is not None and (self.dirty or not self.save_path.exists()):
            self.save(self.save_path)
            self._rotate_journal()
        if self.journal is not None:
            self.journal.close()


def main(config: SmanaConfig) -> int:
    """Run the mapper until SIGINT/SIGTERM."""
    return run_service(MapperService, config)
