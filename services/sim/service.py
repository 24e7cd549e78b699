"""The simulator service: the `Simulation` core on the robot's zenoh keys.

Publishes, at rates counted in simulated time:
- `robot/pose` (with the configured pose noise) and `robot/pose_truth`, at `pose_rate_hz`;
- `robot/cloud`: one camera `SemanticCloud` per frame at `camera.rate_hz` (and, with
  `camera.publish_images`, `robot/image/{rgb,depth,semantic}`);
- `robot/scan`: LiDAR `SemanticCloud`s at `lidar.rate_hz` when `lidar.enabled`;
- `robot/clock`: `{"sim_time_s", "real_time_factor"}` (the factor actually achieved).
Subscribes to `robot/cmd_vel`; the base stops `robot.cmd_timeout_s` after the last command.

Pacing: simulated time follows the wall clock times `real_time_factor`. When rendering cannot
keep up, the debt is dropped rather than caught up in a burst (counted as `lag_resets`), so the
achieved factor is lower and says so. In lockstep, after each cloud the world waits (up to
`lockstep_timeout_s` of wall time) for the mapper's `MapDelta` whose `cloud_seq` is that cloud's
seq, so a slow mapper sees every cloud and the closed loop keeps its timing. Clouds then go out
with congestion control BLOCK; otherwise DROP (a stale cloud is better lost than queued).
"""

from __future__ import annotations

import collections
import math
import time
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import MapDelta, VelocityCommand
from smana.common.plausibility import StampGate
from smana.common.service import Reject, Service, run_service

from .finishing import FinishedFrame, finished, make_worker
from .simulation import Simulation, pose_message

MAX_DEBT_S = 0.25  # wall seconds the simulation may lag before the debt is forgiven
MAX_TICK_S = 0.05  # wall seconds of physics per tick before commands get a turn


