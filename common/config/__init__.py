"""Typed configuration: one TOML file, one section per service, validated at load.

    [general]   robot name, class table, run directory, status period      general.py
    [zenoh]     how every process reaches the others (common/zenoh_config)  general.py
    [deploy]    what `smana up` starts and how it restarts it              deploy.py
    [sim] [mapper] [navgraph] [planner] [explorer] [replay] [ros2]          one module each
    [geometric] the labeller of clouds without labels (common/geometric)   geometric.py
    [fleet]     several robots, one map, one graph, coordinated views     fleet.py
    [mapper.<key>] [sim.<key>]  a back-end's or a world's own parameters, declared beside it
                ([mapper.octree], [mapper.tsdf], [sim.garden], [sim.ply], a plugin's)

Each section is defined once, in its module, as a `Section` dataclass (`section.py`): its fields
carry their limits and the one generic validator checks them, on load and when a core is given a
section made in Python. A core receives its section as it is (`Explorer(config.explorer)`); parts
of a core are nested tables (`[explorer.follower]`). A variant's parameters (a mapping back-end's,
a world's) are a `Section` beside the variant's code, attached by its registry's name
(`with_variants`, section.py), for smana's variants and plugins alike.

An unknown key, a value of the wrong type or out of range, or a number that is not finite (`1e400`
reads as inf) is a `ConfigError` that names it (`mapper.resolution_m: expected a number > 0, got
-1`). Command-line overrides use the same dotted
names (`--set mapper.resolution_m=0.3`). The config actually used is written into the run
directory as `config.toml`, so a run can be repeated exactly.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from smana.common.config.deploy import DeployConfig, ServiceDeployConfig
from smana.common.config.explorer import ExplorerConfig
from smana.common.config.fleet import FleetConfig
from smana.common.config.general import GeneralConfig, ZenohConfig
from smana.common.config.geometric import GeometricConfig
from smana.common.config.mapper import MapperConfig
from smana.common.config.navgraph import NavgraphConfig
from smana.common.config.planner import PlannerConfig
from smana.common.config.replay import ReplayConfig
from smana.common.config.ros2 import Ros2Config
from smana.common.config.section import ConfigError, Section, build, param, table, to_toml
from smana.common.config.sim import SimConfig
from smana.common.version import smana_version

__all__ = [
    "ConfigError",
    "DeployConfig",
    "ExplorerConfig",
    "FleetConfig",
    "GeneralConfig",
    "GeometricConfig",
    "MapperConfig",
    "NavgraphConfig",
    "PlannerConfig",
    "ReplayConfig",
    "Ros2Config",
    "Section",
    "ServiceDeployConfig",
    "SimConfig",
    "SmanaConfig",
    "ZenohConfig",
    "build",
    "param",
    "table",
]


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
    geometric: GeometricConfig = field(default_factory=GeometricConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)
    fleet: FleetConfig = field(default_factory=FleetConfig)

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
        """The config as TOML, headed by the smana that wrote it (a comment: it reads back)."""
        return f"# written by smana {smana_version()}\n" + to_toml(self)

    def write(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_toml())
        return p


# -- reading ---------------------------------------------------------------------------------


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
