"""[explorer] config section."""

from __future__ import annotations

from dataclasses import dataclass

from smana.common.config._schema import Section, param


@dataclass
class ExplorerConfig(Section, section="explorer"):
    time_budget_s: float = param(480.0, gt=0)  # robot (pose stamp) time, and wall time as well
    # The budget starts with the first pose once a map and a planner are there; past the budget
    # plus this, with neither, the explorer gives up (ends `no_graph` or `no_planner`).
    startup_grace_s: float = param(120.0, ge=0)
    enabled: bool = True
    control_rate_hz: float = param(10.0, gt=0)
    # next-best-view scoring (services/explorer/frontier.py)
    fov_deg: float = param(57.0, gt=0)  # the camera's horizontal field of view
    view_range_m: float = param(4.0, gt=0)  # how far a view is assumed to map the ground
    view_min_range_m: float = param(0.3, ge=0)
    n_yaw: int = param(16, gt=0)
    occlusion: bool = True  # obstacle nodes hide what is behind them
    candidate_spacing_m: float = param(0.6, gt=0)
    min_gain_m2: float = param(0.4, ge=0)  # a view seeing less unknown area is not worth it
    path_cost_weight: float = param(0.05, ge=0)  # m^2 of view gain per unit of A* path cost
    max_queries: int = param(10, gt=0)  # path queries per plan (branch and bound cap)
    replan_period_s: float = param(3.0, gt=0)
    switch_margin_m2: float = param(1.0, ge=0)
    stuck_timeout_s: float = param(8.0, gt=0)
    done_after_empty: int = param(3, gt=0)
    # traversability cost overrides sent with every path request, "grass=4" or "1=4"
    class_costs: list[str] = param([])
    planner_timeout_s: float = param(2.0, gt=0)
    # pure pursuit (services/explorer/follower.py)
    lookahead_m: float = param(0.4, gt=0)
    max_linear_mps: float = param(0.4, gt=0)
    max_angular_radps: float = param(1.0, gt=0)
    goal_tolerance_m: float = param(0.2, gt=0)
    pose_timeout_s: float = param(1.0, gt=0)  # no pose for this long: stop the robot
