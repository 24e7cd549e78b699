"""Coordinated exploration (issue 17): the coordinator's claim book, what a member's explorer makes
of the others (team.py), the planner's moving obstacles, and two explorers in a toy garden."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config import SmanaConfig
from smana.common.config.fleet import FleetConfig
from smana.services.coordinator.claims import ClaimBook
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.team import Team
from smana.services.planner.planner import Planner
from tests.test_explorer_loop import COST, RES, TRAV, ToyWorld, _garden, _params
from tests.test_planner_planner import CLASSES, TERRAIN, dense_grid

FLEET = FleetConfig(robots=["r1", "r2", "r3"], goal_separation_m=2.0, claim_radius_m=1.5)


# -- the claim book -------------------------------------------------------------------------------


def test_claims_are_kept_apart_first_come_first_served():
    book = ClaimBook(["r1", "r2"], goal_separation_m=2.0, ttl_s=5.0)
    assert book.claim("r1", (1.0, 1.0), 0.0) == (True, None)
    assert book.claim("r2", (2.0, 1.5), 0.0) == (False, "r1")  # 1.1 m from r1's goal
    assert book.claim("r2", (4.0, 1.0), 0.0) == (True, None)
    assert book.claim("r1", (3.5, 1.0), 0.1) == (False, "r2")  # r1 keeps its old claim
    assert book.snapshot() == {"r1": [1.0, 1.0], "r2": [4.0, 1.0]}
    assert book.claim("r1", (1.5, 1.0), 0.2) == (True, None)  # moving its own goal is fine
    book.confirm("r1", None, 0.3)  # its state says it has no goal any more
    assert "r1" not in book.snapshot()
    with pytest.raises(ValueError, match="not a member"):
        book.claim("r9", (0.0, 0.0), 0.0)
    with pytest.raises(ValueError, match="finite"):
        book.claim("r1", (math.nan, 0.0), 0.0)
    assert (book.granted, book.refused, book.released) == (3, 2, 1)


def test_a_silent_member_loses_its_claim():
    book = ClaimBook(["r1", "r2"], goal_separation_m=2.0, ttl_s=5.0)
    book.claim("r1", (1.0, 1.0), 0.0)
    book.confirm("r1", (1.0, 1.0), 4.0)  # its state still says so: kept
    assert book.expire(8.0) == []
    assert book.expire(9.5) == ["r1"]
    assert book.claim("r2", (1.0, 1.0), 9.5) == (True, None)


# -- a member's view of the others ---------------------------------------------------------------


def test_claimed_area_matches_a_per_cell_reference():
    team = Team(FLEET, "r1")
    team.update_goals({"r1": [0.0, 0.0], "r2": [1.3, 2.1], "r3": [3.9, 0.2]})
    origin, shape = np.array([-0.4, -0.2]), (30, 22)
    got = team.claimed(origin, RES, shape)
    want = np.zeros(shape, bool)
    for i in range(shape[0]):
        for j in range(shape[1]):
            cx, cy = origin[0] + (i + 0.5) * RES, origin[1] + (j + 0.5) * RES
            for gx, gy in ([1.3, 2.1], [3.9, 0.2]):  # ours is left out
                want[i, j] |= math.hypot(cx - gx, cy - gy) <= 1.5
    assert np.array_equal(got, want) and want.any()
    keep = team.apart(np.array([[1.3, 0.3], [1.3, 0.0], [0.0, 0.0]]))
    assert keep.tolist() == [False, True, True]  # 1.8 m and 2.1 m from r2's goal


def test_a_member_ahead_stops_us_and_the_later_member_gives_way_first():
    r1, r2 = Team(FLEET, "r1"), Team(FLEET, "r2")
    # face to face, 0.8 m apart: both stop
    r1.update_position("r2", 0.8, 0.0, 0.0)
    r2.update_position("r1", 0.0, 0.0, 0.0)
    assert r1.hold(0.0, 0.0, 0.0, 0.0) == (True, False)
    assert r2.hold(0.8, 0.0, math.pi, 0.0) == (True, False)
    # r2 comes after r1 in fleet.robots: it gives way after 3 s, r1 only after 9 s
    for t in (1.0, 2.0):
        r1.update_position("r2", 0.8, 0.0, t)
        r2.update_position("r1", 0.0, 0.0, t)
        assert r1.hold(0.0, 0.0, 0.0, t) == (True, False)
        assert r2.hold(0.8, 0.0, math.pi, t) == (True, False)
    r2.update_position("r1", 0.0, 0.0, 3.0)
    assert r2.hold(0.8, 0.0, math.pi, 3.0) == (True, True)
    r1.update_position("r2", 0.8, 0.0, 3.0)
    assert r1.hold(0.0, 0.0, 0.0, 3.0) == (True, False)
    # beside or behind is not ahead; a stale pose is forgotten
    assert r1.hold(0.0, 0.0, math.pi, 3.0) == (False, False)
    assert r1.hold(0.0, 0.0, 0.0, 3.0 + FLEET.pose_timeout_s + 0.1) == (False, False)


# -- the planner's moving obstacles ---------------------------------------------------------------


def test_the_planner_goes_round_another_robot_and_lets_a_close_one_leave():
    planner = Planner(dense_grid(np.full((40, 20), TERRAIN, np.uint16)), CLASSES)
    start, goal, other = (0.5, 2.0), (7.5, 2.0), np.array([[4.0, 2.0]])
    free = planner.plan(start, goal)
    around = planner.plan(start, goal, avoid=other, avoid_radius_m=0.9)
    assert free.ok and around.ok
    assert np.hypot(*(free.path[:, :2] - other[0]).T).min() < 0.2
    assert np.hypot(*(around.path[:, :2] - other[0]).T).min() >= 0.9 - 1e-6
    assert around.cost_total > free.cost_total
    # the cached enter costs are put back: the next query without obstacles is the first one
    again = planner.plan(start, goal)
    assert again.cost_total == pytest.approx(free.cost_total)
    # a goal beside the other robot is refused with the reason
    blocked = planner.plan(start, (4.5, 2.0), avoid=other, avoid_radius_m=0.9)
    assert not blocked.ok and blocked.error == "goal_blocked" and "another robot" in blocked.message
    # a robot already 0.5 m from the other may leave, never closer than it is
    leave = planner.plan((3.5, 2.0), (0.5, 2.0), avoid=other, avoid_radius_m=0.9)
    assert leave.ok
    assert np.hypot(*(leave.path[1:, :2] - other[0]).T).min() >= 0.5 - 1e-6


# -- two explorers on one shared map -------------------------------------------------------------


def _avoiding(world, grid, start_xy, others, radius_m):
    """The toy planner, going round the other robots as the planner service does (nodes within
    `radius_m` of another robot closed, unless the robot itself is that close)."""
    flags = grid.flags.copy()
    cx = (np.arange(flags.shape[0]) + 0.5) * RES
    cy = (np.arange(flags.shape[1]) + 0.5) * RES
    for ox, oy in others:
        if math.hypot(start_xy[0] - ox, start_xy[1] - oy) < radius_m:
            continue
        near = (cx[:, None] - ox) ** 2 + (cy[None, :] - oy) ** 2 < radius_m**2
        flags[near] |= fr.KNOWN | fr.OBSTACLE
    return world.path_cost(GridBox(grid.origin_xy, grid.resolution_m, grid.labels, flags))


def _team_run(n: int, start_xy, t_max=300.0, dt=0.1):
    """n explorers on one toy world (one shared map: what the fleet mapper gives), claiming goals
    from one book; returns (time to 90 % of the reachable area, goal pairs, closest approach)."""
    world = ToyWorld(_garden(1))
    fleet = FleetConfig(
        robots=[f"r{i + 1}" for i in range(n)], goal_separation_m=2.0, claim_radius_m=1.5
    )
    book = ClaimBook(fleet.robots, fleet.goal_separation_m, ttl_s=10.0)
    params = _params(
        max_range_m=3.0,
        follower={"lookahead_m": 0.3, "max_linear_mps": 0.5},
        max_queries=6,
        time_budget_s=t_max,
    )
    flat, bound = fr.path_cost_scale(0.8, COST, RES)
    robots = []
    for i, name in enumerate(fleet.robots):
        team = Team(fleet, name)
        robots.append(
            {
                "name": name,
                "ex": Explorer(params, TRAV, 9, bound, flat, team=team),
                "team": team,
                "pose": [*start_xy[i], 0.0],
            }
        )
    reach = world.reachable_traversable(start_xy[0])
    t, t90, closest, goal_pairs = 0.0, None, math.inf, []
    while t < t_max and not all(r["ex"].done for r in robots):
        if round(t / dt) % 3 == 0:
            for r in robots:
                world.reveal(*r["pose"])
            grid = world.grid()
            for r in robots:
                r["ex"].update_grid(grid)
        for r in robots:
            x, y, yaw = r["pose"]
            for o in robots:
                if o is not r:
                    r["team"].update_position(o["name"], o["pose"][0], o["pose"][1], t)
            r["team"].update_goals(book.snapshot())
            ex = r["ex"]
            ex.update_pose(x, y, yaw, t)
            reason = ex.wants_plan()
            if reason:

                def claim(xy, name=r["name"]):
                    ok, holder = book.claim(name, xy, 0.0)
                    return ok, holder, book.snapshot().get(holder)

                others = [o["pose"][:2] for o in robots if o is not r]
                ex.plan(_avoiding(world, ex.grid, (x, y), others, 0.9), reason, claim)
            book.confirm(r["name"], None if ex.goal is None else ex.goal.choice.xy, t)
            v, w = ex.control()
            r["pose"] = [x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt, yaw + w * dt]
        goals = [r["ex"].goal.choice.xy for r in robots if r["ex"].goal is not None]
        goal_pairs += [np.hypot(*(a - b)) for k, a in enumerate(goals) for b in goals[k + 1 :]]
        for k, a in enumerate(robots):
            for b in robots[k + 1 :]:
                closest = min(closest, math.dist(a["pose"][:2], b["pose"][:2]))
        if t90 is None and (world.known & reach).sum() >= 0.9 * reach.sum():
            t90 = t
        t += dt
    return t90, goal_pairs, closest


@pytest.mark.slow
def test_two_explorers_share_the_garden_and_keep_apart():
    t1, _, _ = _team_run(1, [(1.0, 1.0)])
    t2, pairs, closest = _team_run(2, [(1.0, 1.0), (1.0, 2.0)])
    assert t1 is not None and t2 is not None
    assert t2 < 0.7 * t1, (t1, t2)  # two robots on one map cover it sooner (0.49x when written)
    assert pairs and min(pairs) >= 2.0 - 1e-9  # never two goals within the separation
    assert closest > 0.45, closest  # they stop for each other (the bodies are 0.4 m across)


def test_fleet_layout_of_smana_up(tmp_path):
    from smana.deploy.supervisor import Supervisor, add_recorder

    cfg = SmanaConfig.load(overrides=['fleet.robots=["r1", "r2"]'])
    sup = Supervisor(cfg, tmp_path)
    add_recorder(sup)
    names = {n: (m.robot, m.service) for n, m in sup.procs.items()}
    assert names == {
        "sim@fleet": ("fleet", "sim"),
        "mapper@fleet": ("fleet", "mapper"),
        "navgraph@fleet": ("fleet", "navgraph"),
        "coordinator@fleet": ("fleet", "coordinator"),
        **{f"{s}@{r}": (r, s) for r in ("r1", "r2") for s in ("mapper", "planner", "explorer")},
        "recorder@fleet": ("fleet", "recorder"),
    }
    assert 'mapper.source="fleet"' in sup.procs["mapper@fleet"].argv
    assert f'general.run_dir="{tmp_path / "robots" / "r2"}"' in sup.procs["explorer@r2"].argv
    # a member's own host runs that member alone, the base none
    robot = SmanaConfig.load(
        overrides=[
            'fleet.robots=["r1", "r2"]',
            "deploy.fleet_base=false",
            'general.robot="r2"',
        ]
    )
    assert {m.robot for m in Supervisor(robot, tmp_path / "a").procs.values()} == {"r2"}
    base = SmanaConfig.load(overrides=['fleet.robots=["r1", "r2"]', "deploy.fleet_members=false"])
    assert {m.robot for m in Supervisor(base, tmp_path / "b").procs.values()} == {"fleet"}


def test_coordinator_service_claims_and_books(fake_stack):
    from smana.common import keys

    sets = ["--set", 'fleet.name="test"', "--set", 'fleet.robots=["r1", "r2"]']
    fake_stack.service("coordinator", *sets)
    fake_stack.wait_alive("coordinator")

    def claim(body):
        return fake_stack.query("coordinator", f"claim/{body.get('robot', 'r1')}", body)

    assert claim({"robot": "r1", "goal": [1.0, 1.0]})["granted"] is True
    got = claim({"robot": "r2", "goal": [1.5, 1.0]})
    assert got["granted"] is False and got["holder"] == "r1"
    assert got["claims"] == {"r1": [1.0, 1.0]}
    assert claim({"robot": "r2", "goal": [5.0, 1.0]})["granted"] is True
    # refused in one line each, and counted: a goal that is not a point, no goal key (a stranger
    # has no key of its own: tests/test_security.py)
    for bad in ({"robot": "r1", "goal": "x"}, {"robot": "r1"}):
        with pytest.raises(Exception, match="claim"):
            claim(bad)
    # r1's explorer says it has no goal any more: its claim ends
    fake_stack.publish(keys.explorer_state("r1"), {"mode": "waiting", "goal": None})
    fake_stack.publish(keys.explorer_state("r2"), b"\xc1 not msgpack")
    assert fake_stack.drained("coordinator")
    assert fake_stack.query("coordinator", "claims")["claims"] == {"r2": [5.0, 1.0]}
    st = fake_stack.status("coordinator")
    assert st.books_add_up() and st.rejected.get("malformed") == 1
    assert st.rejected.get("value") == 1 and st.rejected.get("missing_field") == 1


def test_members_poses_in_the_fleet_frame():
    world = FleetConfig(robots=["r1", "r2"])
    assert world.to_fleet_frame("r2", 1.0, 2.0, 0.3) == (1.0, 2.0, 0.3)
    own = FleetConfig(
        robots=["r1", "r2"], frame="start_pose", start_poses=[[0, 0, 0], [5.0, 1.0, math.pi / 2]]
    )
    x, y, yaw = own.to_fleet_frame("r2", 1.0, 0.0, 0.1)  # 1 m ahead of r2's start, facing +y
    assert (x, y, yaw) == pytest.approx((5.0, 2.0, math.pi / 2 + 0.1))
    assert own.to_fleet_frame("fleet", 1.0, 0.0) == (1.0, 0.0, 0.0)  # not a member: as it is


def test_a_stalled_member_holds_nobody_back():
    book = ClaimBook(["r1", "r2"], goal_separation_m=2.0, ttl_s=60.0, stall_s=20.0)
    book.claim("r1", (1.0, 1.0), 0.0)
    book.confirm("r1", (1.0, 1.0), 0.0, distance_m=5.0)
    book.confirm("r1", (1.0, 1.0), 15.0, distance_m=5.3)  # a back-off, not progress
    assert book.claim("r2", (1.5, 1.0), 15.0) == (False, "r1")
    book.confirm("r1", (1.0, 1.0), 21.0, distance_m=5.5)
    assert book.stalled_members(21.0) == ["r1"] and book.snapshot(21.0) == {}
    assert book.claim("r2", (1.5, 1.0), 21.0) == (True, None)  # r1 is wedged: r2 may go
    assert book.snapshot() == {"r1": [1.0, 1.0], "r2": [1.5, 1.0]}  # still in the book
    book.confirm("r1", (1.0, 1.0), 25.0, distance_m=6.6)  # it moves again
    assert book.snapshot(25.0) == {"r1": [1.0, 1.0], "r2": [1.5, 1.0]}


def test_a_stuck_explorer_reverses_out_before_going_on():
    from tests.test_explorer_loop import _explorer

    world = ToyWorld(_garden(1))
    ex = _explorer(_params(max_range_m=3.0))
    world.reveal(1.0, 1.0, 0.0)
    ex.update_grid(world.grid())
    ex.update_pose(1.0, 1.0, 0.0, 0.0)
    ex.plan(world.path_cost(ex.grid), ex.wants_plan())
    assert ex.goal is not None
    t = 0.0
    while ex.wants_plan() != "stuck":  # the robot does not move: wedged
        t += 0.5
        ex.update_pose(1.0, 1.0, 0.0, t)
        assert t < 60
    ex.plan(world.path_cost(ex.grid), "stuck")
    v, w = ex.control()
    assert v < 0 and w == 0.0  # reversing, straight
    ex.update_pose(0.9, 1.0, 0.0, t + 2.5)  # the back-off is over: on along the new path
    assert ex.control()[0] >= 0
    # wedged again, with another member 0.6 m behind: reversing would run into it
    ex.team = Team(FLEET, "r1")
    ex.team.update_position("r2", 0.3, 1.0, t + 3.0)
    while ex.wants_plan() != "stuck":
        t += 0.5
        ex.update_pose(0.9, 1.0, 0.0, t)
        ex.team.update_position("r2", 0.3, 1.0, t)
        assert t < 120
    ex.plan(world.path_cost(ex.grid), "stuck")
    assert ex.control()[0] >= 0  # no reversing into r2
