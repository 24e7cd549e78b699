"""The simulator core: world, physics, robot, sensors and degradation, without zenoh.

    from smana.common.config.sim import CameraConfig, SimConfig
    from smana.services.sim.simulation import Simulation

    with Simulation(SimConfig(noise="medium", camera=CameraConfig(width=320, height=320))) as sim:
        sim.set_velocity(0.3, 0.2)
        sim.step(0.5)                      # simulated seconds
        frame = sim.camera_frame()         # images + labelled cloud (world frame, published pose)
        cloud = frame.to_cloud()           # as a SemanticCloud message
        scan = sim.lidar_scan()
        truth = sim.true_pose()            # 4x4; sim.published_pose() adds the pose noise

Time is simulated time (`sim.time_s`), advanced only by `step`; the service paces it against the
wall clock. Random streams (label redraws, confidences, pose noise) are separate children of the
config's seed, so enabling one kind of noise does not change the draws of another. The parts
receive their sections of the config as they are: the world `sim.world` (services/sim/worlds),
the robot `[sim.robot]`, the camera `[sim.camera]`, the LiDAR `[sim.lidar]`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pybullet as p

from smana.common.classes import ClassTable
from smana.common.config import SimConfig
from smana.common.messages import Pose, SemanticCloud, matrix_to_quat

from .camera import CameraCapture, SemanticCamera
from .degrade import LabelDegrader, PoseNoise
from .lidar import Lidar
from .robot import DiffDriveRobot
from .scene import DROP, BulletScene, transform_points
from .worlds import World, build_world


def _semantic_cloud(frame, source: str) -> SemanticCloud:
    """A camera frame's or a LiDAR scan's cloud, placed with the published sensor pose."""
    m = frame.world_from_sensor
    return SemanticCloud(
        stamp_s=frame.stamp_s,
        seq=frame.seq,
        points=frame.points,
        labels=frame.labels,
        confidences=frame.confidences,
        sensor_position=m[:3, 3].copy(),
        sensor_orientation_xyzw=matrix_to_quat(m[:3, :3]),
        source=source,
    )


@dataclass
class CameraFrame:
    """One camera frame as published. `points` are in the world frame as the robot believes it
    to be (the published, possibly noisy, pose); `true_world_from_sensor` is the real pose."""

    stamp_s: float
    seq: int
    rgb: np.ndarray  # u1[H, W, 3]
    depth_m: np.ndarray  # f4[H, W], inf where no point
    semantic_true: np.ndarray  # i4[H, W] true class ids, -1 where no point
    semantic: np.ndarray  # i4[H, W] labels after degradation, -1 where no point
    points: np.ndarray  # f4[N, 3] world frame (published pose)
    labels: np.ndarray  # u2[N]
    confidences: np.ndarray  # f4[N]
    rows: np.ndarray  # i8[N] pixel of each point
    cols: np.ndarray  # i8[N]
    world_from_sensor: np.ndarray  # 4x4 published sensor pose
    true_world_from_sensor: np.ndarray  # 4x4

    def to_cloud(self) -> SemanticCloud:
        return _semantic_cloud(self, "camera")


@dataclass
class PendingFrame:
    """A rendered frame waiting for `Simulation.finish_camera`."""

    stamp_s: float
    seq: int
    capture: CameraCapture
    world_from_sensor: np.ndarray  # published (possibly noisy) sensor pose


@dataclass
class LidarScan:
    stamp_s: float
    seq: int
    points: np.ndarray  # f4[N, 3] world frame (published pose)
    labels: np.ndarray  # u2[N]
    confidences: np.ndarray  # f4[N]
    world_from_sensor: np.ndarray  # published
    true_world_from_sensor: np.ndarray

    def to_cloud(self) -> SemanticCloud:
        return _semantic_cloud(self, "lidar")


def pose_message(m: np.ndarray, stamp_s: float, seq: int) -> Pose:
    return Pose(float(stamp_s), int(seq), m[:3, 3].copy(), matrix_to_quat(m[:3, :3]))


def _seed_sequences(seed: int) -> list[np.random.SeedSequence]:
    """The label, confidence and pose-noise streams of a seed (the same ones in any process)."""
    return np.random.SeedSequence([int(seed), 0x51A]).spawn(3)


class FrameFinisher:
    """The second half of a camera frame: degrade its labels and build its world-frame cloud.

    It holds the label and confidence random streams, so frames must pass through one finisher in
    the order they were captured. It touches no PyBullet state: it may run on another thread or in
    another process (the sim service finishes frames in a worker process while the next renders).
    """

    def __init__(self, config: SimConfig, colour_lut: np.ndarray):
        labels_ss, conf_ss, _ = _seed_sequences(config.seed)
        self.stride = config.camera.stride
        self.degrader = LabelDegrader(
            config.noise,
            np.random.default_rng(labels_ss),
            colour_lut,
            region_px=config.slic_region_px,
            iterations=config.slic_iterations,
        )
        self._conf_rng = np.random.default_rng(conf_ss)

    def finish(
        self, pending: PendingFrame, stride: int | None = None, timings: dict | None = None
    ) -> CameraFrame:
        stride = self.stride if stride is None else int(stride)
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        cap = pending.capture
        sem = self.degrader.degrade(cap.labels, timings).labels
        t0 = time.perf_counter()
        rows, cols = np.nonzero(sem[::stride, ::stride] >= 0)
        rows, cols = rows * stride, cols * stride
        pts_sensor = cap.points_sensor(rows, cols)
        frame = CameraFrame(
            stamp_s=pending.stamp_s,
            seq=pending.seq,
            rgb=cap.rgb,
            depth_m=cap.depth_m,
            semantic_true=cap.labels,
            semantic=sem,
            points=transform_points(pts_sensor, pending.world_from_sensor),
            labels=sem[rows, cols].astype(np.uint16),
            confidences=self.degrader.confidences(len(rows), self._conf_rng),
            rows=rows,
            cols=cols,
            world_from_sensor=pending.world_from_sensor,
            true_world_from_sensor=cap.world_from_sensor,
        )
        if timings is not None:
            timings["cloud_ms"] = 1e3 * (time.perf_counter() - t0)
        return frame


class Simulation:
    """A garden world with a robot in it (module docstring)."""

    def __init__(
        self,
        config: SimConfig | None = None,
        *,
        classes: ClassTable | None = None,
        world: World | None = None,
    ):
        self.config = cfg = config or SimConfig()
        classes = classes or (world.classes if world else ClassTable.load("garden3drms"))
        self.world = world or build_world(cfg, classes)
        self.scene = BulletScene(self.world)
        self.dt_physics = 1.0 / cfg.physics_hz
        p.setTimeStep(self.dt_physics, physicsClientId=self.scene.client)
        if cfg.spawn:
            x, y, yaw = (float(v) for v in cfg.spawn)
            z = float(self.world.ground.height_at(x, y))
        else:
            x, y, z = self.world.spawn_pose(cfg.robot.radius_m + 0.05)
            yaw = 0.0
        self.robot = DiffDriveRobot(self.scene.client, cfg.robot, xy=(x, y), ground_z=z, yaw=yaw)
        self.scene.register(self.robot.body, DROP)
        self._camera: SemanticCamera | None = None
        self._lidar: Lidar | None = None
        self.finisher = FrameFinisher(cfg, self.world.classes.colour_lut)
        self.degrader = self.finisher.degrader
        pose_ss = _seed_sequences(cfg.seed)[2]
        self.pose_noise = PoseNoise(
            cfg.pose_noise_xy_m, cfg.pose_noise_yaw_rad, np.random.default_rng(pose_ss)
        )
        self.time_s = 0.0
        # one sequence for camera and LiDAR clouds, so that a MapDelta's cloud_seq names one
        self.cloud_seq = 0
        self.camera_frames = 0
        self.lidar_scans = 0
        # let the robot settle on its wheels before anyone looks
        self.step(0.5)
        self.time_s = 0.0

    # -- time and motion ----------------------------------------------------------------------

    def step(self, dt_s: float) -> int:
        """Advance simulated time by about `dt_s` (whole physics steps); returns the step count."""
        if not dt_s >= 0 or not math.isfinite(dt_s):
            raise ValueError(f"dt_s must be finite and >= 0, got {dt_s}")
        n = int(round(dt_s / self.dt_physics))
        c = self.scene.client
        for _ in range(n):
            self.robot.update(self.time_s, self.dt_physics)
            p.stepSimulation(physicsClientId=c)
            self.time_s += self.dt_physics
        return n

    def set_velocity(self, linear_mps: float, angular_radps: float) -> None:
        """Command the base (clamped to the limits); it stops `cmd_timeout_s` after the last."""
        self.robot.command(linear_mps, angular_radps, self.time_s)

    def true_pose(self) -> np.ndarray:
        """4x4 world-from-base pose (ground truth)."""
        return self.robot.matrix()

    def published_pose(self) -> np.ndarray:
        """The pose as localisation would give it: the truth with fresh pose noise."""
        return self.pose_noise.apply(self.robot.matrix())

    # -- sensors ------------------------------------------------------------------------------

    @property
    def camera(self) -> SemanticCamera:
        if self._camera is None:
            self._camera = SemanticCamera(self.scene, self.config.camera)
        return self._camera

    @property
    def lidar(self) -> Lidar:
        if self._lidar is None:  # builds ~131k rays' lists: only when asked for
            self._lidar = Lidar(self.scene, self.config.lidar, parent_body=self.robot.body)
        return self._lidar

    def camera_frame(self, stride: int | None = None, timings: dict | None = None) -> CameraFrame:
        """Render, label, degrade and unproject one camera frame (see CameraFrame). With
        `timings`, the time of each stage goes in it (ms): render, label, slic, redraw, cloud."""
        return self.finish_camera(self.capture_camera(timings), stride, timings)

    def capture_camera(self, timings: dict | None = None) -> PendingFrame:
        """The first half of `camera_frame`: render and label at the current time (PyBullet, so
        on the thread that owns the simulation)."""
        base_true = self.robot.matrix()
        base_pub = self.pose_noise.apply(base_true)
        mount = self.config.camera.mount_matrix()
        cap = self.camera.capture(base_true @ mount, timings)
        self.cloud_seq += 1
        self.camera_frames += 1
        return PendingFrame(self.time_s, self.cloud_seq, cap, base_pub @ mount)

    def finish_camera(
        self, pending: PendingFrame, stride: int | None = None, timings: dict | None = None
    ) -> CameraFrame:
        """The second half: degrade the labels and build the world-frame cloud (`FrameFinisher`).
        Frames must be finished in the order they were captured."""
        return self.finisher.finish(pending, stride, timings)

    def lidar_scan(self, timings: dict | None = None) -> LidarScan:
        """Cast one LiDAR scan; labels are the hit bodies' true classes (confidence 1)."""
        base_true = self.robot.matrix()
        base_pub = self.pose_noise.apply(base_true)
        hits = self.lidar.scan(base_true, timings)
        world_from_sensor = base_pub @ self.config.lidar.mount_matrix()
        self.cloud_seq += 1
        self.lidar_scans += 1
        return LidarScan(
            stamp_s=self.time_s,
            seq=self.cloud_seq,
            points=transform_points(hits.points_sensor, world_from_sensor),
            labels=hits.labels.astype(np.uint16),
            confidences=np.ones(len(hits.labels), "f4"),
            world_from_sensor=world_from_sensor,
            true_world_from_sensor=hits.world_from_sensor,
        )

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        self.scene.close()

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
