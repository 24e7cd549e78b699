"""The explorer service in-process on the fake zenoh (tests/support/fake_zenoh.py), with the test
standing in for the robot (integrates cmd_vel, publishes poses), the navgraph (publishes
GraphPatches) and the planner (a queryable answering straight-line paths). The explorer's real
process runs in the end-to-end tests (test_e2e_explore.py, test_resilience.py)."""

from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import (
    GraphPatch,
    PathReply,
    PathRequest,
    Pose,
    ServiceStatus,
    VelocityCommand,
    decode,
    encode,
)
from smana.common.query import request
from tests.conftest import wait_for

RES = 0.2
BOUNDS = [
    "--set",
    "navgraph.bounds_min_xy=[0.0, 0.0]",
    "--set",
    "navgraph.bounds_max_xy=[8.0, 8.0]",
]


def patch(x_max_m: float, seq: int = 1) -> GraphPatch:
    """Terrain known over x in [0, x_max), the whole width: patch number `seq` of a navgraph."""
    nx, ny = int(round(x_max_m / RES)), int(round(8.0 / RES))
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    cells = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.int32)
    k = len(cells)
    return GraphPatch(
        stamp_s=0.0,
        seq=seq,
        resolution_m=RES,
        origin_xy=np.zeros(2),
        cells=cells,
        labels=np.full(k, 2, np.uint16),
        heights=np.zeros(k, np.float32),
        flags=np.ones(k, np.uint8),
    )


class StubRobot:
    """Integrates the last velocity command and publishes poses at 20 Hz."""

    def __init__(self, session, robot):
        self.x, self.y, self.yaw = 1.0, 4.0, 0.0
        self.v = self.w = 0.0
        self.max_v = 0.0
        self.session = session
        self.pose_key = keys.pose(robot)
        self.sub = session.declare_subscriber(keys.cmd_vel(robot), self.on_cmd)
        self._stop = threading.Event()
        self.t = 1000.0  # robot time: a pose stamped 0.0 is far in its past
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def on_cmd(self, sample):
        cmd = decode(sample.payload.to_bytes(), VelocityCommand)
        self.v, self.w = cmd.linear_mps, cmd.angular_radps
        self.max_v = max(self.max_v, self.v)

    def run(self):
        dt = 0.05
        while not self._stop.is_set():
            self.x += self.v * math.cos(self.yaw) * dt
            self.y += self.v * math.sin(self.yaw) * dt
            self.yaw += self.w * dt
            self.t += dt
            pose = Pose.from_xyz_yaw(self.x, self.y, 0.0, self.yaw, stamp_s=self.t)
            self.session.put(self.pose_key, encode(pose))
            time.sleep(dt)

    def close(self):
        self._stop.set()
        self.thread.join()
        self.sub.undeclare()


def stub_planner(session, robot, calls):
    def on_query(query):
        req = decode(query.payload.to_bytes(), PathRequest)
        calls.append(req)
        a, b = req.start[:2], req.goal[:2]
        n = max(2, int(np.ceil(np.hypot(*(b - a)) / RES)) + 1)
        path = np.zeros((n, 3), np.float32)
        path[:, :2] = a + (b - a) * np.linspace(0, 1, n)[:, None]
        length = float(np.hypot(*(b - a)))
        reply = PathReply(
            request_id=req.request_id,
            ok=True,
            path=path,
            cost_total=length * 5.0,
            cost_distance=length,
        )
        query.reply(query.key_expr, encode(reply))

    # a planner says it is there with its liveliness token: the explorer waits for one
    token = session.liveliness().declare_token(keys.alive(robot, "planner"))
    return session.declare_queryable(keys.path_query(robot), on_query), token


