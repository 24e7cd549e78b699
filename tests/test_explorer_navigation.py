"""Goals sent to the explorer (services/explorer/navigation.py), in-process and without Zenoh: the
check of a goal and of a cancel, pre-emption and cancel, the feedback's fields, and closed loops on
a toy grid (a unicycle integrates the commands, a straight-line path function stands in for the
planner) where a goal is reached, aborted, or pauses and resumes exploration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config.explorer import ExplorerConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.navigation import (
    STATES,
    GoalRefused,
    GoalSpec,
    parse_cancel,
    parse_goal,
)

RES = 0.2
TRAV = np.array([False, True, True, False, False])  # 0 unknown, 1 grass, 2 terrain, 4 hedge
LO, HI = (-10.0, -10.0), (10.0, 10.0)


def parse(body):
    return parse_goal(body, LO, HI, 0.2, 5.0)


def grid(n: int = 50, known_cols: int | None = None, hedge: tuple[int, int] | None = None):
    """An n x n box of terrain from (0, 0), known up to column `known_cols` of x (all by
    default), with a hedge node at `hedge`."""
    labels = np.full((n, n), 2, np.uint16)
    flags = np.full((n, n), fr.KNOWN, np.uint8)
    if known_cols is not None:
        labels[known_cols:] = 0
        flags[known_cols:] = 0
    if hedge is not None:
        labels[hedge] = 4
        flags[hedge] |= fr.OBSTACLE
    return GridBox(np.zeros(2), RES, labels, flags)


def straight(calls: list | None = None, reachable=lambda xy: True):
    def path_cost(start, goal, allow_unknown=False):
        if calls is not None:
            calls.append((np.array(start), np.array(goal), allow_unknown))
        if not reachable(goal):
            return None
        n = max(2, int(np.ceil(np.hypot(*(goal - start)) / RES)) + 1)
        path = start + (goal - start) * np.linspace(0, 1, n)[:, None]
        return float(np.hypot(*(goal - start))), path

    return path_cost


def explorer(mode="explore", **cfg) -> Explorer:
    ex = Explorer(ExplorerConfig(mode=mode, **cfg), TRAV, 5)
    ex.update_grid(grid())
    ex.update_pose(1.0, 1.0, 0.0, 100.0)
    return ex


def run(ex: Explorer, path_cost, seconds: float, until=lambda ex: False, dt=0.1):
    """The service's tick, with a unicycle for the robot; returns the commands sent."""
    x, y, yaw = ex.pose
    sent = []
    for _ in range(int(seconds / dt)):
        reason = ex.wants_plan()
        if reason is not None:
            ex.plan(path_cost, reason)
        v, w = ex.control()
        sent.append((v, w))
        x, y = x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt
        yaw += w * dt
        ex.update_pose(x, y, yaw, ex.t_now + dt)
        if until(ex):
            break
    return sent


# -- checking a goal ---------------------------------------------------------------------------


def test_a_good_goal_is_parsed_with_defaults_and_a_made_up_id():
    g = parse({"x": 3, "y": -2.5})
    assert (g.x, g.y, g.yaw, g.tolerance_m) == (3.0, -2.5, None, 0.2)
    assert 1 <= len(g.id) <= 64
    assert parse({"x": 0, "y": 0}).id != g.id
    g = parse({"x": 1.0, "y": 2.0, "yaw": 3 * math.pi, "tolerance_m": 0.5, "id": "a goal/1"})
    assert g.yaw == pytest.approx(-math.pi) and g.tolerance_m == 0.5 and g.id == "a goal/1"


