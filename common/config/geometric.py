"""[geometric] config section: the geometric labeller's own knobs (common/geometric.py), for
clouds that carry no labels (`smana replay --label-field none`, the ROS 2 input).

The robot's limits are not repeated here: the labeller takes the highest step from
`planner.max_step_m` and sizes its slope window by `navgraph.robot_radius_m`. The steepest slope
the robot climbs has no other home, so it lives here.
"""

from __future__ import annotations

from dataclasses import dataclass

from smana.common.config.section import ConfigError, Section, param

MAX_GRID_SIDE = 4000  # cells along a side of the labeller's grid at most (64 MB of indices)


@dataclass
class GeometricConfig(Section, section="geometric"):
    cell_m: float = param(0.2, gt=0)  # side of the 2D cells the ground is estimated on
    max_slope_deg: float = param(20.0, gt=0, lt=90)  # a steeper ground cell is an obstacle
    # A cell with fewer points is unknown (a lone return says nothing about the ground)
    min_points: int = param(2, ge=1)
    # Points farther than this from the sensor (on x or y) are unknown: bounds the grid, so that
    # one stray return far away cannot make it huge
    max_distance_m: float = param(100.0, gt=0)

    def validate(self) -> None:
        side = 2 * self.max_distance_m / self.cell_m
        if side > MAX_GRID_SIDE:
            raise ConfigError(
                f"geometric.max_distance_m: {self.max_distance_m:g} m at cell_m "
                f"{self.cell_m:g} makes a grid {side:.0f} cells wide (at most {MAX_GRID_SIDE}); "
                "lower max_distance_m or raise cell_m"
            )
