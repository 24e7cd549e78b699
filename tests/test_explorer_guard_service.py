"""The explorer service's guard, on the fake zenoh: a wall its map does not show (as when a
drifted pose has moved the map's obstacles) stops the robot at the guard's margin, from the
safety scan alone; a scan it cannot use is counted and changes nothing."""

from __future__ import annotations

import math

import numpy as np

from smana.common import keys
from smana.common.messages import SemanticCloud, ServiceStatus, encode
from smana.common.query import request
from tests.conftest import wait_for
from tests.test_explorer_service import BOUNDS, StubRobot, patch, stub_planner

WALL_X = 2.6  # the unmapped wall, world frame


class ScannedRobot(StubRobot):
    """The stub robot with a safety scanner: the wall x = WALL_X, in its base frame, with every
    pose."""

    scan_seq = 0

    def publish_scan(self):
        ys = np.arange(-3.0, 3.0, 0.03)
        world = np.column_stack([np.full_like(ys, WALL_X), self.y + ys])
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        d = world - [self.x, self.y]
        base = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        base = base[np.hypot(*base.T) < 3.0]
        self.scan_seq += 1
        n = len(base)
        scan = SemanticCloud(
            stamp_s=self.t,
            seq=self.scan_seq,
            points=np.column_stack([base, np.zeros(n)]).astype(np.float32),
            labels=np.zeros(n, np.uint16),
            confidences=np.zeros(n, np.float32),
            sensor_position=np.zeros(3),
            frame_id="base_link",
            source="safety_scan",
        )
        self.session.put(keys.safety_scan(self.robot), encode(scan))


def test_an_unmapped_wall_stops_the_robot_at_the_guards_margin(fake_stack, tmp_path):
    s, robot = fake_stack.session, fake_stack.robot
    calls = []
    planner, token = stub_planner(s, robot, calls)
    bot = ScannedRobot(s, robot)
    bot.robot = robot
    ticks = {"n": 0}

    def scan_every_other_pose(sample):
        ticks["n"] += 1
        if ticks["n"] % 2 == 0:
            bot.publish_scan()

    pose_sub = s.declare_subscriber(keys.pose(robot), scan_every_other_pose)
    proc = fake_stack.service("explorer", "--run-dir", str(tmp_path / "run"), *BOUNDS)
    try:
        fake_stack.wait_alive("explorer")
        # the map knows terrain to x = 4 m and nothing of the wall: the frontier lies beyond it
        s.put(keys.graph_patch(robot), encode(patch(4.0)))

        def guard():
            return request(s, keys.explorer_state(robot), timeout_s=5)["guard"]

        assert wait_for(lambda: guard()["stopped"] > 0, 30), fake_stack.log("explorer")
        # it stays stopped at the wall while the explorer gives that way up (no progress)
        assert wait_for(
            lambda: request(s, keys.explorer_state(robot), timeout_s=5)["n_stuck"] > 0, 30
        ), fake_stack.log("explorer")
        front = bot.x + 0.28 * math.cos(bot.yaw)
        assert front < WALL_X, (bot.x, bot.yaw)
        g = guard()
        assert g["scans"] > 10 and g["slowed"] > 0
        assert 0.0 < g["min_clearance_m"] <= 0.2

        # a scan in another frame is refused and counted; the explorer runs on
        bad = SemanticCloud(stamp_s=bot.t, seq=1, frame_id="world", source="safety_scan")
        s.put(keys.safety_scan(robot), encode(bad))

        def rejected():
            st = request(s, keys.status(robot, "explorer"), timeout_s=5)
            assert isinstance(st, ServiceStatus) and st.books_add_up(), st
            return st.rejected

        assert wait_for(lambda: rejected().get("frame") == 1, 10), rejected()
        s.put(keys.safety_scan(robot), b"\x00garbage")
        assert wait_for(lambda: rejected().get("malformed") == 1, 10), rejected()
        assert proc.poll() is None
    finally:
        pose_sub.undeclare()
        bot.close()
        planner.undeclare()
        token.undeclare()
