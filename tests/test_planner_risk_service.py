"""planner.risk in the running stack: map deltas carrying a label distribution go through navgraph
to the planner service, which answers path queries (the explorer's and the ROS 2 actions' way in)
under the configured mode. In-process on the fake zenoh."""

from __future__ import annotations

import numpy as np

from smana.common import keys
from smana.common.messages import MapDelta, PathReply, PathRequest, encode
from smana.common.query import request
from tests.conftest import wait_for

RES = 0.1
TERRAIN, GRASS, HEDGE = 2, 1, 4
CONFIG = [
    "--set",
    "navgraph.bounds_min_xy=[0.0, 0.0]",
    "--set",
    "navgraph.bounds_max_xy=[4.0, 4.0]",
    "--set",
    "navgraph.robot_radius_m=0.2",
    "--set",
    "planner.graph_sync_timeout_s=3.0",
]


def doubtful_ground() -> MapDelta:
    """4 x 4 m of certain terrain with a band x in [2.0, 2.4) m of grass the map holds at 60 %,
    the hedge class (infinite cost) at 40 %."""
    ij = [(i, j) for i in range(40) for j in range(40)]
    band = np.array([20 <= i < 24 for i, _ in ij])
    n = len(ij)
    return MapDelta(
        stamp_s=1.0,
        seq=1,
        cloud_seq=1,
        backend="octree-bayes",
        resolution_m=RES,
        centres=np.array([((i + 0.5) * RES, (j + 0.5) * RES, 0.05) for i, j in ij], np.float32),
        labels=np.where(band, GRASS, TERRAIN).astype(np.uint16),
        confidences=np.where(band, 0.6, 1.0).astype(np.float32),
        occupied=np.ones(n, np.uint8),
        values=np.full(n, 2.0, np.float32),
        alt_labels=np.where(band, HEDGE, 0).astype(np.uint16),
        alt_confidences=np.where(band, 0.4, 0.0).astype(np.float32),
    )


def plan(stack, start, goal) -> PathReply:
    req = PathRequest(request_id="t", start=np.array(start, float), goal=np.array(goal, float))
    reply = request(stack.session, keys.path_query(stack.robot), req, 10.0)
    assert isinstance(reply, PathReply), reply
    return reply


def test_the_service_plans_under_the_configured_risk(fake_stack):
    stack = fake_stack
    stack.service("navgraph", *CONFIG)
    stack.service(
        "planner", *CONFIG, "--set", 'planner.risk="chance"', "--set", "planner.max_risk=0.1"
    )
    stack.wait_alive("navgraph")
    stack.wait_alive("planner")
    stack.publisher(keys.map_delta(stack.robot)).put(encode(doubtful_ground()))
    assert wait_for(lambda: plan(stack, (0.5, 0.5), (1.5, 3.5)).ok)  # certain terrain
    # P(hedge) 0.4 > max_risk 0.1: the band is closed, and a goal in it is refused saying why
    r = plan(stack, (0.5, 0.5), (2.1, 1.0))
    assert not r.ok and r.error == "goal_blocked" and "max_risk" in r.message, r
    across = plan(stack, (0.5, 2.0), (3.5, 2.0))
    assert not across.ok and across.error == "unreachable", across  # the band spans the map
