"""[explorer] config section: what `Explorer` (services/explorer/exploration.py) receives as it is.

    [explorer]           the exploration loop: budget, candidates, scoring, replanning, giving up
    [explorer.view]      the camera footprint a candidate view is scored with (`FovModel`)
    [explorer.follower]  pure pursuit toward the chosen view (`PurePursuit`)
    [explorer.pose_filter]  the pose it steers by: the localisation's, filtered (`PoseFilter`)
    [explorer.guard]     the last check of every command against the safety scan (`Guard`)

The service-only keys (control rate, timeouts, class cost overrides) live in [explorer] too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param, table


@dataclass
class ViewConfig(Section, section="explorer.view"):
    """A candidate view: a sector of `fov_deg` from `min_range_m` to `max_range_m` around the
    candidate node, tried at `n_yaw` headings (services/explorer/frontier.py)."""

    fov_deg: float = param(57.0, gt=0, le=360)  # the camera's horizontal field of view
    max_range_m: float = param(4.0, gt=0)  # how far a view is assumed to map the ground
    # a camera a few decimetres above the ground does not see the ground right under its lens
    min_range_m: float = param(0.3, ge=0)
    n_yaw: int = param(16, gt=0)  # headings tried at each candidate
    occlusion: bool = True  # obstacle nodes hide what is behind them

    def validate(self) -> None:
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(
                f"explorer.view.min_range_m: must be below explorer.view.max_range_m "
                f"({self.max_range_m:g}), got {self.min_range_m:g}"
            )


@dataclass
class FollowerConfig(Section, section="explorer.follower"):
    """Pure pursuit with turn-in-place (services/explorer/follower.py)."""

    lookahead_m: float = param(0.4, gt=0)  # the point of the path steered at
    max_linear_mps: float = param(0.4, gt=0)  # forward speed commanded at most
    max_angular_radps: float = param(1.0, gt=0)  # turn rate commanded at most
    goal_tolerance_m: float = param(0.2, gt=0)  # a goal this close is reached
    # heading error above which the robot stops and turns in place
    turn_in_place_rad: float = param(math.radians(30), gt=0)
    # heading error at which the forward speed has fallen to zero (linear taper up to there)
    slow_down_rad: float = param(math.radians(45), gt=0)
    final_yaw_tolerance_rad: float = param(math.radians(10), ge=0)  # heading error at a goal


@dataclass
class PoseFilterConfig(Section, section="explorer.pose_filter"):
    """The position the explorer steers by: a Kalman filter of the localisation's x and y,
    predicted with the commanded speed, its measurement noise estimated from the innovations
    (services/explorer/pose_filter.py); the yaw passes as it comes. Noise-free poses pass
    through it as they are."""

    enabled: bool = True  # false: the raw poses
    # how far the robot's motion strays from the commanded speed, per second (acceleration
    # limits, wheel slip, an obstacle holding it)
    motion_sd_mps: float = param(0.2, gt=0)
    window_s: float = param(5.0, gt=0)  # the innovations averaged for the noise estimate
    reset_m: float = param(1.0, gt=0)  # a pose this far from the prediction resets the filter
    max_gap_s: float = param(1.0, gt=0)  # so does a pose after a longer gap


@dataclass
class GuardConfig(Section, section="explorer.guard"):
    """The last check of every velocity command (services/explorer/guard.py): the robot's
    footprint, moved along the command for `horizon_s`, must keep `margin_m` from the points of
    the robot's safety scan (robot/safety_scan, base frame) or not come closer to them than it
    is; else the command is slowed, and stopped when no slower one passes. It needs no map and
    no pose: a drifted pose moves the map's obstacles, not what the scan sees."""

    enabled: bool = True  # false: commands go out as the explorer computes them
    # the robot's footprint: rectangles [centre x, centre y, half x, half y] in its base frame
    # (the simulated robot's chassis and its two wheels)
    footprint: list[list[float]] = param(
        [[0.0, 0.0, 0.28, 0.17], [0.0, 0.2, 0.11, 0.11], [0.0, -0.2, 0.11, 0.11]]
    )
    margin_m: float = param(0.06, ge=0)  # clearance kept from what the scan shows
    horizon_s: float = param(1.0, gt=0, le=5.0)  # the command is followed this far ahead
    # a scan's points are kept this long (robot time), placed by the pose the explorer steers
    # by: they cover the robot's sides, where the scanner's low beams do not reach
    memory_s: float = param(1.5, ge=0)
    range_m: float = param(1.5, gt=0)  # points farther from the robot are ignored
    # points between these heights in the base frame count (the ground and what the robot
    # passes under do not); the simulated robot's base frame is 0.15 m above the ground
    z_min_m: float = param(-0.05)
    z_max_m: float = param(0.15)
    # a scan older than this (robot time) is not trusted: the robot drives without the guard
    # and says so (a robot with no safety scanner never had one)
    stale_s: float = param(0.5, gt=0)

    def validate(self) -> None:
        for r in self.footprint:
            if len(r) != 4 or r[2] <= 0 or r[3] <= 0:
                raise ConfigError(
                    f"explorer.guard.footprint: each rectangle is [x, y, half x, half y] with "
                    f"positive halves, got {r!r}"
                )
        if not self.footprint:
            raise ConfigError("explorer.guard.footprint: at least one rectangle")
        if self.z_min_m >= self.z_max_m:
            raise ConfigError("explorer.guard.z_min_m: must be below explorer.guard.z_max_m")


