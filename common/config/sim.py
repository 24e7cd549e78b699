"""[sim] config section, and its parts: [sim.camera], [sim.lidar], [sim.robot]. Each part is what
its core receives as it is (`SemanticCamera(scene, config.camera)`, `DiffDriveRobot(client,
config.robot)`). A world's own knobs are declared beside the world (`GardenConfig` in
services/sim/worlds/garden.py, `PlyConfig` in worlds/cloud.py, a plugin's in its module) and read
from `[sim.<config_key>]` (`[sim.garden]`, `[sim.ply]`): the world registry lists them, by name
only (`with_variants`), and the world gets them as `config.garden`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from smana.common.config.section import (
    ConfigError,
    Section,
    param,
    table,
    variant_tables,
    with_variants,
)


def _check_xyz(key: str, xyz: list[float]) -> None:
    if len(xyz) != 3:
        raise ConfigError(f"{key}: expected [x, y, z], got {xyz!r}")


@dataclass
class CameraConfig(Section, section="sim.camera"):
    """The semantic RGB-D camera (services/sim/camera.py). The default follows the paper: 640 x
    640 pixels, 57 degree field of view."""

    enabled: bool = True  # camera clouds on robot/cloud
    width: int = param(640, ge=8, le=4096)  # image width, pixels
    height: int = param(640, ge=8, le=4096)  # image height, pixels
    fov_deg: float = param(57.0, ge=1, lt=170)  # vertical (horizontal too when square)
    near_m: float = param(0.05, gt=0)  # nearer depths are not rendered
    max_range_m: float = param(8.0, gt=0)  # farther pixels give no point
    rate_hz: float = param(2.0, gt=0)  # simulated time
    stride: int = param(1, gt=0)  # keep every n-th pixel row and column in the cloud
    # mount on the robot's base frame: position and downward pitch
    mount_xyz: list[float] = param([0.25, 0.0, 0.20])
    mount_pitch_deg: float = 15.0  # downward pitch of the camera
    publish_images: bool = False  # robot/image/{rgb,depth,semantic} with each camera frame
    # where frames are degraded and encoded while the next renders: "thread", "process" or "off"
    # (in line); measured in services/sim/finishing.py. Lockstep always finishes in line.
    worker: Literal["process", "thread", "off"] = "thread"

    def validate(self) -> None:
        _check_xyz("sim.camera.mount_xyz", self.mount_xyz)
        if not self.near_m < self.max_range_m:
            raise ConfigError("sim.camera.near_m: must be below sim.camera.max_range_m")

    @property
    def focal_px(self) -> float:
        return (self.height / 2) / math.tan(math.radians(self.fov_deg) / 2)

    def mount_matrix(self) -> np.ndarray:
        """Sensor pose in the robot's base frame (4x4)."""
        pitch = math.radians(self.mount_pitch_deg)
        c, s = math.cos(pitch), math.sin(pitch)
        m = np.eye(4)
        m[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # x tilts down
        m[:3, 3] = self.mount_xyz
        return m


@dataclass
class LidarConfig(Section, section="sim.lidar"):
    """A spinning LiDAR (services/sim/lidar.py); the default is an Ouster OS1-64: 64 x 2048 rays,
    33.2 deg vertical."""

    enabled: bool = False  # LiDAR scans on robot/scan
    rate_hz: float = param(10.0, gt=0)  # scans per simulated second
    channels: int = param(64, gt=0)  # beams (rows of the scan)
    columns: int = param(2048, gt=0)  # azimuth steps of a turn
    vfov_deg: float = param(33.2, gt=0, lt=180)  # vertical field of view
    max_range_m: float = param(20.0, gt=0)  # farther rays give no return
    min_range_m: float = param(0.3, ge=0)  # nearer returns are dropped
    mount_xyz: list[float] = param([0.0, 0.0, 0.30])  # on the base frame, level

    def validate(self) -> None:
        k = self.section
        _check_xyz(f"{k}.mount_xyz", self.mount_xyz)
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(f"{k}.min_range_m: must be below {k}.max_range_m")
        if self.channels * self.columns > 4_000_000:
            raise ConfigError(f"{k}: channels x columns must be at most 4M rays")

    @property
    def n_rays(self) -> int:
        return self.channels * self.columns

    def directions(self) -> np.ndarray:
        """Unit ray directions (channels * columns, 3) in the sensor frame, channel-major: top
        channel first, azimuth from -pi (behind) counter-clockwise."""
        half = math.radians(self.vfov_deg) / 2
        el = np.linspace(half, -half, self.channels) if self.channels > 1 else np.zeros(1)
        az = -math.pi + np.arange(self.columns) * (2 * math.pi / self.columns)
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(
            -1, 3
        )

    def starts(self) -> np.ndarray:
        """Where each ray starts, m along it (its first possible return)."""
        return np.full(self.n_rays, float(self.min_range_m))

    def mount_matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, 3] = self.mount_xyz
        return m


