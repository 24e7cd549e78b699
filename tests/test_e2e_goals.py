"""End to end in simulation: `smana up` (sim, mapper, navgraph, planner and the explorer in
`mode = "navigate"`, each a process on an isolated loopback router) drives the simulated robot to
the goals it is sent over `explorer/goal`: a goal to a free place about 4 m away is reached within
its tolerance (the ground-truth pose says so), with feedback at >= 1 Hz; a second goal pre-empts
the first; a cancel stops the robot; a navigator never explores. The goal's target is chosen on
the world's ground truth: free with clearance, in the robot's component."""

from __future__ import annotations

import math
import threading
import time

import msgpack
import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import Pose, decode
from smana.common.query import request
from tests.conftest import kernels_ready, wait_for
from tests.test_resilience import Up

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

GARDEN = ["sim.garden.size_m=8.0", "navgraph.bounds_min_xy=[-5.0, -5.0]"]
GARDEN += ["navgraph.bounds_max_xy=[5.0, 5.0]"]
NAVIGATE = [
    'explorer.mode="navigate"',
    "deploy.recorder.enabled=false",
    # exploration's budget does not apply to a navigator: a short one must not end the run
    "explorer.time_budget_s=5",
]
TOLERANCE_M = 0.3


def goal_about_4m_away() -> tuple[float, float, float]:
    """A free place 3.8 to 4.2 m from where the robot spawns, with the most clearance there, in
    the robot's component of free ground: (x, y, distance)."""
    from scipy import ndimage

    from smana.common.config import SmanaConfig
    from smana.services.sim.worlds import build_world

    cfg = SmanaConfig.load(None, ["sim.seed=3", *GARDEN])
    world = build_world(cfg.sim)
    r = cfg.sim.robot.radius_m + 0.05
    sx, sy, _ = world.spawn_pose(r)
    trav = world.traversability(r)
    comps, _ = ndimage.label(trav.data)
    xs, ys = trav.cell_centres()
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    d = np.hypot(gx - sx, gy - sy)
    clearance = ndimage.distance_transform_edt(trav.data) * trav.resolution_m
    ok = (comps == comps[trav.index_of(sx, sy)]) & (np.abs(d - 4.0) <= 0.2)
    i, j = np.unravel_index(np.argmax(np.where(ok, clearance, -1.0)), ok.shape)
    assert ok[i, j] and clearance[i, j] > 0.2
    return float(xs[i]), float(ys[j]), float(d[i, j])


class Watch:
    """The robot's ground-truth pose and the goals' feedback, as they arrive."""

    def __init__(self, session, robot):
        self.lock = threading.Lock()
        self.truth: list[tuple[float, float, float]] = []  # (wall time, x, y)
        self.feedback: list[tuple[float, dict]] = []
        self.subs = [
            session.declare_subscriber(keys.pose_truth(robot), self._on_truth),
            session.declare_subscriber(keys.explorer_goal_feedback(robot), self._on_feedback),
        ]

    def _on_truth(self, sample) -> None:
        p = decode(sample.payload.to_bytes(), Pose)
        with self.lock:
            self.truth.append((time.monotonic(), float(p.position[0]), float(p.position[1])))

    def _on_feedback(self, sample) -> None:
        fb = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:
            self.feedback.append((time.monotonic(), fb))

    def where(self) -> tuple[float, float]:
        with self.lock:
            return self.truth[-1][1:]

    def speed(self, window_s: float = 0.5) -> float:
        """Ground-truth speed over the last `window_s` (inf until that much has arrived)."""
        with self.lock:
            now = time.monotonic()
            recent = [p for p in self.truth if p[0] >= now - window_s]
        if len(recent) < 2 or recent[-1][0] - recent[0][0] < 0.6 * window_s:
            return math.inf
        (t0, x0, y0), (t1, x1, y1) = recent[0], recent[-1]
        return math.hypot(x1 - x0, y1 - y0) / (t1 - t0)

    def of(self, gid: str) -> list[tuple[float, dict]]:
        with self.lock:
            return [(t, fb) for t, fb in self.feedback if fb["id"] == gid]

    def reached(self, gid: str, state: str) -> bool:
        return any(fb["state"] == state for _, fb in self.of(gid))

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def test_the_simulated_robot_reaches_a_goal_4m_away_and_stops_on_a_cancel(tmp_path):
    gx, gy, dist = goal_about_4m_away()
    up = Up(tmp_path, [*GARDEN, *NAVIGATE])
    watch = None
    try:
        s = up.session
        watch = Watch(s, up.robot)
        ready = ("planner", "explorer")
        assert wait_for(
            lambda: all(up.alive(x) and kernels_ready(s, up.robot, x) for x in ready), 300
        ), up.log()
        state = lambda: request(s, keys.explorer_state(up.robot))  # noqa: E731
        assert wait_for(lambda: state()["pose"] is not None and len(watch.truth) > 0, 60)

        def send(**body) -> dict:
            return request(s, keys.explorer_goal(up.robot), body, timeout_s=5)

        # a first goal, pre-empted by a second to the same place once the robot is under way
        assert send(x=gx, y=gy, tolerance_m=TOLERANCE_M, id="first")["accepted"]
        x0, y0 = watch.where()
        assert wait_for(lambda: math.dist(watch.where(), (x0, y0)) > 0.3, 60), up.log("explorer")
        assert send(x=gx, y=gy, tolerance_m=TOLERANCE_M, id="second")["accepted"]
        assert wait_for(lambda: watch.reached("first", "preempted"), 5)
        assert wait_for(lambda: watch.reached("second", "active"), 5)

        # reached within its tolerance
        budget_s = 20 * dist / 0.4  # generous: a loaded machine runs the simulator slowly
        assert wait_for(
            lambda: watch.reached("second", "succeeded") or watch.reached("second", "aborted"),
            budget_s,
        ), (watch.of("second")[-1:], up.log("explorer")[-3000:])
        end = [fb for _, fb in watch.of("second") if fb["state"] != "active"]
        assert end[0]["state"] == "succeeded", end
        assert math.dist(watch.where(), (gx, gy)) <= TOLERANCE_M + 0.1, (watch.where(), gx, gy)
        # feedback at >= 1 Hz while it ran
        times = [t for t, fb in watch.of("second") if fb["state"] == "active"]
        gaps = np.diff(times)
        assert len(times) >= 3 and gaps.max() <= 1.0, gaps
        # a navigator never explores, and its state says so
        st = state()
        assert st["n_plans"] == 0 and not st["exploring"]
        assert st["nav_goal"] == {"id": "second", "state": "succeeded", "reason": ""}

        # a cancel stops the robot: back towards the start, then canceled under way
        assert send(x=x0, y=y0, id="back")["accepted"]
        assert wait_for(lambda: watch.speed() > 0.1, 60), up.log("explorer")[-3000:]
        r = request(s, keys.explorer_goal_cancel(up.robot), {"id": "back"}, timeout_s=5)
        assert r["canceled"] and r["id"] == "back"
        assert wait_for(lambda: watch.reached("back", "canceled"), 5)
        assert wait_for(lambda: watch.speed() < 0.02, 5), watch.speed()
        assert up.proc.poll() is None  # the navigator waits for more goals
    finally:
        if watch is not None:
            watch.close()
        up.close()
