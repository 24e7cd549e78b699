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

Several robots share one world when given names (`Simulation(config, robots=["r1", "r2"])`, a
fleet): each member has its own body, pose noise, label and confidence streams, cloud numbering
and LiDAR; one camera renders for all, from each member's pose. Methods take `member` (index or
name; 0 by default, so `sim.robot`, `sim.camera_frame()` ... are the single robot's as before).
Members see each other (camera and LiDAR) but drop those points like their own body's: a fleet
filters its members by their broadcast poses rather than mapping them as obstacles. They collide
as rigid bodies; contact episodes and the closest approach are kept per pair
(`robot_contacts()`, `min_separation_m()`).

Time is simulated time (`sim.time_s`), advanced only by `step`; the service paces it against the
wall clock. Random streams (label redraws, confidences, pose noise) are separate children of the
config's seed, so enabling one kind of noise does not change the draws of another. The parts
receive their sections of the config as they are: the world `sim.world` (services/sim/worlds),
the robot `[sim.robot]`, the camera `[sim.camera]`, the LiDAR `[sim.lidar]`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pybullet as p

from smana.common.classes import ClassTable
from smana.common.config import SimConfig
from smana.common.config.fleet import FleetConfig
from smana.common.messages import Pose, SemanticCloud, matrix_to_quat

from .camera import CameraCapture, SemanticCamera
from .degrade import (
    GARDEN_CONFUSABLE,
    GARDEN_IDS,
    WET_CONFUSABLE,
    WET_IDS,
    LabelDegrader,
    PoseNoise,
)
from .lidar import Lidar, safety_cloud
from .perception import LabelNoise, perception_matrix, split_matrix
from .robot import DiffDriveRobot
from .scene import DROP, MEMBER, BulletScene, transform_points
from .worlds import World, build_world, spawn_clearance_m


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
    member: int = 0  # which member's finisher (random streams) it goes through


@dataclass
class LidarScan:
    stamp_s: float
    seq: int
    points: np.ndarray  # f4[N, 3] world frame (published pose)
    labels: np.ndarray  # u2[N]
    confidences: np.ndarray  # f4[N]
    world_from_sensor: np.ndarray  # published
    true_world_from_sensor: np.ndarray
    member_hits: int = 0  # rays that hit another member (dropped)

    def to_cloud(self) -> SemanticCloud:
        return _semantic_cloud(self, "lidar")


def pose_message(m: np.ndarray, stamp_s: float, seq: int) -> Pose:
    return Pose(float(stamp_s), int(seq), m[:3, 3].copy(), matrix_to_quat(m[:3, :3]))


def _seed_sequences(seed: int, member: int = 0) -> list[np.random.SeedSequence]:
    """The label, confidence, pose-noise, bleed and pose-drift streams of a seed (the same ones
    in any process; children by index, so the first three are what they were before the last
    two). Member 0 of a fleet keeps the single robot's; member k > 0 draws from (seed, k)."""
    if member == 0:
        return np.random.SeedSequence([int(seed), 0x51A]).spawn(5)
    return np.random.SeedSequence([int(seed), 0x51A, int(member)]).spawn(5)


def _persistent_key(seed: int) -> int:
    """The persistent errors' hash key: the seed's, the same for every member of a fleet (one
    network, one mistake about a place)."""
    return int(np.random.SeedSequence([int(seed), 0x51A, 0xE44]).generate_state(1, np.uint64)[0])


def _wet(config: SimConfig) -> bool:
    return config.world == "garden" and getattr(config.garden, "water_share", 0.0) > 0


