"""[sim] config section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config._schema import ConfigError, Section, param


@dataclass
class SimConfig(Section, section="sim"):
    """`smana sim`: the PyBullet simulator (services/sim, its docstrings say more)."""

    world: str = "garden"  # "garden" (procedural), or a labelled PLY: "ply:PATH" or a path
    seed: int = 3  # world layout; noise streams derive from it too
    size_m: float = param(12.0, gt=0)  # side of the procedural garden
    ground_resolution_m: float = param(0.1, gt=0)  # height field / ground class raster cell
    voxel_m: float = param(0.05, gt=0)  # object voxels of a world built from a PLY
    # label noise: "off" = true labels, confidence 1; "none".."high" = paper 4.2.1 (SLIC,
    # confusion redraw with p = 1.0 / 0.9 / 0.8 / 0.7, confidence uniform in [0.33, 1])
    noise: Literal["off", "none", "low", "medium", "high"] = "none"
    slic_region_px: int = param(20, gt=0)
    slic_iterations: int = param(3, gt=0)
    pose_noise_xy_m: float = param(0.0, ge=0)  # std dev of the published x and of y
    pose_noise_yaw_rad: float = param(0.0, ge=0)  # std dev of the published yaw
    camera_enabled: bool = True
    camera_width: int = param(640, gt=0)
    camera_height: int = param(640, gt=0)
    camera_fov_deg: float = param(57.0, gt=0)
    camera_rate_hz: float = param(2.0, gt=0)  # simulated time
    camera_max_range_m: float = param(8.0, gt=0)
    camera_stride: int = param(1, gt=0)  # keep every n-th pixel row and column in the cloud
    publish_images: bool = False  # robot/image/{rgb,depth,semantic} with each camera frame
    # where frames are degraded and encoded while the next renders: "thread", "process" or "off"
    # (in line); measured in services/sim/finishing.py. Lockstep always finishes in line.
    camera_worker: Literal["process", "thread", "off"] = "thread"
    lidar_enabled: bool = False
    lidar_rate_hz: float = param(10.0, gt=0)
    lidar_channels: int = param(64, gt=0)  # Ouster OS1-64: 64 x 2048, 33.2 deg vertical
    lidar_columns: int = param(2048, gt=0)
    lidar_vfov_deg: float = param(33.2, gt=0)
    lidar_max_range_m: float = param(20.0, gt=0)
    lidar_min_range_m: float = param(0.3, ge=0)
    pose_rate_hz: float = param(20.0, gt=0)
    clock_rate_hz: float = param(10.0, gt=0)
    physics_hz: float = param(240.0, gt=0)
    real_time_factor: float = param(1.0, gt=0)  # also the upper bound in lockstep
    # lockstep: after each camera cloud, wait for the mapper's MapDelta with that cloud_seq
    # (at most lockstep_timeout_s of wall time) before simulating on
    lockstep: bool = False
    lockstep_timeout_s: float = param(5.0, gt=0)
    cmd_timeout_s: float = param(0.5, gt=0)  # the base stops when commands stop this long
    max_linear_mps: float = param(1.0, gt=0)
    max_angular_radps: float = param(2.0, gt=0)
    spawn: list[float] = param([])  # [x, y, yaw]; empty: free spot near centre

    def validate(self) -> None:
        if self.spawn and len(self.spawn) != 3:
            raise ConfigError(f"sim.spawn: expected [x, y, yaw] or [], got {self.spawn!r}")
        for name in ("camera_width", "camera_height"):
            if getattr(self, name) > 4096:
                raise ConfigError(f"sim.{name}: at most 4096, got {getattr(self, name)}")
        if not self.camera_fov_deg < 170:
            raise ConfigError(f"sim.camera_fov_deg: below 170, got {self.camera_fov_deg}")
        if self.slic_region_px < 2:
            raise ConfigError(f"sim.slic_region_px: at least 2, got {self.slic_region_px}")
        if self.lidar_min_range_m >= self.lidar_max_range_m:
            raise ConfigError("sim.lidar_min_range_m: must be below sim.lidar_max_range_m")
        if self.physics_hz < 50:
            raise ConfigError(f"sim.physics_hz: at least 50, got {self.physics_hz}")