def test_explorer_drives_to_the_frontier_survives_bad_input_and_finishes(fake_stack, tmp_path):
    zenoh_stack = fake_stack
    s = zenoh_stack.session
    robot = zenoh_stack.robot
    calls = []
    planner, planner_token = stub_planner(s, robot, calls)
    bot = StubRobot(s, robot)
    run_dir = tmp_path / "run"
    proc = zenoh_stack.service(
        "explorer",
        "--run-dir",
        str(run_dir),
        *BOUNDS,
        "--set",
        "explorer.done_after_empty=1",
        "--set",
        'explorer.class_costs=["grass=4"]',
    )
    try:
        zenoh_stack.wait_alive("explorer")
        s.put(keys.graph_patch(robot), encode(patch(4.0)))
        # the frontier is the line x = 4 m: the robot must head there
        assert wait_for(lambda: bot.x > 2.5, 30), (bot.x, zenoh_stack.log("explorer"))
        assert calls and calls[0].class_costs == {1: 4.0} and not calls[0].allow_unknown
        st = request(s, keys.explorer_state(robot), timeout_s=5)
        assert st["mode"] in ("following", "waiting", "spinning")
        assert st["distance_m"] > 1.0
        # the checkpoint holds the goal it drives to (written at every new goal, not only every
        # 10 s): a spare that takes over drives on to it
        checkpoint = run_dir / "explorer" / "state.json"

        def saved_goal():
            live = request(s, keys.explorer_state(robot), timeout_s=5)["goal"]
            saved = json.loads(checkpoint.read_text())["goal"] if checkpoint.exists() else None
            return live is not None and saved is not None and saved["xy"] == live["xy"]

        assert wait_for(saved_goal, 5), zenoh_stack.log("explorer")

        # bad input is counted, not fatal
        s.put(keys.graph_patch(robot), b"\x00garbage")
        bad = patch(1.0)
        bad.resolution_m = 0.5  # a grid that does not match
        s.put(keys.graph_patch(robot), encode(bad))
        s.put(keys.pose(robot), encode(Pose()) + b"x")
        # A pose stamped 0.0 once ended the run (the budget looked spent); a 1 km jump was taken.
        s.put(keys.pose(robot), encode(Pose.from_xyz_yaw(bot.x, bot.y, 0, 0, stamp_s=0.0)))
        s.put(keys.pose(robot), encode(Pose.from_xyz_yaw(1000.0, 0, 0, 0, stamp_s=bot.t)))

        def errors():
            st = request(s, keys.status(robot, "explorer"), timeout_s=5)
            assert isinstance(st, ServiceStatus)
            assert st.books_add_up(), st
            return sum(st.rejected.values())

        assert wait_for(lambda: errors() >= 5, 10)
        st = request(s, keys.status(robot, "explorer"), timeout_s=5)
        assert st.rejected.get("stamp") == 1 and st.rejected.get("pose_jump") == 1, st.rejected
        assert proc.poll() is None
        assert request(s, keys.explorer_state(robot), timeout_s=5)["mode"] != "done"

        # everything known: nothing left to explore, the explorer stops the robot and exits 0
        s.put(keys.graph_patch(robot), encode(patch(8.0, seq=2)))
        proc.wait(timeout=60)
        assert proc.returncode == 0, zenoh_stack.log("explorer")
        # the fake network delivers a put before it returns: the explorer's last command (stop)
        # reached the robot before its thread ended
        assert bot.v == 0.0 and bot.w == 0.0
        state = json.loads((run_dir / "explorer" / "state.json").read_text())
        assert state["done_reason"] in ("no_frontier", "no_view_worth_it")
        assert state["plans"] and state["explored_m2"] > 50
        # the strategy is recorded for the lab to tell runs apart; one history row per plan
        assert state["strategy"] == "nbv"
        assert {p["strategy"] for p in state["plans"]} == {"nbv"}
        assert len(state["history"]) == state["n_plans"] and len(state["history"][0]) == 4
        traj = np.loadtxt(run_dir / "explorer" / "trajectory.csv", delimiter=",", skiprows=1)
        assert traj[:, 1].max() > 2.5
        g = np.load(run_dir / "explorer" / "graph.npz")
        assert (g["flags"] & 1).sum() == 40 * 40

        # restarted in the same run (a supervisor restart): it resumes, sees the run finished,
        # and exits 0 at once without losing what the first one travelled
        again = zenoh_stack.service("explorer", "--run-dir", str(run_dir), *BOUNDS)
        again.wait(timeout=30)
        assert again.returncode == 0, zenoh_stack.log("explorer")
        state2 = json.loads((run_dir / "explorer" / "state.json").read_text())
        assert state2["distance_m"] == pytest.approx(state["distance_m"])
        assert len(state2["plans"]) == len(state["plans"])
        traj2 = np.loadtxt(run_dir / "explorer" / "trajectory.csv", delimiter=",", skiprows=1)
        assert len(traj2) >= len(traj)
    finally:
        bot.close()
        planner.undeclare()
        planner_token.undeclare()