class FrameFinisher:
    """The second half of a camera frame: degrade its labels and build its world-frame cloud.

    It holds the label and confidence random streams, so frames must pass through one finisher in
    the order they were captured. It touches no PyBullet state: it may run on another thread or in
    another process (the sim service finishes frames in a worker process while the next renders).
    """

    def __init__(self, config: SimConfig, colour_lut: np.ndarray, member: int = 0):
        labels_ss, conf_ss, _, bleed_ss, _ = _seed_sequences(config.seed, member)
        self.stride = config.camera.stride
        # the wet garden's water joins Table 2's confusions (degrade.py WET_CONFUSABLE)
        wet = _wet(config)
        ids = WET_IDS if wet else GARDEN_IDS
        # the paper's levels redraw from Table 2 as they always have; "realistic" from
        # [sim.perception]'s matrix, split by its persistent share (perception.py)
        perception = config.perception
        matrix = persistent = None
        if config.noise == "realistic":
            matrix = perception_matrix(perception, ids, wet)
            if perception.persistent_share > 0:
                persistent, matrix = split_matrix(matrix, perception.persistent_share)
        self.degrader = LabelDegrader(
            config.noise,
            np.random.default_rng(labels_ss),
            colour_lut,
            region_px=config.slic_region_px,
            iterations=config.slic_iterations,
            ids=ids,
            confusable=WET_CONFUSABLE if wet else GARDEN_CONFUSABLE,
            matrix=matrix,
        )
        self._conf_rng = np.random.default_rng(conf_ss)
        self.noise: LabelNoise | None = None
        if persistent is not None or (matrix is not None and perception.bleed_px > 0):
            self.noise = LabelNoise(
                perception,
                persistent,
                ids,
                self.degrader.size,
                _persistent_key(config.seed),
                np.random.default_rng(bleed_ss),
            )

    def finish(
        self, pending: PendingFrame, stride: int | None = None, timings: dict | None = None
    ) -> CameraFrame:
        stride = self.stride if stride is None else int(stride)
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        cap = pending.capture
        sem = self.degrader.degrade(cap.labels, timings).labels
        if self.noise is not None:
            sem = self.noise.apply(sem, cap.labels, lambda: _world_xy(cap), timings)
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


def _world_xy(cap: CameraCapture) -> np.ndarray:
    """The true world x, y of every pixel with a point, row-major (f4[N, 2])."""
    rows, cols = np.nonzero(cap.labels >= 0)
    pts = cap.points_sensor(rows, cols)
    m = cap.world_from_sensor
    r = np.asarray(m[:2, :3], np.float32)
    return np.einsum("ij,kj->ik", pts, r) + np.asarray(m[:2, 3], np.float32)


class FleetFinisher:
    """Finishes each member's frames with that member's `FrameFinisher` (`PendingFrame.member`):
    what a camera worker thread is handed (finishing.py)."""

    def __init__(self, finishers: list[FrameFinisher]):
        self.finishers = finishers

    def finish(
        self, pending: PendingFrame, stride: int | None = None, timings: dict | None = None
    ) -> CameraFrame:
        return self.finishers[pending.member].finish(pending, stride, timings)


class Member:
    """One robot of the simulation: its body, its random streams and its sensors' counters."""

    def __init__(
        self,
        name: str,
        index: int,
        robot: DiffDriveRobot,
        finisher: FrameFinisher,
        pose_noise: PoseNoise,
    ):
        self.name = name
        self.index = index
        self.robot = robot
        self.finisher = finisher
        self.pose_noise = pose_noise
        self.lidar: Lidar | None = None  # built when first asked for (one per body)
        self.safety: Lidar | None = None  # the safety scanner, likewise
        self.safety_seq = 0
        # one sequence for camera and LiDAR clouds, so that a MapDelta's cloud_seq names one
        self.cloud_seq = 0
        self.camera_frames = 0
        self.lidar_scans = 0
        self.member_px = 0  # camera pixels on other members, over all frames (dropped)
        self.member_hits = 0  # LiDAR hits on other members, over all scans (dropped)


