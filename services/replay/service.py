"""The replay service: a recorded dataset on the robot's keys, in place of the simulator.

Per scan it publishes `robot/clock`, `robot/pose` and the filtered, labelled, world-frame cloud on
`robot/scan` (LiDAR datasets) or `robot/cloud` (camera), then paces the next one as `player.Pacer`
says: lockstep (after the mapper's MapDelta for this scan) or realtime (at the recorded rate x N).
In lockstep nothing may be lost, so scans and poses go out on blocking (reliable) publishers.
Before the first scan it waits for the services in `replay.wait_for` to be alive, so that nothing
published is lost to a subscriber that is not there yet: up to `replay.wait_timeout_s` for a
service that shows no sign of life, up to `deploy.startup_timeout_s` for one that shows its
`starting` token (compiling its kernels on a cold cache takes minutes on a busy machine). When the
sequence is done it writes into the run directory, if there is one, `replay.json` (counts,
latencies, the distance its poses cover) and `replay_trajectory.csv` (every pose it published:
what a run's report measures the distance on, whoever else heard them), and exits.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from smana.common import keys, progress
from smana.common.classes import ClassTable
from smana.common.config import ReplayConfig, SmanaConfig
from smana.common.geometric import TABLE as GEOMETRIC_TABLE
from smana.common.geometric import GeometricLabeller
from smana.common.messages import GraphPatch, MapDelta
from smana.common.service import Service, kernels_loaded

from .player import END, FeedItem, Pacer, ScanFeed
from .readers import DatasetReader, detect_format, open_dataset
from .readers.base import NO_LABELS
from .readers.rosbag import fixed_pose_matrix

TRAJECTORY_NAME = "replay_trajectory.csv"  # every pose the replay published, in the run dir


def open_reader(rc: ReplayConfig) -> DatasetReader:
    """The dataset named by the [replay] section, with only the options its format takes."""
    if not rc.dataset:
        raise ValueError("no dataset: give `smana replay DATASET` or set replay.dataset")
    fmt = rc.format or detect_format(rc.dataset)
    fixed = None
    if rc.fixed_pose:
        if len(rc.fixed_pose) == 16:
            fixed = np.asarray(rc.fixed_pose, float).reshape(4, 4)
        elif len(rc.fixed_pose) == 4:
            fixed = fixed_pose_matrix(rc.fixed_pose)
        else:
            raise ValueError("replay.fixed_pose must be x, y, z, yaw or 16 numbers (4x4)")
    return open_dataset(
        rc.dataset,
        fmt,
        sequence=rc.sequence or None,
        label_field=rc.label_field if rc.label_field != "label" else None,
        cloud_topic=rc.cloud_topic or None,
        odom_topic=rc.odom_topic or None,
        fixed_pose=fixed,
    )


def table_name(rc: ReplayConfig, reader: DatasetReader) -> str:
    """The class table of the replay: the one named, or the dataset's own (`geometric` for scans
    read without labels, which no other table fits: ValueError)."""
    name = rc.class_table or reader.class_table
    if not reader.labelled and name != GEOMETRIC_TABLE:
        raise ValueError(
            f"--label-field {NO_LABELS} labels points with the {GEOMETRIC_TABLE!r} class table, "
            f"not {name!r}: leave out --table (replay.class_table)"
        )
    return name


def topic_of(rc: ReplayConfig, reader: DatasetReader) -> str:
    """ "scan" or "cloud": where the clouds go."""
    if rc.topic != "auto":
        return rc.topic
    return "scan" if reader.sensor == "lidar" else "cloud"


class Progress:
    """Scans handled of the total on stderr: a bar with an ETA on a terminal (common/progress.py),
    a log line every 10 s otherwise (the line logs and scripts read)."""

    def __init__(self, total: int, stream=None):
        self.total = total
        self.stream = stream or sys.stderr
        on = progress.enabled(self.stream) and self.stream is sys.stderr
        self.drawn = on  # (tqdm also disables a bar it has closed)
        self.bar = progress.bar(total, "replay", unit="scan", enable=on)
        self.t0 = time.monotonic()
        self._last = 0.0

    def update(self, done: int, extra: str = "", force: bool = False) -> None:
        if self.drawn:
            if self.bar.disable:  # closed: the last update was forced
                return
            if done != self.bar.n or force:
                self.bar.set_postfix_str(extra, refresh=False)
                self.bar.update(done - self.bar.n)
            if force:
                self.bar.close()
            return
        now = time.monotonic()
        if not force and now - self._last < 10.0:
            return
        self._last = now
        frac = done / self.total if self.total else 1.0
        rate = done / max(now - self.t0, 1e-9)
        self.stream.write(
            f"replay: {done}/{self.total} scans {100 * frac:5.1f}% {rate:5.1f} scans/s {extra}\n"
        )
        self.stream.flush()


class ReplayService(Service):
    name = "replay"
    tick_period_s = 0.005  # realtime pacing resolution

    def __init__(self, config: SmanaConfig, reader: DatasetReader | None = None):
        super().__init__(config)
        rc = self.rc = config.replay
        self.reader = reader if reader is not None else open_reader(rc)
        self.reader.report_skipped()
        self.table = ClassTable.load(table_name(rc, self.reader))
        self.topic = topic_of(rc, self.reader)
        # scans without labels are labelled by geometry, against this robot's limits
        labeller = None if self.reader.labelled else GeometricLabeller.from_config(config)
        self.feed = ScanFeed(
            self.reader,
            self.table,
            rc.max_range_m,
            rc.min_range_m,
            "lidar" if self.topic == "scan" else "camera",
            rc.start,
            rc.count,
            labeller=labeller,
        )
        period = 1.0 / (self.reader.rate_hz * rc.rate_factor)
        self.pacer = Pacer(rc.mode, rc.rate_factor, rc.ack_timeout_s, period_s=period)
        self.phase = "waiting"  # -> running -> done
        self.exit_code = 0
        self._alive: set[str] = set()
        self._warming: set[str] = set()  # live, their status says their kernels compile
        self._starting: set[str] = set()
        self._last_sign: dict[str, float] = {}  # service -> when it last showed a token
        self._next: FeedItem | object | None = None
        self._feed_done = False
        self.done = 0  # scans handled (published or skipped)
        self.empty = 0
        self.read_errors: list[tuple[str, str]] = []
        self.points_in = self.points_out = 0
        self.points_range = self.points_ignored = self.points_nonfinite = 0
        self.scan_log: list[tuple[int, int, str, float, int]] = []  # seq, index, name, stamp, n
        self.pose_log: list[tuple[float, ...]] = []  # t, x, y, z, yaw of every pose published
        self._t_wait = time.monotonic()
        self._t_run = None
        self.progress = Progress(len(self.feed))
        if self.table.name != config.general.class_table:
            self.log.warning(
                "replaying with class table %r but general.class_table is %r: run the mapper "
                "and navgraph with --set general.class_table=%s so labels mean the same",
                self.table.name,
                config.general.class_table,
                self.table.name,
            )
        if self.topic not in config.mapper.inputs:
            self.log.warning(
                "clouds go to robot/%s: the mapper needs --set mapper.inputs='[\"%s\"]'",
                self.topic,
                self.topic,
            )

    # -- wiring ----------------------------------------------------------------------------------

    def setup(self) -> None:
        r = self.robot
        lockstep = self.rc.mode == "lockstep"
        cloud_key = keys.scan(r) if self.topic == "scan" else keys.cloud(r)
        # In lockstep no scan may be lost, so the link blocks instead of dropping; nor may a
        # pose (a recorder measures the run on them). In realtime a large scan put on a DROP
        # link is often lost on the way, which the first and last must not be: the clock starts
        # at the first one's MapDelta and the replay ends at the last one's, so a lost one
        # stalled the replay for ack_timeout_s. They go out on a blocking publisher.
        self.cloud_pub = self.publisher(cloud_key, reliable_block=lockstep)
        self.cloud_pub_sure = (
            self.cloud_pub if lockstep else self.publisher(cloud_key, reliable_block=True)
        )
        self.pose_pub = self.publisher(keys.pose(r), reliable_block=lockstep)
        self.clock_pub = self.publisher(keys.clock(r))
        self.subscribe(keys.map_delta(r), self.on_delta, MapDelta)
        # Who is alive (or starting): for wait_for, and to know whether a MapDelta can still come
        # at the end.
        for key in (keys.alive_any(r), keys.starting_any(r)):
            self._declared.append(
                self.session.liveliness().declare_subscriber(key, self._on_token, history=True)
            )
        # A service is live before its kernels are loaded: wait_for waits for them too.
        self._declared.append(self.session.declare_subscriber(keys.status_any(r), self._on_status))
        self.feed.start()
        self.log.info(
            "replaying %d scans of %s (%s, %.1f Hz) on %s, %s%s",
            len(self.feed),
            self.reader.path,
            self.reader.format,
            self.reader.rate_hz,
            cloud_key,
            self.rc.mode,
            f" x{self.rc.rate_factor:g}" if not lockstep else "",
        )

    def _on_token(self, sample) -> None:
        # zenoh thread: only record and wake the main loop
        import zenoh

        *_, kind, name = str(sample.key_expr).split("/")
        where = self._alive if kind == "alive" else self._starting
        if sample.kind == zenoh.SampleKind.PUT:
            where.add(name)
        else:
            where.discard(name)
        self._last_sign[name] = time.monotonic()
        self._wake.set()

    def _on_status(self, sample) -> None:
        # zenoh thread: only record and wake the main loop
        if (got := kernels_loaded(sample)) is None:
            return
        name, loaded = got
        (self._warming.discard if loaded else self._warming.add)(name)
        self._wake.set()

    def _not_ready(self) -> tuple[list[str], str]:
        """The services of wait_for not alive yet, and why the replay gives up on them ("" while
        it still waits): one that showed no token for wait_timeout_s, or was still starting
        after deploy.startup_timeout_s."""
        missing = [s for s in self.rc.wait_for if s not in self._alive or s in self._warming]
        now = time.monotonic()
        waited = now - self._t_wait
        silent = [
            s
            for s in missing
            if s not in self._starting
            and s not in self._alive  # (alive, its kernels loading: still starting)
            and now - max(self._t_wait, self._last_sign.get(s, 0.0)) > self.rc.wait_timeout_s
        ]
        if silent:
            return missing, (
                f"{', '.join(silent)} not alive after {self.rc.wait_timeout_s:.0f} "
                "s: nothing to replay into"
            )
        if missing and waited > max(self.rc.wait_timeout_s, self.config.deploy.startup_timeout_s):
            return missing, (
                f"{', '.join(missing)} still starting after {waited:.0f} s "
                "(deploy.startup_timeout_s): nothing to replay into"
            )
        return missing, ""

    def on_delta(self, delta: MapDelta) -> None:
        if self.pacer.on_ack(int(delta.cloud_seq)) is not None and self.rc.mode == "lockstep":
            self._advance()

    # -- the main loop -----------------------------------------------------------------------------

    def tick(self) -> None:
        if self.phase == "waiting":
            missing, give_up = self._not_ready()
            if not missing:
                self.phase = "running"
                self._t_run = time.monotonic()
                self.pacer.prime = "mapper" in self._alive
            elif give_up:
                self.log.error("%s", give_up)
                self.exit_code = 1
                self.phase = "done"
                self.stop()
                return
            else:
                return
        if self.phase != "running":
            return
        for f in self.pacer.overdue():
            self.log.warning(
                "no MapDelta for scan seq %d after %.0f s: sending it again",
                f.seq,
                self.rc.ack_timeout_s,
            )
            self.cloud_pub.put(f.payload)
        self._advance()
        self._maybe_finish()
        self.progress.update(self.done, self._progress_extra())

    def _advance(self) -> None:
        """Publish every scan that may go out now."""
        while self.phase == "running":
            if self._next is None:
                self._next = self.feed.get()
                if self._next is None:
                    return  # the reader is behind; the next tick tries again
            if self._next is END:
                self._feed_done = True
                return
            item: FeedItem = self._next
            if item.error:
                self.read_errors.append((item.name, item.error))
                self.note("dataset", f"{item.name}: {item.error}")
                self.done += 1
                self._next = None
                continue
            if not self.pacer.ready(item.stamp_s):
                return
            self._publish(item)
            self._next = None
            if self.rc.mode == "lockstep" and item.cloud is not None:
                return  # wait for this scan's MapDelta

    def _publish(self, item: FeedItem) -> None:
        pc = item.prepared
        self.clock_pub.put({"sim_time_s": item.stamp_s, "real_time_factor": self.rc.rate_factor})
        self.pose_pub.put(item.pose)
        self.pose_log.append(item.pose_row)
        if item.cloud is not None:
            seq = item.seq  # what the mapper's MapDelta will name it by (cloud_seq)
            sent_at = self.pacer.clock()
            ends = not self.pacer.published or item.index == self.feed.indices[-1]
            (self.cloud_pub_sure if ends else self.cloud_pub).put(item.cloud)
            self.pacer.on_published(seq, item.index, item.stamp_s, item.cloud, sent_at)
            self.scan_log.append((seq, item.index, item.name, item.stamp_s, pc.n_out))
        else:
            self.pacer.start_clock(item.stamp_s)
            self.empty += 1
        self.done += 1
        self.points_in += pc.n_in
        self.points_out += pc.n_out
        self.points_range += pc.n_out_of_range
        self.points_ignored += pc.n_ignored
        self.points_nonfinite += pc.n_nonfinite

    def _maybe_finish(self) -> None:
        if not self._feed_done or self.phase != "running":
            return
        mapper_alive = "mapper" in self._alive
        if self.pacer.in_flight and mapper_alive:
            return  # wait for the last MapDeltas (overdue() bounds the wait)
        if mapper_alive or self.pacer.acked:
            self.pacer.give_up_waiting()
        else:  # no mapper at all (publishing for a viewer, say): nothing was lost
            self.pacer.in_flight.clear()
        self.phase = "done"
        self.progress.update(self.done, self._progress_extra(), force=True)
        summary = self.summary()
        self._write_summary(summary)
        self._write_trajectory()
        self._save_graph()
        self.log.info("replay done: %s", summary_line(summary))
        if self.rc.mode == "lockstep" and summary["lost"]:
            self.exit_code = 1
        self.stop()

    # -- reporting --------------------------------------------------------------------------------

    def _progress_extra(self) -> str:
        p = self.pacer
        lat = p.latency_summary()["mean_ms"]
        parts = [f"lat {lat:.0f} ms" if lat is not None else "lat -"]
        if p.overtaken:
            parts.append(f"overtaken {p.overtaken}")
        if p.unacknowledged:
            parts.append(
                f"lost {p.unacknowledged}"
                if self.rc.mode == "lockstep"
                else f"unacknowledged {p.unacknowledged}"
            )
        if p.late_published or p.late_integrated:
            parts.append(f"late {p.late_published}+{p.late_integrated}")
        return " ".join(parts)

    def summary(self) -> dict:
        p = self.pacer
        wall = time.monotonic() - (self._t_run or time.monotonic())
        return {
            "dataset": str(self.reader.path),
            "format": self.reader.format,
            "class_table": self.table.name,
            "topic": self.topic,
            "mode": self.rc.mode,
            "rate_factor": self.rc.rate_factor,
            "recorded_rate_hz": self.reader.rate_hz,
            "scans": len(self.feed),
            "published": p.published,
            "empty": self.empty,
            "skipped_by_reader": [[s.name, s.reason] for s in self.reader.skipped],
            "read_errors": [list(e) for e in self.read_errors],
            "acknowledged": p.acked,
            "lost": p.lost,
            "overtaken": p.overtaken,
            "unacknowledged": p.unacknowledged,
            "resends": p.resends,
            "late_published": p.late_published,
            "late_integrated": p.late_integrated,
            "latency": p.latency_summary(),
            "points_in": self.points_in,
            "points_published": self.points_out,
            "points_out_of_range": self.points_range,
            "points_ignored_class": self.points_ignored,
            "points_nonfinite": self.points_nonfinite,
            "wall_s": wall,
            "scans_per_s": p.published / wall if wall > 0 else None,
            "poses_published": len(self.pose_log),
            "distance_m": path_length_m(self.pose_log),
            "trajectory": TRAJECTORY_NAME,
            # per published scan: seq, dataset index, name, stamp, points, integration latency
            "per_scan": [
                [seq, i, name, stamp, n, _ms(p.latency_by_seq.get(seq))]
                for seq, i, name, stamp, n in self.scan_log
            ],
        }

    def _write_summary(self, summary: dict) -> None:
        run_dir = self.config.general.run_dir
        if run_dir:
            path = Path(run_dir) / "replay.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(summary, indent=1))
            self.log.info("summary written to %s", path)

    def _write_trajectory(self) -> None:
        run_dir = self.config.general.run_dir
        if run_dir:
            rows = np.array(self.pose_log, float).reshape(-1, 5)
            np.savetxt(
                Path(run_dir) / TRAJECTORY_NAME,
                rows,
                delimiter=",",
                fmt="%.4f",
                header="t_s,x_m,y_m,z_m,yaw_rad",
                comments="",
            )

    def _save_graph(self) -> None:
        """The navigation graph as it stands after the last scan, as `<run_dir>/graph.npz` (the
        explorer's format: dense labels, heights, flags over the allocated box)."""
        run_dir = self.config.general.run_dir
        if not run_dir or "navgraph" not in self._alive:
            return
        from smana.common.navgrid import NavGrid
        from smana.common.query import QueryError, request

        try:
            patch = request(self.session, keys.query(self.robot, "navgraph", "graph"), None, 10.0)
        except QueryError as exc:
            self.note("graph", f"could not fetch the navigation graph: {exc}")
            return
        if not isinstance(patch, GraphPatch):
            self.note("graph", "navgraph/graph did not answer with a GraphPatch")
            return
        nav = self.config.navgraph
        grid = NavGrid.from_bounds(nav.bounds_min_xy, nav.bounds_max_xy, patch.resolution_m)
        grid.apply_patch(patch.cells, patch.labels, patch.heights, patch.flags)
        box = grid.known_box()
        if box is None:
            return
        labels, heights, flags = grid.box(*box)
        origin = grid.origin_xy + np.array(box[:2]) * grid.resolution_m
        path = Path(run_dir) / "graph.npz"
        np.savez_compressed(
            path,
            origin_xy=origin,
            resolution_m=grid.resolution_m,
            labels=labels,
            heights=heights,
            flags=flags,
        )
        self.log.info("navigation graph (%d nodes) written to %s", len(patch.cells), path)

    def status_details(self) -> dict:
        p = self.pacer
        return {
            "progress": f"{self.done}/{len(self.feed)}",
            "phase": self.phase,
            "published": p.published,
            "acknowledged": p.acked,
            "lost": p.lost,
            "overtaken": p.overtaken,
            "poses_published": len(self.pose_log),
            "late": p.late_published + p.late_integrated,
        }

    def on_stop(self) -> None:
        self.feed.stop()
        self.reader.close()


def path_length_m(rows) -> float:
    """Horizontal length of the path through (t, x, y, ...) rows, as a run's report measures it."""
    return sum(math.dist(a[1:3], b[1:3]) for a, b in zip(rows, rows[1:]))


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000.0, 3)


def summary_line(s: dict) -> str:
    lat = s["latency"]
    mean = f"{lat['mean_ms']:.0f} ms" if lat["mean_ms"] is not None else "-"
    if s["mode"] == "lockstep":  # a loss is a failure
        losses = f"{s['lost']} lost"
    else:  # the mapper's latest-wins input drops what it cannot keep up with, by design
        losses = (
            f"{s['overtaken']} overtaken (dropped as stale by the mapper, or on the way), "
            f"{s['unacknowledged']} unacknowledged"
        )
    return (
        f"{s['published']}/{s['scans']} scans published ({s['empty']} empty, "
        f"{len(s['read_errors'])} unreadable), {s['acknowledged']} integrated, {losses}, "
        f"{s['late_published']}+{s['late_integrated']} late, latency mean {mean}, "
        f"{s['points_published']}/{s['points_in']} points kept, {s['poses_published']} poses "
        f"over {s['distance_m']:.1f} m"
    )


def main(config: SmanaConfig, reader: DatasetReader | None = None) -> int:
    service = ReplayService(config, reader)
    with progress.logs_around_bar():
        service.run()
    return service.exit_code
