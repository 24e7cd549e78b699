"""[navgraph] config section: the parameters of the navigation graph (`NavGraph(classes, config)`
receives this section as it is)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from smana.common.config._schema import ConfigError, Section, param


@dataclass
class NavgraphConfig(Section, section="navgraph"):
    resolution_m: float = param(0.2, gt=0, le=100.0)
    bounds_min_xy: list[float] = param([-50.0, -50.0])
    bounds_max_xy: list[float] = param([50.0, 50.0])
    robot_radius_m: float = param(0.4, ge=0, lt=math.inf)  # sizes the safety-zone stencil
    tile_size: int = param(32, ge=1, le=256)  # nodes per tile side; memory is allocated per tile
    # Occupied voxels remembered per node column (to recompute the node when the top one is
    # cleared); a 1.7 m person over ground at 0.1 m / 0.2 m fills ~70. Beyond it the lowest
    # levels are forgotten and a column cleared down to them becomes unknown.
    column_capacity: int = param(256, ge=1, le=4096)

    def validate(self) -> None:
        for name in ("bounds_min_xy", "bounds_max_xy"):
            if len(getattr(self, name)) != 2:
                raise ConfigError(f"navgraph.{name}: expected [x, y], got {getattr(self, name)}")
        if not all(a < b for a, b in zip(self.bounds_min_xy, self.bounds_max_xy, strict=True)):
            raise ConfigError("navgraph.bounds_max_xy: must exceed bounds_min_xy on both axes")