def place_members(
    world: World,
    first_xy: tuple[float, float],
    count: int,
    spacing_m: float,
    clearance_m: float,
) -> list[tuple[float, float]]:
    """`count` spots on free ground: `first_xy`, then, one by one, the free cell nearest to it
    (ties broken by bearing, so the result is deterministic) that is at least `spacing_m` from
    every spot taken. Free: the world's traversability with `clearance_m`, in the component of
    `first_xy` (so every member can reach every other through passages with that clearance; when
    `first_xy` itself has less, the component of the free cell nearest to it). ValueError when
    they do not fit."""
    from scipy import ndimage  # a fleet's only: a single robot's sim starts without scipy

    trav = world.traversability(clearance_m)
    xs, ys = trav.cell_centres()
    comps, _ = ndimage.label(trav.data)
    here = comps[trav.index_of(*first_xy)]
    if not here and trav.data.any():
        ii, jj = np.nonzero(trav.data)
        k = np.argmin(np.hypot(xs[ii] - first_xy[0], ys[jj] - first_xy[1]))
        here = comps[ii[k], jj[k]]
    if not here:
        raise ValueError(f"no free ground with {clearance_m:g} m clearance in world {world.name!r}")
    free = comps == here
    ii, jj = np.nonzero(free)
    px, py = xs[ii], ys[jj]
    dx, dy = px - first_xy[0], py - first_xy[1]
    order = np.lexsort((np.round(np.arctan2(dy, dx), 9), np.round(np.hypot(dx, dy), 9)))
    px, py = px[order], py[order]
    spots = [(float(first_xy[0]), float(first_xy[1]))]
    ok = np.ones(len(px), bool)
    while len(spots) < count:
        x, y = spots[-1]
        ok &= np.hypot(px - x, py - y) >= spacing_m - 1e-9
        k = np.flatnonzero(ok)
        if not len(k):
            raise ValueError(
                f"cannot place {count} robots {spacing_m:g} m apart on free ground around "
                f"({first_xy[0]:.2f}, {first_xy[1]:.2f}) in world {world.name!r}: only "
                f"{len(spots)} fit (set fleet.start_poses, fewer robots or a larger world)"
            )
        spots.append((float(px[k[0]]), float(py[k[0]])))
    return spots