@pytest.mark.parametrize(
    "body, kind",
    [
        (None, "malformed"),
        ([1.0, 2.0], "malformed"),
        ({"y": 1.0}, "malformed"),
        ({"x": "1", "y": 1.0}, "malformed"),
        ({"x": True, "y": 1.0}, "malformed"),
        ({"x": 1.0, "y": 1.0, "tolerance": 0.5}, "malformed"),  # misspelt: not the default
        ({"x": math.nan, "y": 1.0}, "value"),
        ({"x": 1.0, "y": math.inf}, "value"),
        ({"x": 1.0, "y": 1.0, "yaw": math.inf}, "value"),
        ({"x": 10.0, "y": 1.0}, "out_of_bounds"),
        ({"x": 1.0, "y": -10.5}, "out_of_bounds"),
        ({"x": 1e308, "y": 1.0}, "out_of_bounds"),
        ({"x": 1.0, "y": 1.0, "tolerance_m": 0.0}, "value"),
        ({"x": 1.0, "y": 1.0, "tolerance_m": -1.0}, "value"),
        ({"x": 1.0, "y": 1.0, "tolerance_m": 5.01}, "value"),
        ({"x": 1.0, "y": 1.0, "id": ""}, "malformed"),
        ({"x": 1.0, "y": 1.0, "id": "x" * 65}, "malformed"),
        ({"x": 1.0, "y": 1.0, "id": "a\nb"}, "malformed"),
        ({"x": 1.0, "y": 1.0, "id": 7}, "malformed"),
    ],
)
def test_a_bad_goal_is_refused_with_a_kind_and_a_reason(body, kind):
    with pytest.raises(GoalRefused) as exc:
        parse(body)
    assert exc.value.kind == kind and str(exc.value)


def test_a_cancel_names_a_goal_or_none():
    assert parse_cancel({}) is None and parse_cancel({"id": None}) is None
    assert parse_cancel({"id": "g1"}) == "g1"
    for bad in (None, {"id": ""}, {"id": 3}, {"goal": "g1"}):
        with pytest.raises(GoalRefused):
            parse_cancel(bad)


def test_a_goal_on_a_known_obstacle_is_refused_and_nothing_changes():
    ex = Explorer(ExplorerConfig(), TRAV, 5)
    ex.update_grid(grid(hedge=(20, 20)))
    ex.update_pose(1.0, 1.0, 0.0, 100.0)
    ex.accept_goal(GoalSpec(6.0, 6.0, None, 0.2, "first"))
    before = (ex.nav.id, ex.nav.state, list(ex.nav_changes))
    with pytest.raises(GoalRefused) as exc:
        ex.accept_goal(GoalSpec(4.1, 4.1, None, 0.2, "on-the-hedge"))  # node (20, 20)
    assert exc.value.kind == "goal_blocked"
    assert (ex.nav.id, ex.nav.state, list(ex.nav_changes)) == before
    # unknown ground is not known to be an obstacle: accepted
    ex.update_grid(grid(known_cols=10))
    ex.accept_goal(GoalSpec(8.0, 1.0, None, 0.2, "into-the-unknown"))
    assert ex.nav.id == "into-the-unknown"


# -- the state machine -------------------------------------------------------------------------


def test_a_new_goal_preempts_the_running_one_and_a_cancel_stops_the_robot():
    ex = explorer()
    ex.accept_goal(GoalSpec(6.0, 1.0, None, 0.2, "g1"))
    run(ex, straight(), 2.0)
    assert ex.nav.state == "active" and ex.goal is not None
    first = ex.nav
    ex.accept_goal(GoalSpec(1.0, 6.0, None, 0.2, "g2"))
    assert first.state == "preempted" and "g2" in first.reason
    assert ex.nav.id == "g2" and ex.nav.state == "active"
    assert [(f["id"], f["state"]) for f in ex.nav_changes] == [
        ("g1", "active"),
        ("g1", "preempted"),
        ("g2", "active"),
    ]
    run(ex, straight(), 2.0)
    v, w = ex.control()
    assert v != 0.0 or w != 0.0  # driving to g2
    # a cancel of another goal (or of the pre-empted one) changes nothing
    for gid in ("g1", "nope"):
        with pytest.raises(GoalRefused) as exc:
            ex.cancel_goal(gid)
        assert exc.value.kind == "unknown_goal" and ex.nav.state == "active"
    ex.cancel_goal("g2")
    assert ex.nav.state == "canceled" and ex.control() == (0.0, 0.0)
    assert ex.nav_changes[-1]["state"] == "canceled"
    with pytest.raises(GoalRefused) as exc:
        ex.cancel_goal(None)  # nothing runs now
    assert exc.value.kind == "no_goal"
    assert set(f["state"] for f in ex.nav_changes) <= set(STATES)


