"""[mapper] config section. `SemanticMap` (services/mapper) receives it as it is.

`backend` is a name from the mapper's back-end registry (`services/mapper/backends/`) or a
`module:Class` spec of an out-of-tree one; the registry checks it: `smana mapper` and `smana up`
do so before anything starts. Each back-end family declares its own parameters beside its code
(`OctreeConfig` in backends/occupancy.py, `TsdfConfig` in backends/tsdf.py, a plugin's in its
module) and they are read from `[mapper.<config_key>]` (`[mapper.octree]`, `[mapper.tsdf]`): the
registry lists them, by name only (`with_variants`), so that common imports no service code
until a back-end's section is wanted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import (
    ConfigError,
    Section,
    param,
    variant_tables,
    with_variants,
)

# The map's limits, declared once: the config checks them and the core (services/mapper) and its
# map files use these. Voxel keys lie in [-KEY_LIMIT, KEY_LIMIT) an axis (OctoMap's 16-bit keys;
# the block grid, services/mapper/block_grid.py); resolutions 0.01 .. 10 m (a MapDelta could carry
# 0.001 .. 100 m, common/messages.py).
KEY_LIMIT = 32768
RESOLUTION_RANGE_M = (0.01, 10.0)


def max_range_for(resolution_m: float) -> float:
    """The longest range that means anything at this resolution: twice the map's extent (the
    key range, +-KEY_LIMIT voxels an axis), past its diagonal. A longer one overflows the
    kernels' set-up."""
    return 4.0 * KEY_LIMIT * resolution_m


@with_variants("smana.services.mapper.backends:config_sections", "backend")
@dataclass(eq=False)
class MapperConfig(Section, section="mapper"):
    backend: str = "octree-max"  # a registry name or a module:Class spec (see the docstring)
    resolution_m: float = param(0.1, gt=0, le=RESOLUTION_RANGE_M[1])  # and >= the range's low
    max_range_m: float = param(10.0, gt=0)  # at most max_range_for(resolution_m)
    # free space carved before a hit (the octrees); 0 = the whole ray; at most max_range_for()
    raycast_range_m: float = param(1.0, ge=0)
    inputs: list[str] = param(["cloud"])  # "cloud" and/or "scan"
    autosave_period_s: float = param(30.0, ge=0)  # 0 = only on shutdown
    load: str = ""  # resume from this map file; "auto" = save_path when it exists
    save_path: str = ""  # "" = <run_dir>/map.npz (no autosave without a run dir)
    # What `mapper/save` queries may leave beside save_path: .npz files, and their megabytes
    # (the autosave itself is never refused). A save past either is refused, counted `quota`.
    save_max_files: int = param(16, ge=1)
    save_max_mb: float = param(2048.0, gt=0)  # megabytes those files may take together
    # What the map is made of: "clouds", the robot's own clouds (`inputs`); "fleet", the map
    # deltas of every `fleet.robots` member, merged into one map (services/mapper/fleet.py;
    # run under the fleet's name, `--robot fleet`)
    source: Literal["clouds", "fleet"] = "clouds"
    # [mapper.octree], [mapper.tsdf], a plugin's: each back-end family's own section
    variants: dict[str, Section] = variant_tables()

    def validate(self) -> None:
        if self.resolution_m < RESOLUTION_RANGE_M[0]:
            low = RESOLUTION_RANGE_M[0]
            raise ConfigError(f"mapper.resolution_m: at least {low:g} m, got {self.resolution_m!r}")
        extent = max_range_for(self.resolution_m)
        for key in ("max_range_m", "raycast_range_m"):
            if getattr(self, key) > extent:
                got, res = getattr(self, key), self.resolution_m
                raise ConfigError(
                    f"mapper.{key}: must be in (0, {extent:g}] at resolution_m {res:g}, got {got:g}"
                )
        if not self.backend.strip():
            raise ConfigError("mapper.backend: expected a back-end name, got ''")
        for name in self.inputs:
            if name not in ("cloud", "scan"):
                raise ConfigError(f"mapper.inputs: 'cloud' and/or 'scan', got {name!r}")
        if not self.inputs:
            raise ConfigError("mapper.inputs: at least one of 'cloud', 'scan'")
