"""The simulator service: the `Simulation` core on the robot's zenoh keys.

Publishes, at rates counted in simulated time:
- `robot/pose` (with the configured pose noise) and `robot/pose_truth`, at `pose_rate_hz`;
- `robot/cloud`: one camera `SemanticCloud` per frame at `camera.rate_hz` (and, with
  `camera.publish_images`, `robot/image/{rgb,depth,semantic}`);
- `robot/scan`: LiDAR `SemanticCloud`s at `lidar.rate_hz` when `lidar.enabled`;
- `robot/safety_scan`: the safety scanner's points in the base frame at `safety_scan.rate_hz`
  when `safety_scan.enabled` (the default);
- `robot/clock`: `{"sim_time_s", "real_time_factor"}` (the factor actually achieved).
Subscribes to `robot/cmd_vel`; the base stops `robot.cmd_timeout_s` after the last command.

A fleet (`fleet.robots` non-empty): the members share one world, and the service runs under the
fleet's name (`general.robot`, `--robot fleet` from the supervisor: its status and liveliness are
`smana/fleet/.../sim`) while each member's streams above go out on that member's own keys
(`smana/<member>/robot/...`), and each member listens to its own `robot/cmd_vel`. Camera frames
(and scans) of the members take turns over the period, so that they do not all render in one
tick; in lockstep the world waits for each member's MapDelta. Contacts between members are
counted per pair (an event `robot_contact` each) and, with a run directory, written at stop to
`<run_dir>/sim.json` with each member's figures.

Pacing: simulated time follows the wall clock times `real_time_factor`. When rendering cannot
keep up, the debt is dropped rather than caught up in a burst (counted as `lag_resets`), so the
achieved factor is lower and says so. In lockstep, after each cloud the world waits (up to
`lockstep_timeout_s` of wall time) for the mapper's `MapDelta` whose `cloud_seq` is that cloud's
seq, so a slow mapper sees every cloud and the closed loop keeps its timing. Clouds then go out
with congestion control BLOCK; otherwise DROP (a stale cloud is better lost than queued).
"""

from __future__ import annotations

import collections
import functools
import json
import math
import os
import time
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import MapDelta, VelocityCommand
from smana.common.plausibility import StampGate
from smana.common.service import Reject, Service, run_service

from .finishing import FinishedFrame, finished, make_worker
from .simulation import Member, Simulation, pose_message

MAX_DEBT_S = 0.25  # wall seconds the simulation may lag before the debt is forgiven
MAX_TICK_S = 0.05  # wall seconds of physics per tick before commands get a turn


class MemberStreams:
    """One member's side of the service: its keys, its command gate, its sensors' schedule and,
    in lockstep, the cloud it waits to see acknowledged."""

    def __init__(self, key_name: str, member: Member, gate: StampGate):
        self.key_name = key_name  # the `<robot>` of its keys
        self.member = member
        self.cmd_stamps = gate  # commands carry their sender's wall clock, checked as any stream
        self.pose_seq = 0
        self.commands = 0
        self.next_camera = self.next_lidar = self.next_safety = 0.0
        self.awaiting: int | None = None  # lockstep: the cloud seq we wait for


