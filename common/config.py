"""Typed configuration: one TOML file, one section per service, validated at load.

    [general]   robot name, class table, run directory, status period
    [zenoh]     how every process reaches the others (see common/zenoh_config.py)
    [deploy]    what `smana up` starts and how it restarts it
    [sim] [mapper] [navgraph] [planner] [explorer] [replay]

Every key is checked: an unknown key, a value of the wrong type or out of range is a `ConfigError`
that names it (`mapper.resolution_m: expected a number > 0, got -1`). Command-line overrides use
the same dotted names (`--set mapper.resolution_m=0.3`). The config actually used is written into
the run directory as `config.toml`, so a run can be repeated exactly.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

Backend = Literal["octree-max", "octree-bayes", "tsdf"]
NoiseLevel = Literal["none", "low", "medium", "high"]
RestartPolicy = Literal["never", "on-failure", "always"]


class ConfigError(ValueError):
    """A config file, key or value that cannot be used. The message names the key."""


def _pos(**kw):
    """A field whose value must be > 0."""
    return field(metadata={"min_exclusive": 0.0}, **kw)


def _nonneg(**kw):
    return field(metadata={"min": 0.0}, **kw)


@dataclass
class GeneralConfig:
    robot: str = "r1"
    class_table: str = "garden3drms"  # bundled name or path to a TOML class table
    run_dir: str = ""  # empty: runs/<timestamp> for `smana up`; no files for a lone service
    status_period_s: float = _pos(default=1.0)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    # Plausibility of inputs (common/plausibility.py): a stamp more than stamp_window_s behind
    # its stream's clock, or ahead of where that clock can be (max_time_rate seconds of stream
    # time per wall second: a simulator's real-time factor, a lockstep replay), is refused; so is
    # a pose further from the last one than max_speed_mps allows, plus pose_slack_m of noise.
    stamp_window_s: float = _pos(default=5.0)
    max_time_rate: float = _pos(default=100.0)
    max_speed_mps: float = _pos(default=3.0)
    pose_slack_m: float = _nonneg(default=1.0)

    def validate(self) -> None:
        from smana.common.keys import check_robot

        try:
            check_robot(self.robot)
        except ValueError as exc:
            raise ConfigError(f"general.robot: {exc}") from None


@dataclass
class ZenohConfig:
    # The embedded default: every process is a client of the supervisor's router on loopback.
    mode: Literal["peer", "client", "router"] = "client"
    connect: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    gossip: bool = False
    config_file: str = ""  # a zenoh JSON5 config applied first; the keys above override it
    # Security, all from zenoh's own features (`smana deploy init-certs` makes the files):
    tls_ca: str = ""  # CA certificate that every tls/ link is checked against
    tls_cert: str = ""  # this host's certificate and key, for listening and connecting (mTLS)
    tls_key: str = ""
    mtls: bool = True  # a listener also demands a certificate signed by the CA
    user: str = ""  # user/password authentication: this session's user name...
    credentials_file: str = ""  # ...whose password is its `user:password` line in this file
    # (a file of one line also names the user); a router accepts every user of the file
    acl_file: str = ""  # a router's access-control policy (JSON5 `access_control` block)


@dataclass
class ServiceDeployConfig:
    """How the supervisor runs one service (dora's vocabulary)."""

    enabled: bool = True
    restart: RestartPolicy = "on-failure"
    # The first restart waits restart_delay_s, each further one in restart_window_s twice as
    # long, up to restart_max_delay_s. Past max_restarts in the window the service is in a crash
    # loop: it is still restarted (every restart_max_delay_s) and the run is reported failed.
    restart_delay_s: float = _nonneg(default=0.1)
    restart_max_delay_s: float = _nonneg(default=10.0)
    max_restarts: int = _nonneg(default=5)
    restart_window_s: float = _pos(default=60.0)
    # A hot spare: once the service is ready, a second process imports and prepares (kernels, a
    # simulated world) and waits; a crashed service is taken over by it in a fraction of a second
    # instead of seconds of start-up. Costs that process's memory (~160-180 MB) while it waits.
    standby: bool = False
    args: list[str] = field(default_factory=list)  # extra command-line arguments


@dataclass
class DeployConfig:
    profile: str = "local"  # set by `smana up --profile NAME` (deploy/profiles/NAME.toml)
    # The supervisor's router. Local services connect to the FIRST listen endpoint; further ones
    # (e.g. tls/0.0.0.0:7448 on a base station) are for other hosts' routers.
    router_listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    router_connect: list[str] = field(default_factory=list)  # other routers (robot -> base)
    robots: list[str] = field(default_factory=list)  # multi-robot: one instance per robot name
    # Health: a service shows its `starting` token within health_timeout_s of its start (or it is
    # killed and restarted), then its `alive` token within startup_timeout_s (loading a map,
    # compiling numba kernels on a cold cache: minutes on a loaded 2-core machine).
    health_timeout_s: float = _pos(default=30.0)
    startup_timeout_s: float = _pos(default=600.0)
    # A service with `standby` gets its hot spare once it has been ready this long: a short run
    # (a test, a quick experiment) never pays for spares, and the spares' imports never compete
    # with the stack's own start-up on a 2-core machine.
    standby_delay_s: float = _nonneg(default=20.0)
    stop_timeout_s: float = _pos(default=5.0)
    finish_with: str = "explorer"  # the run ends when this service exits with status 0
    sim: ServiceDeployConfig = field(default_factory=lambda: ServiceDeployConfig(standby=True))
    mapper: ServiceDeployConfig = field(default_factory=lambda: ServiceDeployConfig(standby=True))
    navgraph: ServiceDeployConfig = field(default_factory=lambda: ServiceDeployConfig(standby=True))
    planner: ServiceDeployConfig = field(default_factory=lambda: ServiceDeployConfig(standby=True))
    explorer: ServiceDeployConfig = field(default_factory=lambda: ServiceDeployConfig(standby=True))
    recorder: ServiceDeployConfig = field(default_factory=ServiceDeployConfig)  # Rerun .rrd


@dataclass
class SimConfig:
    """`smana sim`: the PyBullet simulator (services/sim, its docstrings say more)."""

    world: str = "garden"  # "garden" (procedural), or a labelled PLY: "ply:PATH" or a path
    seed: int = 3  # world layout; noise streams derive from it too
    size_m: float = _pos(default=12.0)  # side of the procedural garden
    ground_resolution_m: float = _pos(default=0.1)  # height field / ground class raster cell
    voxel_m: float = _pos(default=0.05)  # object voxels of a world built from a PLY
    # label noise: "off" = true labels, confidence 1; "none".."high" = paper 4.2.1 (SLIC,
    # confusion redraw with p = 1.0 / 0.9 / 0.8 / 0.7, confidence uniform in [0.33, 1])
    noise: Literal["off", "none", "low", "medium", "high"] = "none"
    slic_region_px: int = _pos(default=20)
    slic_iterations: int = _pos(default=3)
    pose_noise_xy_m: float = _nonneg(default=0.0)  # std dev of the published x and of y
    pose_noise_yaw_rad: float = _nonneg(default=0.0)  # std dev of the published yaw
    camera_enabled: bool = True
    camera_width: int = _pos(default=640)
    camera_height: int = _pos(default=640)
    camera_fov_deg: float = _pos(default=57.0)
    camera_rate_hz: float = _pos(default=2.0)  # simulated time
    camera_max_range_m: float = _pos(default=8.0)
    camera_stride: int = _pos(default=1)  # keep every n-th pixel row and column in the cloud
    publish_images: bool = False  # robot/image/{rgb,depth,semantic} with each camera frame
    # where frames are degraded and encoded while the next renders: "thread", "process" or "off"
    # (in line); measured in services/sim/finishing.py. Lockstep always finishes in line.
    camera_worker: Literal["process", "thread", "off"] = "thread"
    lidar_enabled: bool = False
    lidar_rate_hz: float = _pos(default=10.0)
    lidar_channels: int = _pos(default=64)  # Ouster OS1-64: 64 x 2048, 33.2 deg vertical
    lidar_columns: int = _pos(default=2048)
    lidar_vfov_deg: float = _pos(default=33.2)
    lidar_max_range_m: float = _pos(default=20.0)
    lidar_min_range_m: float = _nonneg(default=0.3)
    pose_rate_hz: float = _pos(default=20.0)
    clock_rate_hz: float = _pos(default=10.0)
    physics_hz: float = _pos(default=240.0)
    real_time_factor: float = _pos(default=1.0)  # also the upper bound in lockstep
    # lockstep: after each camera cloud, wait for the mapper's MapDelta with that cloud_seq
    # (at most lockstep_timeout_s of wall time) before simulating on
    lockstep: bool = False
    lockstep_timeout_s: float = _pos(default=5.0)
    cmd_timeout_s: float = _pos(default=0.5)  # the base stops when commands stop this long
    max_linear_mps: float = _pos(default=1.0)
    max_angular_radps: float = _pos(default=2.0)
    spawn: list[float] = field(default_factory=list)  # [x, y, yaw]; empty: free spot near centre

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


@dataclass
class MapperConfig:
    backend: Backend = "octree-max"
    resolution_m: float = _pos(default=0.1)
    max_range_m: float = _pos(default=10.0)
    raycast_range_m: float = _nonneg(default=1.0)  # free space carved before a hit; 0 = whole ray
    inputs: list[str] = field(default_factory=lambda: ["cloud"])  # "cloud" and/or "scan"
    autosave_period_s: float = _nonneg(default=30.0)  # 0 = only on shutdown
    load: str = ""  # resume from this map file; "auto" = save_path when it exists
    save_path: str = ""  # "" = <run_dir>/map.npz (no autosave without a run dir)
    # OctoMap sensor model (its defaults) and Semantic Octomap fusion constants
    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    max_same_gain: float = 0.5  # same label: c += gain * c_obs * (1 - c)
    max_disagree_factor: float = 0.9  # other label: the winner's confidence times this
    # TSDF (voxblox fast integrator, Kimera semantics)
    tsdf_truncation_voxels: float = _pos(default=2.0)
    tsdf_label_probability: float = 0.9
    tsdf_max_weight: float = _pos(default=10000.0)

    def validate(self) -> None:
        for name in self.inputs:
            if name not in ("cloud", "scan"):
                raise ConfigError(f"mapper.inputs: 'cloud' and/or 'scan', got {name!r}")
        if not self.inputs:
            raise ConfigError("mapper.inputs: at least one of 'cloud', 'scan'")
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "tsdf_label_probability"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ConfigError(f"mapper.{name}: expected 0 < p < 1, got {getattr(self, name)}")
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise ConfigError("mapper.prob_miss / prob_hit: need prob_miss < 0.5 < prob_hit")
        if not self.clamp_min < 0.5 < self.clamp_max:
            raise ConfigError("mapper.clamp_min / clamp_max: need clamp_min < 0.5 < clamp_max")
        if not 0.0 <= self.max_same_gain <= 1.0:
            raise ConfigError(f"mapper.max_same_gain: expected 0..1, got {self.max_same_gain}")
        if not 0.0 < self.max_disagree_factor <= 1.0:
            raise ConfigError(
                f"mapper.max_disagree_factor: expected (0, 1], got {self.max_disagree_factor}"
            )


@dataclass
class NavgraphConfig:
    resolution_m: float = _pos(default=0.2)
    bounds_min_xy: list[float] = field(default_factory=lambda: [-50.0, -50.0])
    bounds_max_xy: list[float] = field(default_factory=lambda: [50.0, 50.0])
    robot_radius_m: float = _nonneg(default=0.4)
    tile_size: int = _pos(default=32)  # nodes per tile side; memory is allocated per tile
    # Occupied voxels remembered per node column (to recompute the node when the top one is
    # cleared); a 1.7 m person over ground at 0.1 m / 0.2 m fills ~70. Beyond it the lowest
    # levels are forgotten and a column cleared down to them becomes unknown.
    column_capacity: int = _pos(default=256)

    def validate(self) -> None:
        for name in ("bounds_min_xy", "bounds_max_xy"):
            if len(getattr(self, name)) != 2:
                raise ConfigError(f"navgraph.{name}: expected [x, y], got {getattr(self, name)}")
        if not all(a < b for a, b in zip(self.bounds_min_xy, self.bounds_max_xy, strict=True)):
            raise ConfigError("navgraph.bounds_max_xy: must exceed bounds_min_xy on both axes")
        if not 1 <= self.tile_size <= 256:
            raise ConfigError(f"navgraph.tile_size: 1..256, got {self.tile_size}")
        if not 1 <= self.column_capacity <= 4096:
            raise ConfigError(f"navgraph.column_capacity: 1..4096, got {self.column_capacity}")


@dataclass
class PlannerConfig:
    h_f: float = _nonneg(default=0.1)
    t_f: float = _nonneg(default=0.8)
    max_step_m: float = _pos(default=0.3)
    unknown_cost: float = _nonneg(default=2.0)  # T(l) of unknown nodes when a request allows them
    # Both are exact (admissible and consistent). "euclidean" is the paper's d(n, g); "octile"
    # (octile distance + cheapest enter cost per step) expands 3-5x fewer nodes.
    heuristic: Literal["octile", "euclidean"] = "octile"
    graph_sync_timeout_s: float = _pos(default=5.0)  # asking navgraph for the graph at start


@dataclass
class ExplorerConfig:
    time_budget_s: float = _pos(default=480.0)  # robot (pose stamp) time, and wall time as well
    # The budget starts with the first pose once a map and a planner are there; past the budget
    # plus this, with neither, the explorer gives up (ends `no_graph` or `no_planner`).
    startup_grace_s: float = _nonneg(default=120.0)
    enabled: bool = True
    control_rate_hz: float = _pos(default=10.0)
    # next-best-view scoring (services/explorer/frontier.py)
    fov_deg: float = _pos(default=57.0)  # the camera's horizontal field of view
    view_range_m: float = _pos(default=4.0)  # how far a view is assumed to map the ground
    view_min_range_m: float = _nonneg(default=0.3)
    n_yaw: int = _pos(default=16)
    occlusion: bool = True  # obstacle nodes hide what is behind them
    candidate_spacing_m: float = _pos(default=0.6)
    min_gain_m2: float = _nonneg(default=0.4)  # a view seeing less unknown area is not worth it
    path_cost_weight: float = _nonneg(default=0.05)  # m^2 of view gain per unit of A* path cost
    max_queries: int = _pos(default=10)  # path queries per plan (branch and bound cap)
    replan_period_s: float = _pos(default=3.0)
    switch_margin_m2: float = _nonneg(default=1.0)
    stuck_timeout_s: float = _pos(default=8.0)
    done_after_empty: int = _pos(default=3)
    # traversability cost overrides sent with every path request, "grass=4" or "1=4"
    class_costs: list[str] = field(default_factory=list)
    planner_timeout_s: float = _pos(default=2.0)
    # pure pursuit (services/explorer/follower.py)
    lookahead_m: float = _pos(default=0.4)
    max_linear_mps: float = _pos(default=0.4)
    max_angular_radps: float = _pos(default=1.0)
    goal_tolerance_m: float = _pos(default=0.2)
    pose_timeout_s: float = _pos(default=1.0)  # no pose for this long: stop the robot


@dataclass
class ReplayConfig:
    """`smana replay DATASET`: publish a recorded dataset on the robot's keys instead of the sim."""

    dataset: str = ""  # path; `smana replay DATASET` sets it
    format: str = ""  # semantickitti, rellis3d, rosbag or folder; "" = detect from the layout
    sequence: str = ""  # SemanticKITTI / RELLIS-3D root holding several sequences: which one
    class_table: str = ""  # "" = the dataset's own table (rellis3d, semantickitti, ...)
    mode: Literal["lockstep", "realtime"] = "lockstep"  # lockstep: wait for each scan's MapDelta
    rate_factor: float = _pos(default=1.0)  # realtime: x N the recorded rate
    topic: Literal["auto", "scan", "cloud"] = "auto"  # auto: LiDAR -> robot/scan, camera -> cloud
    max_range_m: float = _pos(default=10.0)  # points farther from the sensor are not published
    min_range_m: float = _nonneg(default=0.5)  # nor closer ones (the robot itself, no-returns)
    start: int = _nonneg(default=0)  # first scan replayed
    count: int = _nonneg(default=0)  # scans replayed; 0 = to the end
    wait_for: list[str] = field(default_factory=lambda: ["mapper"])  # alive before the 1st scan
    wait_timeout_s: float = _pos(default=60.0)
    ack_timeout_s: float = _pos(default=30.0)  # lockstep: resend a scan after this long
    label_field: str = "label"  # bags / PLY: the integer label field
    cloud_topic: str = ""  # bags: the PointCloud2 topic ("" = the only one)
    odom_topic: str = ""  # bags: the nav_msgs/Odometry topic ("" = the only one)
    fixed_pose: list[float] = field(default_factory=list)  # bags without odometry: x, y, z, yaw


@dataclass
class SmanaConfig:
    general: GeneralConfig = field(default_factory=GeneralConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    deploy: DeployConfig = field(default_factory=DeployConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    navgraph: NavgraphConfig = field(default_factory=NavgraphConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    explorer: ExplorerConfig = field(default_factory=ExplorerConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        overrides: list[str] | None = None,
        layers: list[str | Path] = (),
    ):
        """Defaults, then `layers` (e.g. a deployment profile), then the TOML file (if any), then
        `section.key=value` overrides. Later values win, table by table."""
        data: dict[str, Any] = {}
        for p in [*layers, *([path] if path else [])]:
            _merge(data, _read_toml(Path(p)))
        for item in overrides or []:
            _apply_override(data, item)
        return build(cls, data, "")

    def to_toml(self) -> str:
        return to_toml(self)

    def write(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_toml())
        return p


# -- building and validating -------------------------------------------------------------------


def _read_toml(p: Path) -> dict:
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def _merge(into: dict, new: dict) -> None:
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v


def _apply_override(data: dict, item: str) -> None:
    if "=" not in item:
        raise ConfigError(f"override {item!r} must look like section.key=value")
    dotted, raw = item.split("=", 1)
    parts = dotted.strip().split(".")
    if len(parts) < 2 or not all(parts):
        raise ConfigError(f"override {item!r}: key must be section.key")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()  # a bare word is a string: --set mapper.backend=tsdf
    node = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"override {item!r}: {part} is not a section")
    node[parts[-1]] = value


def build(cls, data: dict, where: str, base=None):
    """Make a `cls` dataclass from a dict, checking every key and value. Keys the dict leaves out
    keep their value in `base` (a section's own default, e.g. `deploy.mapper.standby = true`)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where or 'config'}: expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        known = ", ".join(sorted(fields))
        name = ", ".join(f"{where}{k}" for k in sorted(unknown))
        raise ConfigError(f"unknown key {name} (known in [{where.rstrip('.') or 'top'}]: {known})")
    if base is None:
        base = cls()
    kwargs = {}
    for name, value in data.items():
        key = f"{where}{name}"
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = build(hint, value, key + ".", getattr(base, name))
        else:
            kwargs[name] = _check_value(key, value, hint, fields[name].metadata)
    obj = dataclasses.replace(base, **kwargs)
    check = getattr(obj, "validate", None)
    if check:
        check()
    return obj


def _check_value(key, v, hint, meta):
    origin = typing.get_origin(hint)
    if origin is Literal:
        choices = typing.get_args(hint)
        if v not in choices:
            raise ConfigError(f"{key}: expected one of {list(choices)}, got {v!r}")
        return v
    if isinstance(hint, types.UnionType):  # X | None: None is spelt by leaving the key out
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
        origin = typing.get_origin(hint)
    if origin is list:
        (item,) = typing.get_args(hint)
        if not isinstance(v, list):
            raise ConfigError(f"{key}: expected a list, got {v!r}")
        return [_check_value(f"{key}[{i}]", x, item, {}) for i, x in enumerate(v)]
    if hint is bool:
        if not isinstance(v, bool):
            raise ConfigError(f"{key}: expected true or false, got {v!r}")
        return v
    if hint in (int, float):
        if isinstance(v, bool) or not isinstance(v, int | float) or (hint is int and v != int(v)):
            what = "an integer" if hint is int else "a number"
            raise ConfigError(f"{key}: expected {what}, got {v!r}")
        v = hint(v)
        if "min_exclusive" in meta and not v > meta["min_exclusive"]:
            raise ConfigError(f"{key}: expected a number > {meta['min_exclusive']:g}, got {v!r}")
        if "min" in meta and not v >= meta["min"]:
            raise ConfigError(f"{key}: expected a number >= {meta['min']:g}, got {v!r}")
        return v
    if hint is str:
        if not isinstance(v, str):
            raise ConfigError(f"{key}: expected a string, got {v!r}")
        return v
    raise ConfigError(f"{key}: unsupported type {hint}")


def to_toml(obj) -> str:
    """Serialise a config dataclass (sections of scalars and lists) as TOML."""
    lines: list[str] = []
    _emit(obj, "", lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _emit(obj, prefix: str, lines: list[str]) -> None:
    scalars, tables = [], []
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        (tables if dataclasses.is_dataclass(v) else scalars).append((f.name, v))
    if prefix and scalars:
        lines.append(f"\n[{prefix}]")
    for name, v in scalars:
        if v is not None:
            lines.append(f"{name} = {_toml_value(v)}")
    for name, v in tables:
        _emit(v, f"{prefix}.{name}" if prefix else name, lines)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {v!r} as TOML")