def test_the_feedback_holds_every_field_of_the_contract():
    ex = explorer()
    ex.accept_goal(GoalSpec(5.0, 1.0, 0.5, 0.3, "fb"))
    run(ex, straight(), 1.0)
    fb = ex.nav_feedback()
    assert set(fb) == {
        "id",
        "state",
        "goal",
        "pose",
        "distance_remaining_m",
        "navigation_time_s",
        "recoveries",
        "reason",
        "error",
    }
    assert fb["id"] == "fb" and fb["state"] == "active" and fb["goal"] == [5.0, 1.0, 0.5]
    assert len(fb["pose"]) == 3 and fb["recoveries"] == 0 and fb["reason"] == ""
    assert fb["navigation_time_s"] == pytest.approx(1.0, abs=0.11)
    # along the path: the robot drove straight at it
    straight_line = math.hypot(5.0 - fb["pose"][0], 1.0 - fb["pose"][1])
    assert fb["distance_remaining_m"] == pytest.approx(straight_line, abs=0.25)
    assert ex.state_dict()["nav_goal"] == {"id": "fb", "state": "active", "reason": ""}
    assert ex.mode == "navigating"


# -- closed loops ------------------------------------------------------------------------------


def test_a_goal_is_reached_within_its_tolerance_and_facing_its_yaw():
    ex = explorer(mode="navigate")
    ex.accept_goal(GoalSpec(6.0, 3.0, math.pi / 2, 0.25, "there"))
    run(ex, straight(), 60.0, until=lambda ex: not ex.nav_active)
    assert ex.nav.state == "succeeded", ex.nav_feedback()
    x, y, yaw = ex.pose
    assert math.hypot(x - 6.0, y - 3.0) <= 0.25
    assert abs((yaw - math.pi / 2 + math.pi) % (2 * math.pi) - math.pi) <= math.radians(10) + 1e-6
    fb = ex.nav_changes[-1]
    assert fb["state"] == "succeeded" and fb["distance_remaining_m"] <= 0.25
    assert ex.control() == (0.0, 0.0) and ex.wants_plan() is None  # a navigator waits


def test_a_navigator_never_explores_and_never_finishes():
    ex = explorer(mode="navigate", time_budget_s=1.0)
    ex.update_grid(grid(known_cols=10))  # frontiers all along x = 2 m
    sent = run(ex, straight(), 5.0)
    assert ex.n_plans == 0 and not ex.done and set(sent) == {(0.0, 0.0)}


def test_exploration_pauses_during_a_goal_and_resumes_after_it():
    ex = explorer()
    ex.update_grid(grid(known_cols=20))
    run(ex, straight(), 1.0)
    assert ex.n_plans >= 1 and ex.goal is not None  # exploring: a view chosen
    plans, goals = ex.n_plans, ex.n_goals
    ex.accept_goal(GoalSpec(1.0, 6.0, None, 0.2, "aside"))
    run(ex, straight(), 60.0, until=lambda ex: not ex.nav_active)
    assert ex.nav.state == "succeeded"
    assert (ex.n_plans, ex.n_goals) == (plans, goals)  # no exploration plan meanwhile
    run(ex, straight(), 1.0)
    assert ex.n_plans > plans and ex.exploring  # explores again


def test_without_resume_after_goal_it_waits_for_goals():
    ex = explorer(resume_after_goal=False)
    ex.update_grid(grid(known_cols=20))
    ex.accept_goal(GoalSpec(1.0, 3.0, None, 0.2, "only"))
    run(ex, straight(), 60.0, until=lambda ex: not ex.nav_active)
    assert ex.nav.state == "succeeded"
    plans = ex.n_plans
    run(ex, straight(), 5.0)
    assert ex.n_plans == plans and not ex.exploring and ex.goal is None