class Simulation:
    """A garden world with a robot, or a fleet of robots, in it (module docstring)."""

    def __init__(
        self,
        config: SimConfig | None = None,
        *,
        classes: ClassTable | None = None,
        world: World | None = None,
        robots: Sequence[str] | None = None,
        fleet: FleetConfig | None = None,
    ):
        """`robots`: the members' names, in order (default: `fleet.robots`, or one robot);
        `fleet`: where the members start (`start_poses`, else `spawn_spacing_m` apart around
        where a single robot would spawn)."""
        self.config = cfg = config or SimConfig()
        fleet = fleet or FleetConfig()
        names = list(robots if robots is not None else fleet.robots or ["robot"])
        if not names or len(set(names)) != len(names):
            raise ValueError(f"robots: need distinct names, got {names!r}")
        classes = classes or (world.classes if world else ClassTable.load("garden3drms"))
        self.world = world or build_world(cfg, classes)
        self.scene = BulletScene(self.world)
        self.dt_physics = 1.0 / cfg.physics_hz
        p.setTimeStep(self.dt_physics, physicsClientId=self.scene.client)
        self.members: list[Member] = []
        for i, (x, y, yaw) in enumerate(self._start_poses(len(names), fleet)):
            z = float(self.world.ground.height_at(x, y))
            robot = DiffDriveRobot(self.scene.client, cfg.robot, xy=(x, y), ground_z=z, yaw=yaw)
            # a fleet's members see each other (depth) but map none of them
            self.scene.register(robot.body, MEMBER if len(names) > 1 else DROP)
            streams = _seed_sequences(cfg.seed, i)
            noise = PoseNoise(
                cfg.pose_noise_xy_m,
                cfg.pose_noise_yaw_rad,
                np.random.default_rng(streams[2]),
                cfg.pose_drift_xy_m_per_sqrt_s,
                cfg.pose_drift_yaw_rad_per_sqrt_s,
                np.random.default_rng(streams[4]),
            )
            finisher = FrameFinisher(cfg, self.world.classes.colour_lut, i)
            self.members.append(Member(names[i], i, robot, finisher, noise))
        self._by_name = {m.name: m for m in self.members}
        self._bodies = np.array([m.robot.body for m in self.members], np.int64)
        # the single robot's names, kept for every caller that knows one robot
        m0 = self.members[0]
        self.robot, self.finisher, self.pose_noise = m0.robot, m0.finisher, m0.pose_noise
        self.degrader = self.finisher.degrader
        self.frame_finisher = FleetFinisher([m.finisher for m in self.members])
        self._camera: SemanticCamera | None = None
        # robot-robot contacts, per pair "a-b" in member order
        self._pairs = [
            (a, b, f"{a.name}-{b.name}")
            for k, a in enumerate(self.members)
            for b in self.members[k + 1 :]
        ]
        self._touching = {key: False for *_, key in self._pairs}
        self._contacts = {key: 0 for *_, key in self._pairs}
        self._min_sep = {key: math.inf for *_, key in self._pairs}
        self.contact_events: list[tuple[float, str]] = []  # (time, pair) of each new episode
        self.time_s = 0.0
        # let the robots settle on their wheels before anyone looks
        self.step(0.5)
        self.time_s = 0.0

    def _start_poses(self, n: int, fleet: FleetConfig) -> list[tuple[float, float, float]]:
        cfg = self.config
        if n > 1 and fleet.start_poses:
            if len(fleet.start_poses) != n:
                raise ValueError(
                    f"fleet.start_poses: one [x, y, yaw] per member ({n}), "
                    f"got {len(fleet.start_poses)}"
                )
            return [(float(x), float(y), float(yaw)) for x, y, yaw in fleet.start_poses]
        clearance = spawn_clearance_m(cfg)
        if cfg.spawn:
            x, y, yaw = (float(v) for v in cfg.spawn)
        else:
            x, y, _ = self.world.spawn_pose(clearance)
            yaw = 0.0
        if n == 1:
            return [(x, y, yaw)]
        # two bodies closer than twice their radius could start inside each other
        spacing = max(fleet.spawn_spacing_m, 2 * cfg.robot.radius_m + 0.05)
        room = max(clearance, fleet.member_clearance_m)
        return [(sx, sy, yaw) for sx, sy in place_members(self.world, (x, y), n, spacing, room)]

    def member(self, which: int | str = 0) -> Member:
        """A member by index or name."""
        if isinstance(which, str):
            try:
                return self._by_name[which]
            except KeyError:
                raise ValueError(f"no robot {which!r} in {list(self._by_name)}") from None
        return self.members[which]

    @property
    def robots(self) -> list[str]:
        return [m.name for m in self.members]

    # -- the single robot's counters (member 0) ------------------------------------------------

    @property
    def cloud_seq(self) -> int:
        return self.members[0].cloud_seq

    @cloud_seq.setter
    def cloud_seq(self, value: int) -> None:
        self.members[0].cloud_seq = value

    @property
    def camera_frames(self) -> int:
        return self.members[0].camera_frames

    @property
    def lidar_scans(self) -> int:
        return self.members[0].lidar_scans

    # -- time and motion ----------------------------------------------------------------------

    def step(self, dt_s: float) -> int:
        """Advance simulated time by about `dt_s` (whole physics steps); returns the step count."""
        if not dt_s >= 0 or not math.isfinite(dt_s):
            raise ValueError(f"dt_s must be finite and >= 0, got {dt_s}")
        n = int(round(dt_s / self.dt_physics))
        c = self.scene.client
        for _ in range(n):
            for m in self.members:
                m.robot.update(self.time_s, self.dt_physics)
            p.stepSimulation(physicsClientId=c)
            self.time_s += self.dt_physics
            if self._pairs:
                self._watch_pairs()
        return n

    def _watch_pairs(self) -> None:
        """After each physics step: a pair that starts touching is one more contact episode."""
        c = self.scene.client
        xy = {
            m.name: p.getBasePositionAndOrientation(m.robot.body, physicsClientId=c)[0][:2]
            for m in self.members
        }
        for a, b, key in self._pairs:
            touching = bool(p.getContactPoints(a.robot.body, b.robot.body, physicsClientId=c))
            if touching and not self._touching[key]:
                self._contacts[key] += 1
                self.contact_events.append((self.time_s, key))
            self._touching[key] = touching
            (ax, ay), (bx, by) = xy[a.name], xy[b.name]
            d = math.hypot(ax - bx, ay - by)
            if d < self._min_sep[key]:
                self._min_sep[key] = d

    def robot_contacts(self) -> dict[str, int]:
        """Contact episodes per pair of members ("a-b", member order) since the start."""
        return dict(self._contacts)

    def min_separation_m(self) -> dict[str, float]:
        """The smallest distance between two members' base centres (x, y) seen per pair."""
        return dict(self._min_sep)

    def take_contact_events(self) -> list[tuple[float, str]]:
        """The (time, pair) of the contact episodes begun since the last call."""
        events, self.contact_events = self.contact_events, []
        return events

    def set_velocity(self, linear_mps: float, angular_radps: float, member: int | str = 0) -> None:
        """Command the base (clamped to the limits); it stops `cmd_timeout_s` after the last."""
        self.member(member).robot.command(linear_mps, angular_radps, self.time_s)

    def true_pose(self, member: int | str = 0) -> np.ndarray:
        """4x4 world-from-base pose (ground truth)."""
        return self.member(member).robot.matrix()

    def published_pose(self, member: int | str = 0) -> np.ndarray:
        """The pose as localisation would give it: the truth with fresh pose noise."""
        m = self.member(member)
        return m.pose_noise.apply(m.robot.matrix(), self.time_s)

    # -- sensors ------------------------------------------------------------------------------

    @property
    def camera(self) -> SemanticCamera:
        if self._camera is None:
            self._camera = SemanticCamera(self.scene, self.config.camera)
        return self._camera

    def lidar_of(self, member: int | str = 0) -> Lidar:
        m = self.member(member)
        if m.lidar is None:  # builds ~131k rays' lists: only when asked for
            m.lidar = Lidar(self.scene, self.config.lidar, parent_body=m.robot.body)
        return m.lidar

    @property
    def lidar(self) -> Lidar:
        return self.lidar_of(0)

    def _others(self, m: Member) -> np.ndarray:
        return self._bodies[self._bodies != m.robot.body]

    def camera_frame(
        self, stride: int | None = None, timings: dict | None = None, member: int | str = 0
    ) -> CameraFrame:
        """Render, label, degrade and unproject one camera frame (see CameraFrame). With
        `timings`, the time of each stage goes in it (ms): render, label, slic, redraw, cloud."""
        return self.finish_camera(self.capture_camera(timings, member), stride, timings)

    def capture_camera(self, timings: dict | None = None, member: int | str = 0) -> PendingFrame:
        """The first half of `camera_frame`: render and label at the current time (PyBullet, so
        on the thread that owns the simulation)."""
        m = self.member(member)
        base_true = m.robot.matrix()
        base_pub = m.pose_noise.apply(base_true, self.time_s)
        mount = self.config.camera.mount_matrix()
        others = self._others(m) if len(self.members) > 1 else None
        cap = self.camera.capture(base_true @ mount, timings, count_bodies=others)
        m.member_px += cap.member_px
        m.cloud_seq += 1
        m.camera_frames += 1
        return PendingFrame(self.time_s, m.cloud_seq, cap, base_pub @ mount, m.index)

    def finish_camera(
        self, pending: PendingFrame, stride: int | None = None, timings: dict | None = None
    ) -> CameraFrame:
        """The second half: degrade the labels and build the world-frame cloud (`FrameFinisher`
        of the frame's member). Each member's frames must be finished in the order they were
        captured."""
        return self.frame_finisher.finish(pending, stride, timings)

    def lidar_scan(self, timings: dict | None = None, member: int | str = 0) -> LidarScan:
        """Cast one LiDAR scan; labels are the hit bodies' true classes (confidence 1)."""
        m = self.member(member)
        base_true = m.robot.matrix()
        base_pub = m.pose_noise.apply(base_true, self.time_s)
        lidar = self.lidar_of(m.index)
        others = self._others(m) if len(self.members) > 1 else None
        hits = lidar.scan(base_true, timings, count_bodies=others)
        labels = hits.labels
        noise = m.finisher.noise
        if noise is not None and noise.persistent is not None:
            # the places the camera gets wrong for good, the LiDAR's labels get wrong too
            xy = transform_points(hits.points_sensor, hits.world_from_sensor)[:, :2]
            labels = noise.persistent.labels(labels, xy)
        world_from_sensor = base_pub @ self.config.lidar.mount_matrix()
        m.cloud_seq += 1
        m.lidar_scans += 1
        m.member_hits += hits.member_hits
        return LidarScan(
            stamp_s=self.time_s,
            seq=m.cloud_seq,
            points=transform_points(hits.points_sensor, world_from_sensor),
            labels=labels.astype(np.uint16),
            confidences=np.ones(len(hits.labels), "f4"),
            world_from_sensor=world_from_sensor,
            true_world_from_sensor=hits.world_from_sensor,
            member_hits=hits.member_hits,
        )

    def safety_scan(self, member: int | str = 0) -> SemanticCloud:
        """One scan of the member's safety scanner (`[sim.safety_scan]`, lidar.safety_cloud)."""
        m = self.member(member)
        if m.safety is None:
            m.safety = Lidar(self.scene, self.config.safety_scan, parent_body=m.robot.body)
        m.safety_seq += 1
        return safety_cloud(m.safety, m.robot.matrix(), self.time_s, m.safety_seq)

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        self.scene.close()

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