@dataclass
class SafetyScanConfig(LidarConfig, section="sim.safety_scan"):
    """A safety scanner: a fan of LiDAR beams from the horizon down, all round, short range, just
    above the chassis, as a field robot carries beside its mapping sensors. Its points go out in
    the robot's base frame on robot/safety_scan, unlabelled and untouched by pose noise: the
    explorer's guard (services/explorer/guard.py) stops a motion that would put the robot on
    what they show, where a drifted pose has moved the map's obstacles. A beam below the horizon
    starts where it leaves a cylinder of `body_radius_m` (it would hit the robot's own top);
    one on the horizon starts at `min_range_m`, as nothing of the robot is that high."""

    enabled: bool = True  # scans on robot/safety_scan (the explorer's guard uses them)
    rate_hz: float = param(10.0, gt=0)  # scans per simulated second
    channels: int = param(6, gt=0)  # beams (rows of the scan), from the horizon down
    columns: int = param(360, gt=0)  # azimuth steps of a turn
    vfov_deg: float = param(18.0, gt=0, lt=90)  # the lowest beam points this far down
    max_range_m: float = param(3.0, gt=0)  # farther rays give no return
    min_range_m: float = param(0.0, ge=0)  # nearer returns are dropped
    mount_xyz: list[float] = param([0.0, 0.0, 0.10])  # on the base frame, above the chassis
    body_radius_m: float = param(0.45, ge=0)  # beams below the horizon start outside this

    def directions(self) -> np.ndarray:
        """Unit ray directions, channel-major: the horizon first, then down to -vfov_deg."""
        el = -np.linspace(0.0, math.radians(self.vfov_deg), self.channels)
        az = -math.pi + np.arange(self.columns) * (2 * math.pi / self.columns)
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(
            -1, 3
        )

    def starts(self) -> np.ndarray:
        """Where each ray starts, m along it: outside the body's cylinder when it points down."""
        d = self.directions()
        horizontal = np.hypot(d[:, 0], d[:, 1])
        down = d[:, 2] < -1e-9
        start = np.maximum(self.min_range_m, self.body_radius_m / np.maximum(horizontal, 1e-9))
        return np.where(down, start, self.min_range_m)

    def validate(self) -> None:
        super().validate()
        if self.starts().max() >= self.max_range_m:
            raise ConfigError(
                f"{self.section}.max_range_m: the lowest beam starts at "
                f"{self.starts().max():.2f} m (body_radius_m), beyond max_range_m"
            )


@dataclass
class RobotConfig(Section, section="sim.robot"):
    """The simulated differential-drive base (services/sim/robot.py)."""

    chassis_half_extents: list[float] = param([0.28, 0.17, 0.07], gt=0)  # x, y, z, metres
    chassis_mass_kg: float = param(12.0, gt=0)  # the body without its wheels
    wheel_radius_m: float = param(0.11, gt=0)  # the two driven wheels
    wheel_width_m: float = param(0.05, gt=0)  # of each driven wheel
    track_m: float = param(0.40, gt=0)  # between the wheels' mid-planes
    wheel_mass_kg: float = param(1.0, gt=0)  # of each driven wheel
    caster_radius_m: float = param(0.04, gt=0)  # the passive ball casters
    caster_offset_m: float = param(0.22, ge=0)  # ahead and behind the axle
    max_wheel_torque_nm: float = param(20.0, gt=0)  # the motors' limit
    max_linear_mps: float = param(1.0, gt=0)  # forward speed limit
    max_angular_radps: float = param(2.0, gt=0)  # turn rate limit
    max_linear_accel_mps2: float = param(1.5, gt=0)  # forward acceleration limit
    max_angular_accel_radps2: float = param(4.0, gt=0)  # turn acceleration limit
    cmd_timeout_s: float = param(0.5, gt=0)  # the base stops when commands stop this long
    colour: list[float] = param([0.95, 0.75, 0.1, 1.0], ge=0, le=1)  # RGBA

    def validate(self) -> None:
        _check_xyz("sim.robot.chassis_half_extents", self.chassis_half_extents)
        if len(self.colour) != 4:
            raise ConfigError(f"sim.robot.colour: expected [r, g, b, a], got {self.colour!r}")

    @property
    def radius_m(self) -> float:
        """Circumscribed radius of the footprint (for clearance checks)."""
        hx, hy, _ = self.chassis_half_extents
        half_width = max(hy, self.track_m / 2 + self.wheel_radius_m)  # ball-shaped wheels
        return math.hypot(max(hx, self.caster_offset_m), half_width)

    @property
    def base_height_m(self) -> float:
        """Height of the base frame (chassis centre) above flat ground at rest."""
        return self.wheel_radius_m + self.chassis_half_extents[2] * 0.6


