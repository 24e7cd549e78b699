"""The exploration state machine in a closed loop with a toy world, in-process and without Zenoh.

The toy world is a ground-truth label raster; a camera reveals nodes in its field of view (with
line of sight), a toy navgraph flags obstacles and the safety zone on what is known, a small A*
with the paper's cost stands in for the planner, and a unicycle integrates the commands.
"""

from __future__ import annotations

import heapq
import json
import math

import numpy as np
import pytest
from scipy import ndimage

from smana.common.config.explorer import ExplorerConfig, FollowerConfig, ViewConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.follower import wrap_angle

RES = 0.2
COST = np.array([np.inf, 2.0, 1.0, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf])
TRAV = np.isfinite(COST)
OBST = np.zeros(9, bool)
OBST[4:] = True


def _garden(seed: int, n=40) -> np.ndarray:
    """Grass and terrain patches with hedge rows (gaps in them) and a few trees."""
    rng = np.random.default_rng(seed)
    lab = np.where(rng.random((n // 5, n // 5)) < 0.5, 1, 2).repeat(5, 0).repeat(5, 1)
    lab = lab.astype(np.uint16)
    lab[:, 0] = lab[:, -1] = lab[0, :] = lab[-1, :] = 4  # a hedge all round
    lab[14, 0:28] = 4  # two hedge rows, each with a gap
    lab[26, 12:40] = 4
    for _ in range(5):
        i, j = rng.integers(4, n - 4, 2)
        lab[i - 1 : i + 1, j - 1 : j + 1] = 8
    return lab


class ToyWorld:
    def __init__(self, labels, inflation_m=0.35):
        self.gt = labels
        self.obstacle = OBST[labels]
        r = inflation_m / RES
        k = int(math.ceil(r))
        disc = np.hypot(*np.mgrid[-k : k + 1, -k : k + 1]) <= r
        self.disc = disc
        self.gt_safety = ndimage.binary_dilation(self.obstacle, disc) & ~self.obstacle
        self.known = np.zeros(labels.shape, bool)
        self.fov = fr.FovModel.build(
            RES, ViewConfig(fov_deg=57.0, max_range_m=3.0, min_range_m=0.3, n_yaw=1)
        )

    def reveal(self, x, y, yaw):
        """Mark nodes the camera sees: in the sector, within range, line of sight not through a
        (true) obstacle; the node under the robot is seen too (a short LiDAR stand-in). Each ray
        is sampled at half-node steps (every ray at once; samples past a ray's end are masked)."""
        c = np.array([int(x / RES), int(y / RES)])
        self.known[c[0], c[1]] = True
        off = self.fov.offsets
        bearing = np.arctan2(off[:, 1], off[:, 0])
        off = off[np.abs(wrap_angle_arr(bearing - yaw)) <= math.radians(57) / 2]
        if not len(off):
            return
        n = np.ceil(np.hypot(off[:, 0], off[:, 1]) * 2).astype(int)  # steps per ray
        s = np.arange(1, n.max())
        frac = s[None, :] / n[:, None]
        px = np.floor(c[0] + frac * off[:, :1] + 0.5).astype(int)
        py = np.floor(c[1] + frac * off[:, 1:] + 0.5).astype(int)
        on_ray = s[None, :] < n[:, None]
        inside = (px >= 0) & (px < self.gt.shape[0]) & (py >= 0) & (py < self.gt.shape[1])
        tx, ty = c[0] + off[:, 0], c[1] + off[:, 1]
        is_target = (px == tx[:, None]) & (py == ty[:, None])
        blocked = ~inside | (
            self.obstacle[px.clip(0, self.gt.shape[0] - 1), py.clip(0, self.gt.shape[1] - 1)]
            & ~is_target
        )
        ok = ~(blocked & on_ray).any(axis=1)
        ok &= (tx >= 0) & (tx < self.gt.shape[0]) & (ty >= 0) & (ty < self.gt.shape[1])
        self.known[tx[ok], ty[ok]] = True

    def grid(self) -> GridBox:
        flags = self.known.astype(np.uint8) * fr.KNOWN
        known_obst = self.known & self.obstacle
        flags[known_obst] |= fr.OBSTACLE
        safety = ndimage.binary_dilation(known_obst, self.disc) & self.known & ~known_obst
        flags[safety] |= fr.SAFETY_ZONE
        labels = np.where(self.known, self.gt, 0).astype(np.uint16)
        return GridBox(np.zeros(2), RES, labels, flags)

    def path_cost(self, grid: GridBox, t_f=0.8, class_cost=COST):
        """A* with the paper's cost over known free nodes (the planner without allow_unknown)."""
        free = fr.traversable_mask(grid.labels, grid.flags, TRAV)
        passable = free
        node_cost = class_cost[np.minimum(grid.labels, 8)]

        def cost(start_xy, goal_xy):
            s, g = grid.cell_of(start_xy), grid.cell_of(goal_xy)
            if not free[g] or not free[s]:
                return None
            dist = {s: 0.0}
            prev = {}
            heap = [(0.0, 0.0, s)]
            while heap:
                _, d, n = heapq.heappop(heap)
                if n == g:
                    path = [g]
                    while path[-1] in prev:
                        path.append(prev[path[-1]])
                    return d, grid.centres(np.array(path[::-1]))
                if d > dist.get(n, math.inf):
                    continue
                for a in (-1, 0, 1):
                    for b in (-1, 0, 1):
                        m = (n[0] + a, n[1] + b)
                        if (a, b) == (0, 0) or not (0 <= m[0] < 40 and 0 <= m[1] < 40):
                            continue
                        if not passable[m]:
                            continue
                        step = math.hypot(a, b) * RES + t_f * node_cost[m]
                        nd = d + step
                        if nd < dist.get(m, math.inf):
                            dist[m], prev[m] = nd, n
                            h = math.hypot(m[0] - g[0], m[1] - g[1]) * RES
                            heapq.heappush(heap, (nd + h, nd, m))
            return None

        return cost

    def reachable_traversable(self, start_xy) -> np.ndarray:
        free = TRAV[self.gt] & ~self.obstacle & ~self.gt_safety
        return fr.reachable_mask(free, (int(start_xy[0] / RES), int(start_xy[1] / RES)))


def _params(max_range_m=4.0, follower=None, **kw) -> ExplorerConfig:
    """The explorer as these tests were written for it: the core's own defaults of the time
    (budget 600 s, a 4 m view, the follower at 0.5 m/s, 1.2 rad/s, 0.15 m), now the config's."""
    old = {"max_linear_mps": 0.5, "max_angular_radps": 1.2, "goal_tolerance_m": 0.15}
    follower = FollowerConfig(**{**old, **(follower or {})})
    kw.setdefault("time_budget_s", 600.0)
    return ExplorerConfig(view=ViewConfig(max_range_m=max_range_m), follower=follower, **kw)


def _explorer(params: ExplorerConfig, class_cost=COST) -> Explorer:
    """The explorer as the service builds it: path costs scored on the toy planner's scale."""
    flat, bound = fr.path_cost_scale(0.8, class_cost, RES)
    return Explorer(params, TRAV, 9, bound, flat)


def wrap_angle_arr(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _run(world: ToyWorld, params: ExplorerConfig, start=(1.0, 1.0, 0.0), dt=0.1, t_max=400.0):
    ex = _explorer(params)
    x, y, yaw = start
    clearance = math.inf
    obstacle_centres = (np.argwhere(world.obstacle) + 0.5) * RES
    t = 0.0
    while t < t_max and not ex.done:
        if round(t / dt) % 3 == 0:
            world.reveal(x, y, yaw)
            ex.update_grid(world.grid())
        ex.update_pose(x, y, yaw, t)
        reason = ex.wants_plan()
        if reason:
            ex.plan(world.path_cost(ex.grid), reason)
        v, w = ex.control()
        x += v * math.cos(yaw) * dt
        y += v * math.sin(yaw) * dt
        yaw = wrap_angle(yaw + w * dt)
        # distance from the robot centre to the nearest obstacle node's square
        d = np.abs(obstacle_centres - (x, y)) - RES / 2
        clearance = min(clearance, float(np.hypot(*np.maximum(d, 0).T).min()))
        t += dt
    return ex, clearance


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["nbv", "nearest_frontier"])
def test_explores_a_toy_garden_without_touching_obstacles(strategy):
    world = ToyWorld(_garden(1))
    params = _params(
        max_range_m=3.0,
        follower={"lookahead_m": 0.3, "max_linear_mps": 0.5},
        max_queries=6,
        time_budget_s=400,
        strategy=strategy,
    )
    ex, clearance = _run(world, params)
    reach = world.reachable_traversable((1.0, 1.0))
    coverage = (world.known & reach).sum() / reach.sum()
    assert ex.done, ex.state_dict()
    assert ex.done_reason in ("no_view_worth_it", "no_frontier")
    assert coverage >= 0.9, coverage
    st = ex.state_dict()
    assert st["strategy"] == strategy
    assert st["distance_m"] > 10
    assert sum(st["label_counts"].values()) > 20
    if strategy == "nbv":
        # the safety zone inflates obstacles by 0.35 m; corner cutting and late sightings (a
        # tree beside the 57-degree camera is mapped only when the robot turns to it) eat some:
        # 0.09-0.20 m over seeds 1-4 with the old score, 0.09-0.12 m with the new (issue 14)
        assert clearance > 0.07, clearance
        assert st["n_goals"] >= 3
    else:
        # no collision; the baseline drives along the edge of unknown space, where obstacles
        # are mapped late, and comes closer than the next-best view (0.00-0.20 m, seeds 1-4)
        assert clearance > 0.0, clearance


def test_grass_cost_shifts_travel_onto_terrain():
    """The planner's class cost reaches the explorer: with grass at cost 8 the robot drives on
    terrain more than with grass at cost 1 (same world, same start)."""
    shares = []
    for grass_cost in (1.0, 8.0):
        world = ToyWorld(_garden(2))
        cost = COST.copy()
        cost[1] = grass_cost
        params = _params(max_range_m=3.0, max_queries=6, time_budget_s=150)
        ex = _explorer(params, cost)
        x, y, yaw, t, dt = 1.0, 1.0, 0.0, 0.0, 0.1
        while t < 150 and not ex.done:
            if round(t / dt) % 3 == 0:
                world.reveal(x, y, yaw)
                ex.update_grid(world.grid())
            ex.update_pose(x, y, yaw, t)
            reason = ex.wants_plan()
            if reason:
                ex.plan(world.path_cost(ex.grid, class_cost=cost), reason)
            v, w = ex.control()
            x, y = x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt
            yaw = wrap_angle(yaw + w * dt)
            t += dt
        counts = ex.label_counts
        shares.append(counts[2] / max(1, counts[1] + counts[2]))
    assert shares[1] > shares[0], shares


def test_stops_when_nothing_is_left_and_on_budget():
    world = ToyWorld(_garden(3))
    world.known[:] = True  # everything already mapped: nothing to explore
    ex = _explorer(_params(empty_retry_s=0.2))
    ex.update_grid(world.grid())
    t = 0.0
    x, y, yaw = 1.0, 1.0, 0.0
    while not ex.done and t < 60:
        ex.update_pose(x, y, yaw, t)
        if ex.wants_plan():
            ex.plan(world.path_cost(ex.grid))
        v, w = ex.control()
        yaw = wrap_angle(yaw + w * 0.1)
        t += 0.1
    assert ex.done_reason == "no_frontier"
    assert t < 20  # one spin (about 9 s) and a few retries

    ex = _explorer(_params(time_budget_s=5.0))
    world = ToyWorld(_garden(3))
    world.reveal(1.0, 1.0, 0.0)
    ex.update_grid(world.grid())
    ex.update_pose(1.0, 1.0, 0.0, 100.0)
    ex.update_pose(1.0, 1.0, 0.0, 106.0)
    assert ex.wants_plan() is None and ex.done_reason == "time_budget"
    assert ex.control() == (0.0, 0.0)


def test_the_budget_starts_with_the_first_map_not_the_first_pose():
    # poses from t=0, but the map only arrives at t=50 (a stack still compiling): the 5 s budget
    # runs from there
    ex = _explorer(_params(time_budget_s=5.0))
    for t in range(0, 50, 5):
        ex.update_pose(1.0, 1.0, 0.0, float(t))
        assert ex.wants_plan() is None and not ex.done
    world = ToyWorld(_garden(3))
    world.reveal(1.0, 1.0, 0.0)
    ex.update_grid(world.grid())
    ex.update_pose(1.0, 1.0, 0.0, 50.0)
    ex.update_pose(1.0, 1.0, 0.0, 53.0)
    assert ex.elapsed_s() == pytest.approx(3.0)
    assert ex.wants_plan() is not None and not ex.done
    ex.update_pose(1.0, 1.0, 0.0, 56.0)
    assert ex.wants_plan() is None and ex.done_reason == "time_budget"
    # a restarted explorer keeps the budget's start, not the trajectory's
    again = _explorer(_params(time_budget_s=5.0))
    again.resume(ex.state_dict(), np.array(ex.trajectory))
    assert again.t_start == 50.0


def test_a_resumed_explorer_keeps_its_goal_and_drives_on_along_its_path():
    # a spare that takes over from the checkpoint (JSON, as on disk) with the robot further on
    world = ToyWorld(_garden(2))
    params = _params(max_range_m=3.0, follower={"lookahead_m": 0.3}, max_queries=6)
    ex = _explorer(params)
    x, y, yaw, t, dt = 1.0, 1.0, 0.0, 0.0, 0.1
    state, saved = None, None
    while t < 200.0 and not ex.done:
        world.reveal(x, y, yaw)
        ex.update_grid(world.grid())
        ex.update_pose(x, y, yaw, t)
        if reason := ex.wants_plan():
            ex.plan(world.path_cost(ex.grid), reason)
        if ex.goal is not saved:  # the service's checkpoint whenever the goal changes
            saved = ex.goal
            state = json.loads(json.dumps(ex.state_dict()))  # as on disk
            traj = np.array(ex.trajectory)
        v, w = ex.control()
        g = ex.goal
        if (
            g is not None
            and g.path_length_m > 1.5
            and ex.follower.remaining_length_m() < (g.path_length_m - 0.8)
        ):
            break  # 0.8 m along a long path: the process dies here
        x += v * math.cos(yaw) * dt
        y += v * math.sin(yaw) * dt
        yaw = wrap_angle(yaw + w * dt)
        t += dt
    assert ex.goal is not None and state["goal"] is not None, "no goal of more than 1.5 m"
    again = _explorer(params)
    again.resume(state, traj)
    again.update_grid(world.grid())
    again.update_pose(x, y, yaw, t)
    assert again.mode == "following"
    assert again.goal.choice.xy.tolist() == ex.goal.choice.xy.tolist()
    np.testing.assert_allclose(again.goal.path_xy, ex.goal.path_xy, atol=1e-3)
    # no new plan before the old one would have come, and it drives on, not back to the start
    assert again.wants_plan() is None
    assert again.follower.remaining_length_m() == pytest.approx(
        ex.follower.remaining_length_m(), abs=0.05
    )
    np.testing.assert_allclose(again.control(), ex.control(), atol=1e-3)


def test_a_path_that_becomes_blocked_triggers_a_replan():
    world = ToyWorld(_garden(4))
    world.known[:20, :] = True
    ex = _explorer(_params())
    ex.update_grid(world.grid())
    ex.update_pose(1.0, 1.0, 0.0, 0.0)
    out = ex.plan(world.path_cost(ex.grid))
    assert out.chosen is not None and ex.mode == "following"
    # an obstacle appears on the path, ahead of the robot
    g = ex.grid
    cells = g.cells_of(ex.follower.remaining)
    mid = cells[len(cells) // 2]
    g.flags[mid[0], mid[1]] |= fr.OBSTACLE
    assert ex.wants_plan() == "blocked"


def test_bad_pose_is_rejected():
    ex = _explorer(_params())
    with pytest.raises(ValueError):
        ex.update_pose(float("nan"), 0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        _params(max_range_m=0)


def test_a_robot_caught_in_a_safety_zone_backs_out_on_the_open_side():
    # a wall of obstacle nodes at ix = 10, its safety zone at ix = 9 and 11; free beyond.
    # The robot stands at ix = 9.6 (inside the zone, next to the wall): the nearest free node
    # is across the wall (ix = 12, 0.5 m away); the open side (ix = 8) is 0.3 m away too, but
    # the point is that a hop through the wall is never taken, even when it is shorter.
    labels = np.full((24, 12), 2, np.uint16)
    flags = np.full((24, 12), fr.KNOWN, np.uint8)
    labels[10, :] = 4
    flags[10, :] |= fr.OBSTACLE
    flags[[8, 9, 11], :] |= fr.SAFETY_ZONE
    g = GridBox(np.zeros(2), RES, labels, flags)
    ex = _explorer(_params(start_search_radius_m=1.0))
    ex.update_grid(g)
    free = fr.traversable_mask(labels, flags, TRAV)
    x, y = 9.9 * RES, 6.5 * RES  # 2 cm from the wall node's edge, closer to the far side's free
    comp, reach, starts = ex._starts(free, (x, y))
    (start,) = [starts[c] for c in starts if comp[starts[c]] == comp[5, 5]]
    assert start[0] == 7  # the open side, not ix = 12 across the wall
    # the far side is a separate component with no clear hop: not reachable from here
    assert not reach[15, 5]
    assert reach[3, 3]


def test_nearest_frontier_goes_by_travel_distance_not_straight_line():
    """A frontier 1.8 m away behind a wall (13 m to drive round) and one 4.8 m away in the open:
    nearest_frontier takes the open one, facing the unknown; a periodic plan keeps it."""
    labels = np.full((40, 20), 2, np.uint16)
    flags = np.full((40, 20), fr.KNOWN, np.uint8)
    flags[0:10, 15:20] = 0  # unknown behind the wall
    flags[30:40, 0:5] = 0  # unknown in the open
    labels[flags == 0] = 0
    labels[0:38, 10] = 4
    flags[0:38, 10] |= fr.OBSTACLE
    g = GridBox(np.zeros(2), RES, labels, flags)
    ex = _explorer(_params(strategy="nearest_frontier"))
    ex.update_grid(g)
    ex.update_pose(5.5 * RES, 5.5 * RES, 0.0, 0.0)

    def straight(start, goal):
        return float(np.hypot(*(goal - start))), np.array([start, goal])

    out = ex.plan(straight)
    c = out.chosen
    assert c is not None and ex.goal is not None
    assert c.cell[0] == 29 and c.cell[1] <= 5, c.cell
    assert abs(wrap_angle(c.yaw)) < math.pi / 2  # faces +x, the unknown
    assert c.score == pytest.approx(-np.hypot(*(c.cell - [5, 5])) * RES, abs=0.5)
    ex.update_pose(6.5 * RES, 5.5 * RES, 0.0, 5.0)
    again = ex.plan(straight, "periodic")
    assert ex.goal.choice is c and not again.switched
    assert ex.state_dict()["strategy"] == "nearest_frontier"


def _walled_in(false_wall: bool):
    """A 40 x 40 lawn, all of it known, cut at x = 2.8-3.0 m by a hedge row: labels the map got
    wrong (`false_wall`: the lawn is really there) or a real one. The robot starts left of it in a
    pocket smaller than the lawn beyond."""
    truth = np.full((40, 40), 1, np.uint16)
    truth[:, 0] = truth[:, -1] = truth[0, :] = truth[-1, :] = 4
    world = ToyWorld(truth.copy())
    world.known[:] = True
    seen = truth.copy()
    seen[14:15, :] = 4  # the row the map sees
    if not false_wall:
        world = ToyWorld(seen.copy())
        world.known[:] = True
    return world, seen


def _loop_with_a_map_that_clears(world, seen, t_max=240.0, known=None):
    """The explorer against a map holding `seen`, which clears a false obstacle node once the
    robot has stood within 1.2 m of it facing it (the graph's evidence, in short); `known`: the
    nodes the map knows (default: all)."""
    ex = _explorer(_params(empty_retry_s=0.2))
    x, y, yaw, t = 0.8, 4.0, math.pi, 0.0
    looked = []
    while t < t_max and not ex.done:
        cells = np.argwhere(OBST[seen] & ~world.obstacle)
        if len(cells):
            d = (cells + 0.5) * RES - (x, y)
            facing = np.cos(np.arctan2(d[:, 1], d[:, 0]) - yaw) > 0.8
            cleared = (np.hypot(*d.T) < 1.2) & facing
            seen[tuple(cells[cleared].T)] = world.gt[tuple(cells[cleared].T)]
        w = ToyWorld(seen.copy())
        w.known[:] = True if known is None else known
        ex.update_grid(w.grid())
        ex.update_pose(x, y, yaw, t)
        if ex.wants_plan():
            ex.plan(w.path_cost(ex.grid))
            if ex._looking and (not looked or looked[-1] is not ex.goal):
                looked.append(ex.goal)
        v, om = ex.control()
        x += v * math.cos(yaw) * 0.1
        y += v * math.sin(yaw) * 0.1
        yaw = wrap_angle(yaw + om * 0.1)
        t += 0.1
    return ex, looked, seen


def test_a_robot_walled_in_by_wrong_labels_looks_again_and_the_wall_clears():
    """No view is left (the whole lawn is known) but free lawn lies beyond a hedge row the map
    got wrong: the explorer drives up to the row and faces it, the map clears it, and the run
    ends as a finished one (no frontier), not as a robot closed in."""
    world, seen = _walled_in(false_wall=True)
    ex, looked, seen = _loop_with_a_map_that_clears(world, seen)
    assert looked, "it never went to look again"
    assert abs(looked[0].choice.xy[0] - 2.7) < 0.5  # the reachable side of the row
    assert abs(wrap_angle(looked[0].choice.yaw)) < 0.5  # facing the row (+x)
    assert (~OBST[seen[14]]).sum() >= 4  # the row seen again: a gap the robot can pass
    assert ex.done_reason in ("no_frontier", "no_view_worth_it")


def test_a_robot_closed_in_by_its_map_says_so_after_its_looks():
    """The same, but the map keeps the row (a real hedge the robot cannot pass, or labels that
    stay wrong): after `recoveries` looks from places `recovery_spacing_m` apart, it ends
    `closed_in` (more seen ground beyond than within reach)."""
    world, seen = _walled_in(false_wall=False)
    ex, looked, _ = _loop_with_a_map_that_clears(world, seen)
    assert ex.done_reason == "closed_in"
    assert len(looked) == ex.config.recoveries == 3
    xy = np.array([g.choice.xy for g in looked])
    assert (np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(3) * 9 >= 1.0).all()


def test_no_look_for_pockets_smaller_than_the_reach():
    """A finished run whose unreachable seen ground (a bed behind a hedge) is smaller than what it
    can reach ends at once, without a look: the same walled lawn with the row moved near the far
    edge, so that the lawn beyond it is the smaller part."""
    truth = np.full((40, 40), 1, np.uint16)
    truth[:, 0] = truth[:, -1] = truth[0, :] = truth[-1, :] = 4
    truth[28:29, :] = 4  # a real row: the pocket beyond is 10 x 38 nodes, the reach far more
    world = ToyWorld(truth)
    world.known[:] = True
    ex, looked, _ = _loop_with_a_map_that_clears(world, truth.copy())
    assert not looked and ex.n_recoveries == 0
    assert ex.done_reason in ("no_frontier", "no_view_worth_it")


def _pocket_with_unknown(row):
    """A lawn cut by a real hedge row at `row`, the far end of the pocket beyond it unseen."""
    truth = np.full((40, 40), 1, np.uint16)
    truth[:, 0] = truth[:, -1] = truth[0, :] = truth[-1, :] = 4
    truth[row : row + 1, :] = 4
    known = np.ones(truth.shape, bool)
    known[34:39, 1:39] = False  # the far end of the pocket, never seen
    return ToyWorld(truth), truth, known


def test_a_frontier_beyond_the_reach_is_worth_a_look():
    """A pocket beyond a real row, smaller than the reach but more than a quarter of it, part of
    it not seen yet (a frontier the robot cannot reach): it looks again, `recoveries` times, and
    ends as a finished run, not closed in. A pocket under a quarter of the reach (the inside of a
    hedge is unknown too: a finished run's pockets border unknown ground) is no reason to look."""
    world, truth, known = _pocket_with_unknown(20)  # 13 x 38 known beyond, 19 x 38 within
    ex, looked, _ = _loop_with_a_map_that_clears(world, truth.copy(), known=known)
    assert len(looked) == ex.n_recoveries == ex.config.recoveries
    assert ex.done_reason in ("no_frontier", "no_view_worth_it")
    world, truth, known = _pocket_with_unknown(28)  # 5 x 38 known beyond, 27 x 38 within
    ex, looked, _ = _loop_with_a_map_that_clears(world, truth.copy(), known=known)
    assert not looked and ex.n_recoveries == 0
    assert ex.done_reason in ("no_frontier", "no_view_worth_it")