def test_an_unreachable_goal_is_aborted_after_goal_timeout_and_the_robot_stays():
    ex = explorer(mode="navigate", goal_timeout_s=3.0)
    calls = []
    ex.accept_goal(GoalSpec(6.0, 6.0, None, 0.2, "walled"))
    sent = run(ex, straight(calls, reachable=lambda g: False), 10.0, until=lambda e: e.nav.t_ended)
    assert ex.nav.state == "aborted" and "no path" in ex.nav.reason
    assert 3.0 < ex.nav_changes[-1]["navigation_time_s"] < 3.5
    assert set(sent) == {(0.0, 0.0)}
    # asked again and again meanwhile (the map may grow), through unknown space
    assert len(calls) >= 3 and all(allow for *_, allow in calls)


def test_a_goal_not_reached_in_its_time_budget_is_aborted():
    ex = explorer(mode="navigate", goal_time_budget_s=2.0)
    ex.accept_goal(GoalSpec(9.0, 9.0, None, 0.2, "far"))
    run(ex, straight(), 10.0, until=lambda e: e.nav.t_ended)
    assert ex.nav.state == "aborted" and "not reached" in ex.nav.reason


def test_a_goal_whose_node_becomes_an_obstacle_is_aborted():
    ex = explorer(mode="navigate")
    ex.accept_goal(GoalSpec(6.1, 1.1, None, 0.2, "hedge-grows"))
    run(ex, straight(), 1.0)
    ex.update_grid(grid(hedge=(30, 5)))
    run(ex, straight(), 1.0, until=lambda e: e.nav.t_ended)
    assert ex.nav.state == "aborted" and "obstacle" in ex.nav.reason


def test_a_stuck_robot_backs_off_counts_a_recovery_and_replans():
    ex = explorer(mode="navigate", stuck_timeout_s=2.0)
    ex.accept_goal(GoalSpec(6.0, 1.0, None, 0.2, "wedged"))
    ex.wants_plan() and ex.plan(straight(), "goal")
    for _ in range(40):  # the robot does not move whatever it is told
        reason = ex.wants_plan()
        if reason is not None:
            ex.plan(straight(), reason)
        ex.control()
        ex.update_pose(1.0, 1.0, 0.0, ex.t_now + 0.1)
    assert ex.nav.recoveries >= 1 and ex.nav.state == "active"
    assert ex.nav_feedback()["recoveries"] == ex.nav.recoveries


def test_a_goal_sent_before_the_first_pose_starts_its_clock_at_that_pose():
    ex = Explorer(ExplorerConfig(mode="navigate", goal_time_budget_s=20.0), TRAV, 5)
    ex.update_grid(grid())
    ex.accept_goal(GoalSpec(3.0, 1.0, None, 0.2, "early"))
    assert ex.nav_feedback()["navigation_time_s"] == 0.0 and ex.nav_feedback()["pose"] is None
    ex.update_pose(1.0, 1.0, 0.0, 1000.0)  # robot time far from 0
    assert ex.wants_plan() == "goal" and ex.nav.state == "active"
    run(ex, straight(), 30.0, until=lambda e: not e.nav_active)
    assert ex.nav.state == "succeeded", ex.nav_feedback()
    assert ex.nav_changes[-1]["navigation_time_s"] < 10.0