class SimService(Service):
    name = "sim"
    tick_period_s = 0.004  # about one physics step (240 Hz) per tick

    def __init__(self, config: SmanaConfig, sim: Simulation | None = None):
        super().__init__(config)
        self.sc = sc = config.sim
        self.sim = sim  # built in warm_up when not given
        g = config.general
        # commands carry their sender's wall clock (the explorer's), checked like any stream
        self.cmd_stamps = StampGate(g.stamp_window_s, g.max_time_rate)
        self.pose_seq = 0
        self.image_seq = 0
        self.period_pose = 1.0 / sc.pose_rate_hz
        self.period_camera = 1.0 / sc.camera.rate_hz
        self.period_lidar = 1.0 / sc.lidar.rate_hz
        self.period_clock = 1.0 / sc.clock_rate_hz
        self._wall0: float | None = None
        self.awaiting: int | None = None  # lockstep: the cloud seq we wait for
        self._awaiting_since = 0.0
        self.lag_resets = 0
        self.lockstep_timeouts = 0
        self.commands = 0
        self.camera_ms: list[float] = []
        self.lidar_ms: list[float] = []
        self.achieved_rtf = 0.0
        self._worker = self._finish = None
        self._in_flight: collections.deque[tuple[Future, float]] = collections.deque()

    def prepare(self) -> None:
        sc = self.sc
        if self.sim is None:
            self.startup_step = "building the world"
            classes = ClassTable.load(self.config.general.class_table)
            self.sim = Simulation(sc, classes=classes)
        sim = self.sim
        t = sim.time_s
        self.next_pose = self.next_camera = self.next_lidar = self.next_clock = t
        self._sim0 = t
        self._rtf_mark = (time.monotonic(), t)
        # Degrading and encoding a frame runs on a worker (`camera.worker`, see finishing.py)
        # while the loop steps physics and renders the next. Not in lockstep,
        # where the world must not move between a cloud and its MapDelta.
        worker = make_worker(
            "off" if sc.lockstep else sc.camera.worker,
            sc,
            sim.finisher,
            sim.world.classes.colour_lut,
        )
        self._worker, self._finish = worker if worker is not None else (None, None)

    # -- wiring ----------------------------------------------------------------------------------

    def setup(self) -> None:
        r, sc = self.robot, self.sc
        block = sc.lockstep  # in lockstep no cloud may be lost
        self.cloud_pub = self.publisher(keys.cloud(r), reliable_block=block)
        self.scan_pub = self.publisher(keys.scan(r), reliable_block=block)
        self.pose_pub = self.publisher(keys.pose(r))
        self.truth_pub = self.publisher(keys.pose_truth(r))
        self.clock_pub = self.publisher(keys.clock(r))
        self.image_pubs = {}
        if sc.camera.publish_images:
            for kind in ("rgb", "depth", "semantic"):
                self.image_pubs[kind] = self.publisher(keys.image(r, kind))
        self.subscribe(keys.cmd_vel(r), self.on_cmd, VelocityCommand)
        if sc.lockstep:
            self.subscribe(keys.map_delta(r), self.on_delta, MapDelta)
        w = self.sim.world
        self.log.info(
            "world %s, %.0f x %.0f m, %d objects; camera %dx%d at %.1f Hz, lidar %s; noise %s, "
            "pose noise %.3g m / %.3g rad; rtf %.2f%s",
            w.name,
            *w.size_m,
            len(w.objects),
            sc.camera.width,
            sc.camera.height,
            sc.camera.rate_hz,
            f"{sc.lidar.rate_hz:.1f} Hz" if sc.lidar.enabled else "off",
            sc.noise,
            sc.pose_noise_xy_m,
            sc.pose_noise_yaw_rad,
            sc.real_time_factor,
            ", lockstep" if sc.lockstep else "",
        )

    def on_cmd(self, cmd: VelocityCommand) -> None:
        verdict = self.cmd_stamps.check(cmd.stamp_s)
        if not verdict.ok:
            raise Reject(verdict.kind, f"velocity command {cmd.seq}: {verdict.reason}")
        self.sim.set_velocity(cmd.linear_mps, cmd.angular_radps)  # ValueError -> rejected
        self.commands += 1

    def on_delta(self, delta: MapDelta) -> None:
        if self.awaiting is not None and int(delta.cloud_seq) >= self.awaiting:
            self.awaiting = None

    def on_stop(self) -> None:
        if self.sim is None:
            return  # stopped while building the world
        try:
            self._drain(block=True)
        finally:
            if self._worker is not None:
                self._worker.shutdown(wait=True)
            self.sim.close()

    # -- the loop --------------------------------------------------------------------------------

    def _anchor(self, now: float) -> None:
        self._wall0, self._sim0 = now, self.sim.time_s

    def tick(self) -> None:
        now = time.monotonic()
        if self._wall0 is None:
            self._anchor(now)
        if self.awaiting is not None:
            if now - self._awaiting_since < self.sc.lockstep_timeout_s:
                self._anchor(now)  # frozen while waiting: no catching up afterwards
                return
            self.lockstep_timeouts += 1
            self.note("lockstep_timeout", f"no MapDelta for cloud {self.awaiting}")
            self.awaiting = None
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
            if self._emit() and self.awaiting is not None:
                return
            if time.monotonic() - now > MAX_TICK_S:
                break
        self._measure_rtf()

    def _next_event(self) -> float:
        t = [self.next_pose, self.next_clock]
        if self.sc.camera.enabled:
            t.append(self.next_camera)
        if self.sc.lidar.enabled:
            t.append(self.next_lidar)
        return min(t)

    def _emit(self) -> bool:
        """Publish whatever is due at the current simulated time; True if a cloud went out."""
        sim, sc = self.sim, self.sc
        t = sim.time_s + 1e-9
        sent_cloud = False
        if t >= self.next_pose:
            self.next_pose = _next(self.next_pose, self.period_pose, sim.time_s)
            self.pose_seq += 1
            self.pose_pub.put(pose_message(sim.published_pose(), sim.time_s, self.pose_seq))
            self.truth_pub.put(pose_message(sim.true_pose(), sim.time_s, self.pose_seq))
        if t >= self.next_clock:
            self.next_clock = _next(self.next_clock, self.period_clock, sim.time_s)
            self.clock_pub.put({"sim_time_s": sim.time_s, "real_time_factor": self.achieved_rtf})
        if sc.camera.enabled and t >= self.next_camera:
            self.next_camera = _next(self.next_camera, self.period_camera, sim.time_s)
            t0 = time.perf_counter()
            pending = sim.capture_camera()
            if self._worker is None:
                self._publish_frame(
                    finished(sim.finish_camera(pending), sc.camera.publish_images), t0
                )
                sent_cloud = True
            else:
                self._drain(block=True)  # one frame in flight at most: order, bounded memory
                self._in_flight.append((self._worker.submit(self._finish, pending), t0))
        if sc.lidar.enabled and t >= self.next_lidar:
            self.next_lidar = _next(self.next_lidar, self.period_lidar, sim.time_s)
            t0 = time.perf_counter()
            scan = sim.lidar_scan()
            self.scan_pub.put(scan.to_cloud())
            self.lidar_ms.append(1000 * (time.perf_counter() - t0))
            self._sent(scan.seq)
            sent_cloud = True
        return sent_cloud

    def _drain(self, block: bool) -> None:
        """Publish the frames the worker has finished, oldest first."""
        while self._in_flight and (block or self._in_flight[0][0].done()):
            future, t0 = self._in_flight.popleft()
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
            self._publish_frame(frame, t0)

    def _publish_frame(self, frame: FinishedFrame, t0: float) -> None:
        self.cloud_pub.put(frame.cloud)
        for kind, payload in frame.images.items():
            self.image_pubs[kind].put(payload)
        self.camera_ms.append(1000 * (time.perf_counter() - t0))
        self._sent(frame.seq)

    def _sent(self, seq: int) -> None:
        if self.sc.lockstep:
            self.awaiting = seq
            self._awaiting_since = time.monotonic()

    def _measure_rtf(self) -> None:
        now = time.monotonic()
        wall0, sim0 = self._rtf_mark
        if now - wall0 >= 1.0:
            self.achieved_rtf = (self.sim.time_s - sim0) / (now - wall0)
            self._rtf_mark = (now, self.sim.time_s)

    def status_details(self) -> dict:
        sim = self.sim
        m = sim.true_pose()
        return {
            "sim_time_s": round(sim.time_s, 3),
            "real_time_factor": round(self.achieved_rtf, 3),
            "real_time_factor_target": self.sc.real_time_factor,
            "camera_frames": sim.camera_frames,
            "camera_latency_ms_mean": _mean(self.camera_ms[-50:]),
            "lidar_scans": sim.lidar_scans,
            "lidar_ms_mean": _mean(self.lidar_ms[-20:]),
            "commands": self.commands,
            "stopped_no_command": sim.robot.timed_out,
            "lag_resets": self.lag_resets,
            "lockstep_timeouts": self.lockstep_timeouts,
            "awaiting_cloud": self.awaiting,
            "pose_xy_yaw": [
                round(m[0, 3], 3),
                round(m[1, 3], 3),
                round(math.atan2(m[1, 0], m[0, 0]), 3),
            ],
        }


def _next(scheduled: float, period: float, now: float) -> float:
    """The next due time on the period's grid; when behind by more than a period, skip ahead
    instead of publishing a burst."""
    nxt = scheduled + period
    return nxt if nxt > now else now + period


def _mean(xs: list[float]) -> float | None:
    return round(sum(xs) / len(xs), 1) if xs else None


def main(config: SmanaConfig) -> int:
    return run_service(SimService, config)
