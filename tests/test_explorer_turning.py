"""Turning on the spot beside an obstacle (services/explorer/driving.py): the check that the
swept circle is clear, against a brute force over every node; and in a closed loop on a toy
grid, a robot whose goal lies behind it with a hedge just ahead on its left reverses along its path
instead of turning into the hedge (the simulated robot's footprint: without the rule its corner
hits the hedge)."""

from __future__ import annotations

import math

import numpy as np

from smana.common.config.explorer import ExplorerConfig
from smana.deploy.report import ground_truth as ev
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.navigation import GoalSpec

TRAV = np.array([False, True, True, False, False])  # 0 unknown, 1 grass, 2 terrain, 4 hedge
RES = 0.1


def box(obstacle: np.ndarray) -> GridBox:
    labels = np.where(obstacle, 4, 2).astype(np.uint16)
    flags = (fr.KNOWN | np.where(obstacle, fr.OBSTACLE, 0)).astype(np.uint8)
    return GridBox(np.zeros(2), RES, labels, flags)


def test_the_turn_check_equals_a_brute_force_over_every_node():
    rng = np.random.default_rng(11)
    for _ in range(200):
        obstacle = rng.random((30, 30)) < rng.uniform(0.0, 0.05)
        ex = Explorer(ExplorerConfig(turn_clearance_m=rng.uniform(0.1, 0.8)), TRAV, 5)
        ex.update_grid(box(obstacle))
        x, y = rng.uniform(-0.5, 3.5, 2)
        r = ex.config.turn_clearance_m
        clear = True
        for i, j in np.argwhere(obstacle):  # the node's square [i, i + 1) x [j, j + 1) * RES
            dx = max(i * RES - x, 0.0, x - (i + 1) * RES)
            dy = max(j * RES - y, 0.0, y - (j + 1) * RES)
            clear &= math.hypot(dx, dy) >= r
        assert ex._turn_clear(x, y) == clear, (x, y, r)


def drive(turn_clearance_m: float):
    """A robot at (2, 1) facing +x with a hedge just ahead on its left, sent to (0, 1) behind it;
    returns its poses (x, y, yaw) and the hedge's raster."""
    hedge = np.zeros((40, 30), bool)
    # ahead and to the left: x in [2.1, 3.0), y in [1.2, 1.7). Its nearest corner is 0.32 m from
    # the robot's centre: clear of the footprint as it stands, not of its corners as it turns.
    hedge[21:30, 12:17] = True
    ex = Explorer(ExplorerConfig(mode="navigate", turn_clearance_m=turn_clearance_m), TRAV, 5)
    ex.update_grid(box(hedge))
    x, y, yaw = 2.0, 1.0, 0.0
    ex.update_pose(x, y, yaw, 100.0)
    ex.accept_goal(GoalSpec(0.0, 1.0, None, 0.2, "behind"))

    def straight(start, goal, allow_unknown=False):
        n = max(2, int(np.ceil(np.hypot(*(goal - start)) / RES)) + 1)
        path = start + (goal - start) * np.linspace(0, 1, n)[:, None]
        return float(np.hypot(*(goal - start))), path

    poses, dt = [], 0.1
    for _ in range(400):
        reason = ex.wants_plan()
        if reason is not None:
            ex.plan(straight, reason)
        v, w = ex.control()
        x, y = x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt
        yaw += w * dt
        ex.update_pose(x, y, yaw, ex.t_now + dt)
        poses.append((x, y, yaw))
        if ex.nav.t_ended is not None:
            break
    return ex, np.array(poses), hedge


def test_a_robot_by_a_hedge_reverses_along_its_path_instead_of_turning_into_it():
    origin = np.full(2, RES / 2)  # the raster's cells are centred, the grid's nodes start at 0
    ex, poses, hedge = drive(0.45)
    assert ex.nav.state == "succeeded", ex.nav
    contact = ev.footprint_contacts(poses, hedge, origin, RES)
    assert not contact.any(), poses[contact][:3]
    assert ex.n_turns_avoided > 0
    # it reversed first: its x fell while it still faced +x
    assert poses[5, 0] < 2.0 and abs(poses[5, 2]) < 0.3
    # the same robot turning anywhere: its corner sweeps the hedge
    ex0, poses0, _ = drive(0.0)
    assert ex0.nav.state == "succeeded"
    assert ev.footprint_contacts(poses0, hedge, origin, RES).any()
    assert ex0.n_turns_avoided == 0


def test_no_look_around_spin_where_it_would_sweep_an_obstacle():
    hedge = np.zeros((40, 30), bool)
    hedge[5:30, 12:17] = True
    ex = Explorer(ExplorerConfig(), TRAV, 5)
    ex.update_grid(box(hedge))
    ex.update_pose(2.0, 1.0, 0.0, 100.0)
    assert not ex._maybe_spin() and ex._spin is None
    ex.update_pose(2.0, 0.3, 0.0, 101.0)  # 0.9 m from the hedge: room to turn
    assert ex._maybe_spin() and ex._spin is not None