@dataclass
class ExplorerConfig(Section, section="explorer"):
    time_budget_s: float = param(480.0, gt=0)  # robot (pose stamp) time, and wall time as well
    # The budget starts with the first pose once a map and a planner are there; past the budget
    # plus this, with neither, the explorer gives up (ends `no_graph` or `no_planner`).
    startup_grace_s: float = param(120.0, ge=0)
    control_rate_hz: float = param(10.0, gt=0)  # velocity commands and the loop's checks
    # "nbv": the paper's next-best view (score below); "nearest_frontier": Yamauchi 1997, the
    # nearest frontier by travel distance, a baseline for the lab
    strategy: Literal["nbv", "nearest_frontier"] = "nbv"
    # next-best-view choice (services/explorer/frontier.py::select_view, `ViewScore`)
    candidate_spacing_m: float = param(0.6, gt=0)  # one candidate per block of this side
    # a view seeing less unknown area is not worth a trip (both strategies: they stop alike)
    min_gain_m2: float = param(0.4, ge=0)
    # score = gain / full view area - w * path cost / cost of one view range on the cheapest
    # flat ground; w = the share of a full view worth driving one max_range_m there. 2: a full
    # view is worth half a view range (2 m) of terrain, or ~0.6 m of grass at cost 4. The
    # ablation in docs/experiments.md (w 0 / 0.5 / 2, grass x4, 3 seeds, cluttered garden) gives
    # the same coverage at every weight; its first run had about half the distance at 2, its
    # rerun under the fixed verdict rules tells the weights apart on neither distance nor
    # terrain share (0.05 on the old m^2-per-cost scale was worth ~32 m of terrain: the gain
    # alone chose the goal).
    path_cost_weight: float = param(2.0, ge=0)
    max_queries: int = param(10, gt=0)  # path queries per plan (branch and bound cap)
    # when to choose again
    replan_period_s: float = param(3.0, gt=0)
    # a periodic plan switches only for a score higher by this (score units: share of a full
    # view; 0.12 is ~1 m^2 of a default 8 m^2 view). nearest_frontier keeps its goal until it is
    # reached or no longer worth a look.
    switch_margin_share: float = param(0.12, ge=0)
    dwell_s: float = param(0.6, ge=0)  # pause at a reached view so the map catches up
    stuck_timeout_s: float = param(8.0, gt=0)  # no progress along the path: give that goal up
    # a given-up goal is left out of the candidates within this radius, for this long
    blacklist_radius_m: float = param(0.5, ge=0)
    blacklist_s: float = param(30.0, ge=0)  # see blacklist_radius_m
    # paths start from the nearest free node within this radius of the robot
    start_search_radius_m: float = param(1.0, ge=0)
    # speed cap while the robot stands on a safety-zone or obstacle node (it got there because
    # an obstacle was mapped late): it backs out slowly
    creep_speed_mps: float = param(0.15, gt=0)
    # turning on the spot sweeps a circle of this radius (the footprint's circumscribed radius:
    # the simulated robot's is 0.42 m). With a known obstacle node inside it the robot creeps
    # along its path (forward, or in reverse towards what lies behind) until it can turn, and
    # takes no look-around spin there. 0: it turns anywhere.
    turn_clearance_m: float = param(0.45, ge=0)
    done_after_empty: int = param(3, gt=0)  # plans finding no view before it is done
    # then, before it gives up: drive to look again at what cuts it off from free ground it has
    # seen (services/explorer/recovery.py), at most this many times while no view is found, each
    # from a place this far from the earlier ones
    recoveries: int = param(3, ge=0)
    recovery_spacing_m: float = param(1.0, gt=0)  # see recoveries
    # seen but unreachable free ground of at least this, and more than the reachable: the robot's
    # own map closed it in (the run ends `closed_in`, a failure)
    closed_in_min_m2: float = param(2.0, gt=0)
    empty_retry_s: float = param(1.0, gt=0)  # wait between plans that found no view
    # traversability cost overrides sent with every path request, "grass=4" or "1=4"
    class_costs: list[str] = param([])
    planner_timeout_s: float = param(2.0, gt=0)  # a path query unanswered this long fails
    pose_timeout_s: float = param(1.0, gt=0)  # no pose for this long: stop the robot
    # "explore": explore until done (and drive to the goals it is sent, pausing exploration);
    # "navigate": only drive to the goals it is sent (`explorer/goal`), never explore, never end
    mode: Literal["explore", "navigate"] = "explore"
    # once a goal has ended, an exploring explorer explores again (false: it waits for goals)
    resume_after_goal: bool = True
    # a goal with no path for this long (robot time) is aborted as unreachable
    goal_timeout_s: float = param(30.0, gt=0)
    # a goal not reached this long (robot time) after it was accepted is aborted
    goal_time_budget_s: float = param(600.0, gt=0)
    # a goal's tolerance may not exceed this (its default is follower.goal_tolerance_m)
    goal_max_tolerance_m: float = param(5.0, gt=0)
    # paths to a goal may cross unknown nodes (re-planned as they are mapped), as Nav2's do
    goal_through_unknown: bool = True
    goal_feedback_period_s: float = param(0.5, gt=0, le=1.0)  # feedback while a goal runs
    view: ViewConfig = table(ViewConfig)
    follower: FollowerConfig = table(FollowerConfig)
    pose_filter: PoseFilterConfig = table(PoseFilterConfig)
    guard: GuardConfig = table(GuardConfig)
