"""[navgraph] config section: the parameters of the navigation graph (`NavGraph(classes, config)`
receives this section as it is)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from smana.common.config.section import ConfigError, Section, param

MAX_TILES = 1 << 24  # the grid's tile table: 64 MB of int32


@dataclass
class NavgraphConfig(Section, section="navgraph"):
    resolution_m: float = param(0.2, gt=0, le=100.0)  # side of a node's cell
    # the graph's fixed bounds, x and y in metres: nodes are allocated only where data arrives
    bounds_min_xy: list[float] = param([-50.0, -50.0])
    bounds_max_xy: list[float] = param([50.0, 50.0])  # see bounds_min_xy
    robot_radius_m: float = param(0.4, ge=0, lt=math.inf)  # sizes the safety-zone stencil
    # The safety zone surrounds a node labelled with a forbidden class (water) as it surrounds an
    # obstacle: a path keeps the robot's radius from it. False: only the node itself is closed.
    forbidden_margin: bool = True
    # A map that doubts before it blocks (docs/architecture.md, "Obstacles"): a node is an
    # obstacle when its column stands more than `obstacle_step_m` over its lowest voxel (the robot
    # cannot drive over it, whatever its label), or when it shows an obstacle class whose label
    # is certain (from a map that sends no label distribution; a probability of 1 from a map
    # that sends one is not certainty). An uncertain obstacle class without that height is
    # doubtful: passable at the planner's `doubtful_cost`, no safety zone round it. Each node
    # keeps evidence: +1 for each update whose top level votes for an obstacle class,
    # -`semantic_miss_weight` for each that does not, kept within +/- max(2 x semantic_confirm,
    # 8); a node whose evidence is not positive shows its top level's other class.
    # semantic_confirm > 0: a doubtful node whose evidence reaches it blocks too (0: never by an
    # uncertain label alone); obstacle_step_m = inf: no geometric obstacles.
    obstacle_step_m: float = param(0.25, gt=0)
    # An occupancy map's voxel makes a geometric obstacle only once its log-odds reach this
    # (OctoMap's hit adds 0.85, a miss takes 0.41: three hits, net of a miss): a wall smeared
    # onto the lawn by noisy poses is hit now and then and seen through in between. 1.0 (two
    # hits) let 0.1 m of white pose noise grow the hedges by a node each side and close 1.4 m
    # passages (docs/architecture.md, "Obstacles"). -inf: every occupied voxel.
    solid_log_odds: float = param(2.0)
    semantic_confirm: int = param(0, ge=0, le=60)
    semantic_miss_weight: int = param(2, ge=1, le=60)
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
        # What the grid would be (common/navgrid.py), refused here rather than by a navgraph
        # that crashes at every restart: nodes per axis, and its table of tiles in memory.
        from smana.common.navgrid import MAX_NODES_PER_AXIS

        span = [b - a for a, b in zip(self.bounds_min_xy, self.bounds_max_xy, strict=True)]
        nodes = [math.ceil(s / self.resolution_m) for s in span]
        tiles = math.prod(-(-n // self.tile_size) for n in nodes)
        if max(nodes) > MAX_NODES_PER_AXIS or tiles > MAX_TILES:
            raise ConfigError(
                f"navgraph.bounds_min_xy / bounds_max_xy / resolution_m: a grid of "
                f"{nodes[0]:.3g} x {nodes[1]:.3g} nodes (at most {MAX_NODES_PER_AXIS} per axis "
                f"and {MAX_TILES} tiles of tile_size); narrow the bounds or coarsen the resolution"
            )