def test_a_goal_that_accepts_the_unreachable_is_accepted_and_aborted_with_its_error():
    """`accept_unreachable` (the ROS 2 actions, as Nav2's navigator): a goal outside the graph or
    on a known obstacle is accepted, pre-empts the running one, and ends "aborted" at once with
    the reason a refusal would give and its error kind; without it, both are refused."""
    with pytest.raises(GoalRefused) as exc:
        parse({"x": 50.0, "y": 0.0})
    assert exc.value.kind == "out_of_bounds"
    far = parse({"x": 50.0, "y": 0.0, "accept_unreachable": True, "id": "far"})
    assert far.unreachable[0] == "out_of_bounds" and "outside" in far.unreachable[1]
    for bad in ({"accept_unreachable": 1}, {"no_path_timeout_s": -1.0},
                {"no_path_timeout_s": 1e9}, {"no_path_timeout_s": "3"}):  # fmt: skip
        with pytest.raises(GoalRefused):
            parse({"x": 1.0, "y": 1.0, **bad})
    ex = Explorer(ExplorerConfig(), TRAV, 5)
    ex.update_grid(grid(hedge=(20, 20)))
    ex.update_pose(1.0, 1.0, 0.0, 100.0)
    ex.accept_goal(GoalSpec(6.0, 6.0, None, 0.2, "first"))
    ex.accept_goal(far)
    assert ex.nav.id == "far" and ex.nav.state == "aborted" and ex.nav.error == "out_of_bounds"
    assert [c["state"] for c in ex.nav_changes[-3:]] == ["preempted", "active", "aborted"]
    assert ex.nav_changes[-1]["error"] == "out_of_bounds"
    on_hedge = parse({"x": 4.1, "y": 4.1, "accept_unreachable": True, "id": "hedge"})
    ex.accept_goal(on_hedge)
    assert ex.nav.state == "aborted" and ex.nav.error == "goal_blocked", ex.nav
    assert "obstacle" in ex.nav.reason and ex.goal is None


def test_a_goal_s_own_no_path_timeout_replaces_the_config_s():
    ex = explorer(mode="navigate", goal_timeout_s=30.0)
    spec = parse({"x": 6.0, "y": 6.0, "no_path_timeout_s": 1.0, "id": "soon"})
    ex.accept_goal(spec)
    run(ex, straight(reachable=lambda g: False), 10.0, until=lambda e: e.nav.t_ended)
    assert ex.nav.state == "aborted" and ex.nav.error == "no_path", ex.nav
    assert 1.0 <= ex.nav_changes[-1]["navigation_time_s"] < 1.5
    # 0: aborted at the first plan that finds no path
    ex.accept_goal(parse({"x": 6.0, "y": 6.0, "no_path_timeout_s": 0.0, "id": "at-once"}))
    run(ex, straight(reachable=lambda g: False), 10.0, until=lambda e: e.nav.t_ended)
    assert ex.nav.error == "no_path" and ex.nav_changes[-1]["navigation_time_s"] < 0.2


def test_a_restarted_explorer_tells_the_sender_its_goal_ended_and_does_not_drive_to_it():
    """A goal the last process was driving to is not resumed: the restarted explorer's first
    feedback ends it "aborted" (error "stopped", the reason says why), and it drives nowhere."""
    ex = explorer(mode="navigate")
    ex.accept_goal(GoalSpec(6.0, 1.0, 0.5, 0.2, "g-before"))
    run(ex, straight(), 2.0)
    assert ex.nav_active and ex.goal is not None
    state = ex.state_dict()
    again = Explorer(ExplorerConfig(mode="navigate"), TRAV, 5)
    again.resume(state, np.array(ex.trajectory))
    (fb,) = again.nav_changes
    assert (fb["id"], fb["state"], fb["error"]) == ("g-before", "aborted", "stopped")
    assert "restarted" in fb["reason"] and fb["goal"] == [6.0, 1.0, 0.5]
    again.update_grid(grid())
    again.update_pose(*ex.pose, ex.t_now + 0.1)
    assert again.goal is None and not again.nav_active
    assert set(run(again, straight(), 2.0)) == {(0.0, 0.0)}
    # a checkpoint whose goal id is not one: nobody to tell, nothing breaks
    state["goal"]["navigate"] = 3
    other = Explorer(ExplorerConfig(mode="navigate"), TRAV, 5)
    other.resume(state, np.array(ex.trajectory))
    assert other.nav_changes == [] and other.goal is None