class SimService(Service):
    name = "sim"
    tick_period_s = 0.004  # about one physics step (240 Hz) per tick

    def __init__(self, config: SmanaConfig, sim: Simulation | None = None):
        super().__init__(config)
        self.sc = sc = config.sim
        self.fleet = config.fleet
        self.sim = sim  # built in warm_up when not given
        self.streams: list[MemberStreams] = []  # one per member, built with the simulation
        self.period_pose = 1.0 / sc.pose_rate_hz
        self.period_camera = 1.0 / sc.camera.rate_hz
        self.period_lidar = 1.0 / sc.lidar.rate_hz
        self.period_safety = 1.0 / sc.safety_scan.rate_hz
        self.period_clock = 1.0 / sc.clock_rate_hz
        self._wall0: float | None = None
        self._awaiting_since = 0.0
        self.lag_resets = 0
        self.lockstep_timeouts = 0
        self.commands = 0
        # the latest timings only, for the status: a run of hours keeps no history of them
        self.camera_ms: collections.deque[float] = collections.deque(maxlen=50)
        self.lidar_ms: collections.deque[float] = collections.deque(maxlen=20)
        self.safety_ms: collections.deque[float] = collections.deque(maxlen=20)
        self.achieved_rtf = 0.0
        self._worker = self._finish = None
        self._in_flight: collections.deque[tuple[Future, float, MemberStreams]] = (
            collections.deque()
        )

    @property
    def awaiting(self) -> int | None:
        """Lockstep: the cloud seq the first member waits for (the single robot's)."""
        return self.streams[0].awaiting if self.streams else None

    def prepare(self) -> None:
        sc, g = self.sc, self.config.general
        if self.sim is None:
            self.startup_step = "building the world"
            classes = ClassTable.load(g.class_table)
            robots = list(self.fleet.robots) if self.fleet.enabled else None
            self.sim = Simulation(sc, classes=classes, robots=robots, fleet=self.fleet)
        sim = self.sim
        # alone, the robot's keys are the service's own namespace; in a fleet, each member's name
        names = sim.robots if self.fleet.enabled else [self.robot]
        self.streams = [
            MemberStreams(name, m, StampGate(g.stamp_window_s, g.max_time_rate))
            for name, m in zip(names, sim.members, strict=True)
        ]
        t = sim.time_s
        self.next_pose = self.next_clock = t
        n = len(self.streams)
        for i, st in enumerate(self.streams):
            # members take turns over the period: not every camera renders in the same tick
            st.next_camera = t + i * self.period_camera / n
            st.next_lidar = t + i * self.period_lidar / n
            st.next_safety = t + i * self.period_safety / n
        self._sim0 = t
        self._rtf_mark = (time.monotonic(), t)
        # Degrading and encoding a frame runs on a worker (`camera.worker`, see finishing.py)
        # while the loop steps physics and renders the next. Not in lockstep,
        # where the world must not move between a cloud and its MapDelta.
        worker = make_worker(
            "off" if sc.lockstep else sc.camera.worker,
            sc,
            sim.frame_finisher,
            sim.world.classes.colour_lut,
        )
        self._worker, self._finish = worker if worker is not None else (None, None)

    # -- wiring ----------------------------------------------------------------------------------

    def setup(self) -> None:
        sc = self.sc
        block = sc.lockstep  # in lockstep no cloud may be lost
        for st in self.streams:
            r = st.key_name
            st.cloud_pub = self.publisher(keys.cloud(r), reliable_block=block)
            st.scan_pub = self.publisher(keys.scan(r), reliable_block=block)
            st.safety_pub = self.publisher(keys.safety_scan(r))
            st.pose_pub = self.publisher(keys.pose(r))
            st.truth_pub = self.publisher(keys.pose_truth(r))
            st.clock_pub = self.publisher(keys.clock(r))
            st.image_pubs = {}
            if sc.camera.publish_images:
                for kind in ("rgb", "depth", "semantic"):
                    st.image_pubs[kind] = self.publisher(keys.image(r, kind))
            self.subscribe(keys.cmd_vel(r), functools.partial(self.on_cmd, st=st), VelocityCommand)
            if sc.lockstep:
                self.subscribe(keys.map_delta(r), functools.partial(self.on_delta, st=st), MapDelta)
        w = self.sim.world
        self.log.info(
            "world %s, %.0f x %.0f m, %d objects; camera %dx%d at %.1f Hz, lidar %s, "
            "safety scan %s; noise %s, pose noise %.3g m / %.3g rad; rtf %.2f%s%s",
            w.name,
            *w.size_m,
            len(w.objects),
            sc.camera.width,
            sc.camera.height,
            sc.camera.rate_hz,
            f"{sc.lidar.rate_hz:.1f} Hz" if sc.lidar.enabled else "off",
            f"{sc.safety_scan.rate_hz:.1f} Hz" if sc.safety_scan.enabled else "off",
            sc.noise,
            sc.pose_noise_xy_m,
            sc.pose_noise_yaw_rad,
            sc.real_time_factor,
            ", lockstep" if sc.lockstep else "",
            f"; fleet {', '.join(s.key_name for s in self.streams)}" if self.fleet.enabled else "",
        )

    def on_cmd(self, cmd: VelocityCommand, st: MemberStreams) -> None:
        verdict = st.cmd_stamps.check(cmd.stamp_s)
        if not verdict.ok:
            raise Reject(verdict.kind, f"velocity command {cmd.seq}: {verdict.reason}")
        # ValueError -> rejected
        self.sim.set_velocity(cmd.linear_mps, cmd.angular_radps, st.member.index)
        st.commands += 1
        self.commands += 1

    def on_delta(self, delta: MapDelta, st: MemberStreams) -> None:
        if st.awaiting is not None and int(delta.cloud_seq) >= st.awaiting:
            st.awaiting = None

    def on_stop(self) -> None:
        if self.sim is None:
            return  # stopped while building the world
        try:
            self._drain(block=True)
        finally:
            if self._worker is not None:
                self._worker.shutdown(wait=True)
            try:
                self._write_summary()
            finally:
                self.sim.close()

    def _write_summary(self) -> None:
        """A fleet's figures in `<run_dir>/sim.json` (written whole, then renamed into place)."""
        run_dir = self.config.general.run_dir
        if not (self.fleet.enabled and run_dir):
            return
        sim = self.sim
        summary = {
            "robots": [st.key_name for st in self.streams],
            **self._contact_figures(),
            "sim_time_s": round(sim.time_s, 3),
            "members": self._member_figures(),
        }
        path = Path(run_dir) / "sim.json"
        tmp = path.with_name(f".sim.json.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(summary, indent=1) + "\n")
            os.replace(tmp, path)
        except OSError as exc:  # the run's figures are lost, not the stop
            self.log.error("could not write %s: %s", path, exc)

    # -- the loop --------------------------------------------------------------------------------

    def _anchor(self, now: float) -> None:
        self._wall0, self._sim0 = now, self.sim.time_s

    def _waiting(self) -> bool:
        return any(st.awaiting is not None for st in self.streams)

    def tick(self) -> None:
        now = time.monotonic()
        if self._wall0 is None:
            self._anchor(now)
        if self._waiting():
            if now - self._awaiting_since < self.sc.lockstep_timeout_s:
                self._anchor(now)  # frozen while waiting: no catching up afterwards
                return
            self.lockstep_timeouts += 1
            missing = ", ".join(
                f"cloud {st.awaiting}" + (f" of {st.key_name}" if self.fleet.enabled else "")
                for st in self.streams
                if st.awaiting is not None
            )
            self.note("lockstep_timeout", f"no MapDelta for {missing}")
            for st in self.streams:
                st.awaiting = None
            self._anchor(now)
        self._drain(block=False)
        sim, rtf = self.sim, self.sc.real_time_factor
        target = self._sim0 + (now - self._wall0) * rtf
        if target - sim.time_s > MAX_DEBT_S * rtf:
            self.lag_resets += 1
            self._anchor(now)
            target = sim.time_s + self.tick_period_s * rtf
        dt = sim.dt_physics
        while sim.time_s + dt <= target + 1e-9 and not self.stopping:
            due = self._next_event()
            sim.step(max(min(target, due) - sim.time_s, dt))
            self._note_contacts()
            if self._emit() and self._waiting():
                return
            if time.monotonic() - now > MAX_TICK_S:
                break
        self._measure_rtf()

    def _next_event(self) -> float:
        t = [self.next_pose, self.next_clock]
        for st in self.streams:
            if self.sc.camera.enabled:
                t.append(st.next_camera)
            if self.sc.lidar.enabled:
                t.append(st.next_lidar)
            if self.sc.safety_scan.enabled:
                t.append(st.next_safety)
        return min(t)

    def _emit(self) -> bool:
        """Publish whatever is due at the current simulated time; True if a cloud went out."""
        sim, sc = self.sim, self.sc
        t = sim.time_s + 1e-9
        sent_cloud = False
        if t >= self.next_pose:
            self.next_pose = _next(self.next_pose, self.period_pose, sim.time_s)
            for st in self.streams:
                st.pose_seq += 1
                i = st.member.index
                st.pose_pub.put(pose_message(sim.published_pose(i), sim.time_s, st.pose_seq))
                st.truth_pub.put(pose_message(sim.true_pose(i), sim.time_s, st.pose_seq))
        if t >= self.next_clock:
            self.next_clock = _next(self.next_clock, self.period_clock, sim.time_s)
            clock = {"sim_time_s": sim.time_s, "real_time_factor": self.achieved_rtf}
            for st in self.streams:
                st.clock_pub.put(clock)
        for st in self.streams:
            if sc.camera.enabled and t >= st.next_camera:
                st.next_camera = _next(st.next_camera, self.period_camera, sim.time_s)
                t0 = time.perf_counter()
                pending = sim.capture_camera(member=st.member.index)
                if self._worker is None:
                    frame = finished(sim.finish_camera(pending), sc.camera.publish_images)
                    self._publish_frame(st, frame, t0)
                    sent_cloud = True
                else:
                    self._drain(block=True)  # one frame in flight at most: order, bounded memory
                    self._in_flight.append((self._worker.submit(self._finish, pending), t0, st))
            if sc.lidar.enabled and t >= st.next_lidar:
                st.next_lidar = _next(st.next_lidar, self.period_lidar, sim.time_s)
                t0 = time.perf_counter()
                scan = sim.lidar_scan(member=st.member.index)
                st.scan_pub.put(scan.to_cloud())
                self.lidar_ms.append(1000 * (time.perf_counter() - t0))
                self._sent(st, scan.seq)
                sent_cloud = True
            if sc.safety_scan.enabled and t >= st.next_safety:
                st.next_safety = _next(st.next_safety, self.period_safety, sim.time_s)
                t0 = time.perf_counter()
                st.safety_pub.put(sim.safety_scan(member=st.member.index))
                self.safety_ms.append(1000 * (time.perf_counter() - t0))
        return sent_cloud

    def _note_contacts(self) -> None:
        for t, pair in self.sim.take_contact_events():
            self.note("robot_contact", f"robots {pair} touch at {t:.2f} s (simulated)")

    def _drain(self, block: bool) -> None:
        """Publish the frames the worker has finished, oldest first."""
        while self._in_flight and (block or self._in_flight[0][0].done()):
            future, t0, st = self._in_flight.popleft()
            try:
                frame = future.result()  # any other failure is counted by the loop
            except BrokenProcessPool:
                self.log.error(
                    "the camera worker process died: finishing frames in line from "
                    "now on (frame lost)"
                )
                self.note("camera_worker", "worker process died")
                self._worker.shutdown(wait=False, cancel_futures=True)
                self._worker = None
                self._in_flight.clear()
                return
            self._publish_frame(st, frame, t0)

    def _publish_frame(self, st: MemberStreams, frame: FinishedFrame, t0: float) -> None:
        st.cloud_pub.put(frame.cloud)
        for kind, payload in frame.images.items():
            st.image_pubs[kind].put(payload)
        self.camera_ms.append(1000 * (time.perf_counter() - t0))
        self._sent(st, frame.seq)

    def _sent(self, st: MemberStreams, seq: int) -> None:
        if self.sc.lockstep:
            st.awaiting = seq
            self._awaiting_since = time.monotonic()

    def _measure_rtf(self) -> None:
        now = time.monotonic()
        wall0, sim0 = self._rtf_mark
        if now - wall0 >= 1.0:
            self.achieved_rtf = (self.sim.time_s - sim0) / (now - wall0)
            self._rtf_mark = (now, self.sim.time_s)

    # -- figures ---------------------------------------------------------------------------------

    def _member_figures(self) -> dict[str, dict]:
        sim = self.sim
        out = {}
        for st in self.streams:
            m = st.member
            out[st.key_name] = {
                "pose_xy_yaw": _xy_yaw(sim.true_pose(m.index)),
                "camera_frames": m.camera_frames,
                "lidar_scans": m.lidar_scans,
                "commands": st.commands,
                "stopped_no_command": m.robot.timed_out,
                "member_px": m.member_px,
                "member_hits": m.member_hits,
            }
        return out

    def _contact_figures(self) -> dict:
        contacts = self.sim.robot_contacts()
        return {
            "robot_contacts": contacts,
            "robot_contacts_total": sum(contacts.values()),
            "min_separation_m": {
                k: round(d, 3) if math.isfinite(d) else None
                for k, d in self.sim.min_separation_m().items()
            },
        }

    def status_details(self) -> dict:
        sim = self.sim
        first = self.streams[0]
        details = {
            "sim_time_s": round(sim.time_s, 3),
            "real_time_factor": round(self.achieved_rtf, 3),
            "real_time_factor_target": self.sc.real_time_factor,
            "camera_frames": sim.camera_frames,
            "camera_latency_ms_mean": _mean(self.camera_ms),
            "lidar_scans": sim.lidar_scans,
            "lidar_ms_mean": _mean(self.lidar_ms),
            "safety_scan_ms_mean": _mean(self.safety_ms),
            "commands": first.commands,
            "stopped_no_command": sim.robot.timed_out,
            "lag_resets": self.lag_resets,
            "lockstep_timeouts": self.lockstep_timeouts,
            "awaiting_cloud": first.awaiting,
            "pose_xy_yaw": _xy_yaw(sim.true_pose()),
        }
        if self.fleet.enabled:
            details["robots"] = self._member_figures()
            details.update(self._contact_figures())
        return details


def _xy_yaw(m) -> list[float]:
    return [round(m[0, 3], 3), round(m[1, 3], 3), round(math.atan2(m[1, 0], m[0, 0]), 3)]


def _next(scheduled: float, period: float, now: float) -> float:
    """The next due time on the period's grid; when behind by more than a period, skip ahead
    instead of publishing a burst."""
    nxt = scheduled + period
    return nxt if nxt > now else now + period


def _mean(xs: collections.deque[float]) -> float | None:
    return round(sum(xs) / len(xs), 1) if xs else None


def main(config: SmanaConfig) -> int:
    return run_service(SimService, config)