@dataclass
class PerceptionConfig(Section, section="sim.perception"):
    """Label noise as a segmentation network makes it (services/sim/perception.py), used when
    `sim.noise = "realistic"` (the paper's levels ignore this section). The defaults are the
    realistic preset: the confusion matrix of a published network (services/sim/
    confusion_rellis3d.py cites it), half of every class's errors persistent, a 2-pixel bleed."""

    # the confusion rows: "rellis3d" (a published network's, measured), "table2" (the paper's at
    # `accuracy`), "pairs" (grass <-> terrain; hedge, topiary and tree among themselves; water
    # <-> grass in the wet garden, at `accuracy`)
    confusion: Literal["rellis3d", "table2", "pairs"] = "rellis3d"
    accuracy: float = param(0.8, ge=0, le=1)  # p of "table2" and "pairs" ("rellis3d": unused)
    # share of each class's errors that is persistent: the same wrong label from every view, for
    # every point of that class in a cell of the ground plane (the rest is redrawn every frame)
    persistent_share: float = param(0.5, ge=0, le=1)
    cell_m: float = param(0.75, gt=0)  # side of the persistent errors' cells, m
    bleed_px: int = param(2, ge=0, le=16)  # labels spill this far over class edges, pixels


@with_variants("smana.services.sim.worlds:config_sections", "world")
@dataclass(eq=False)
class SimConfig(Section, section="sim"):
    """`smana sim`: the PyBullet simulator (services/sim, its docstrings say more)."""

    # "garden" (procedural), "ply:PATH" or a path to a labelled PLY, a world registered in
    # services/sim/worlds/__init__.py ("NAME" or "NAME:ARG"), or an out-of-tree "module:Class"
    world: str = "garden"
    seed: int = 3  # world layout; noise streams derive from it too
    # label noise: "off" = true labels, confidence 1; "none".."high" = paper 4.2.1 (SLIC,
    # confusion redraw with p = 1.0 / 0.9 / 0.8 / 0.7, confidence uniform in [0.33, 1]);
    # "realistic" = [sim.perception]: a published network's confusions, persistent errors and
    # boundary bleed
    noise: Literal["off", "none", "low", "medium", "high", "realistic"] = "none"
    slic_region_px: int = param(20, ge=2)  # side of a SLIC superpixel (label noise)
    slic_iterations: int = param(3, gt=0)  # SLIC's iterations per frame
    pose_noise_xy_m: float = param(0.0, ge=0)  # std dev of the published x and of y
    pose_noise_yaw_rad: float = param(0.0, ge=0)  # std dev of the published yaw
    # pose drift: a random walk added to the published pose, its std dev after t seconds is
    # this times sqrt(t) (in x and in y; in yaw)
    pose_drift_xy_m_per_sqrt_s: float = param(0.0, ge=0)
    pose_drift_yaw_rad_per_sqrt_s: float = param(0.0, ge=0)  # see pose_drift_xy_m_per_sqrt_s
    pose_rate_hz: float = param(20.0, gt=0)  # robot/pose and robot/pose_truth (sim time)
    clock_rate_hz: float = param(10.0, gt=0)  # robot/clock: simulated time, real-time factor
    physics_hz: float = param(240.0, ge=50)  # PyBullet's steps per simulated second
    real_time_factor: float = param(1.0, gt=0)  # also the upper bound in lockstep
    # lockstep: after each camera cloud, wait for the mapper's MapDelta with that cloud_seq
    # (at most lockstep_timeout_s of wall time) before simulating on
    lockstep: bool = False
    lockstep_timeout_s: float = param(5.0, gt=0)
    spawn: list[float] = param([])  # [x, y, yaw]; empty: free spot near centre
    camera: CameraConfig = table(CameraConfig)
    lidar: LidarConfig = table(LidarConfig)
    safety_scan: SafetyScanConfig = table(SafetyScanConfig)
    robot: RobotConfig = table(RobotConfig)
    perception: PerceptionConfig = table(PerceptionConfig)
    # [sim.garden], [sim.ply], a plugin's: each world's own section
    variants: dict[str, Section] = variant_tables()

    def validate(self) -> None:
        if self.spawn and len(self.spawn) != 3:
            raise ConfigError(f"sim.spawn: expected [x, y, yaw] or [], got {self.spawn!r}")
