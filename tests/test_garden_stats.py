"""The "3drms" garden layout holds the paper's statistics (section 4.3: 48 % of the surface free,
55 % of the traversable surface terrain) and its connectivity, for every seed the experiments use;
the "classic" layout stays what it was."""

from __future__ import annotations

import hashlib
from collections import deque

import numpy as np
import pytest
from scipy import ndimage

from smana.common.config.sim import GardenConfig
from smana.services.sim.worlds import BOX, GroundModel, Primitive, World
from smana.services.sim.worlds.garden import generate
from smana.services.sim.worlds.garden_3drms import FILL_MIN_RADIUS_M, _fill_beds, _Placer
from smana.services.sim.worlds.objects import GRASS, OBSTACLE, TERRAIN, WorldObject

ROBOT_RADIUS_M = 0.4  # navgraph.robot_radius_m: the safety zone the navigation graph keeps
EXPERIMENT_SEEDS = range(3, 13)


@pytest.fixture(scope="module", params=EXPERIMENT_SEEDS)
def garden(request) -> World:
    return generate(seed=request.param, layout="3drms")


def test_default_layout_is_the_papers():
    assert GardenConfig().layout == "3drms"


def test_free_and_terrain_shares_are_the_papers(garden):
    assert 0.44 <= garden.free_fraction() <= 0.52
    assert 0.50 <= garden.terrain_share() <= 0.60
    top = garden.top_class().data
    ground = np.isin(top, [GRASS, TERRAIN])
    assert garden.terrain_share() == pytest.approx((top == TERRAIN).sum() / ground.sum())


def test_spawn_is_a_clear_plaza_and_everything_connects(garden):
    x, y, _ = garden.spawn_pose(ROBOT_RADIUS_M)
    assert abs(x) < 0.2 and abs(y) < 0.2  # the centre itself is free
    # no object within 2.5 m of the centre: the robot starts in the open
    xs, ys = garden.top_class().cell_centres()
    near = np.hypot(*np.meshgrid(xs, ys, indexing="ij")) < 2.5
    assert set(np.unique(garden.top_class().data[near])) <= {GRASS, TERRAIN}
    assert garden.reachable_fraction(ROBOT_RADIUS_M) >= 0.85
    assert garden.reachable_fraction(ROBOT_RADIUS_M, TERRAIN) >= 0.98


def test_small_and_large_gardens():
    small = generate(seed=3, layout="3drms", size_m=6.0)
    assert small.reachable_fraction(ROBOT_RADIUS_M) >= 0.85
    assert small.reachable_fraction(ROBOT_RADIUS_M, TERRAIN) >= 0.98
    x, y, _ = small.spawn_pose(ROBOT_RADIUS_M)
    assert abs(x) < 0.2 and abs(y) < 0.2
    big = generate(seed=1, layout="3drms", size_m=30.0, ground_resolution_m=0.2)
    assert 0.44 <= big.free_fraction() <= 0.52
    assert 0.50 <= big.terrain_share() <= 0.60
    assert big.reachable_fraction(ROBOT_RADIUS_M) >= 0.85


def test_same_seed_same_garden():
    a, b = generate(seed=4, layout="3drms"), generate(seed=4, layout="3drms")
    assert np.array_equal(a.ground.classes, b.ground.classes)
    assert [o.primitives for o in a.objects] == [o.primitives for o in b.objects]
    other = generate(seed=5, layout="3drms")
    assert not np.array_equal(other.ground.classes, a.ground.classes)


def _fingerprint(world: World) -> str:
    h = hashlib.sha256()
    h.update(world.ground.heights.tobytes())
    h.update(world.ground.classes.tobytes())
    for o in world.objects:
        h.update(f"{o.kind}{o.class_id}".encode())
        for p in o.primitives:
            h.update(p.shape.encode())
            h.update(np.array([*p.centre, *p.half_extents, p.yaw], np.float64).tobytes())
    return h.hexdigest()[:16]


def test_classic_layout_is_unchanged():
    """Fingerprints taken from the generator before the "3drms" layout was added."""
    assert _fingerprint(generate(seed=3, layout="classic")) == CLASSIC_SEED3
    assert _fingerprint(generate(seed=5, size_m=6.0, layout="classic")) == CLASSIC_SEED5_6M


CLASSIC_SEED3 = "d24276be3637964a"
CLASSIC_SEED5_6M = "bea0a2b64c1b205b"


def _reachable_slow(ok: np.ndarray, start: tuple[int, int]) -> int:
    """Cells reachable from `start` through side-by-side neighbours: a plain flood fill."""
    seen, todo = {start}, deque([start])
    while todo:
        i, j = todo.popleft()
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            q = (i + di, j + dj)
            if 0 <= q[0] < ok.shape[0] and 0 <= q[1] < ok.shape[1] and ok[q] and q not in seen:
                seen.add(q)
                todo.append(q)
    return len(seen)


def _flood_fill_share(world: World, radius_m: float) -> float:
    ok = world.traversability(radius_m)
    x, y, _ = world.spawn_pose(radius_m)
    start = tuple(int(v) for v in ok.index_of(x, y))
    return _reachable_slow(ok.data, start) / ok.data.sum()


def test_reachable_fraction_matches_a_flood_fill():
    world = generate(seed=6, layout="3drms", size_m=8.0)
    got = world.reachable_fraction(ROBOT_RADIUS_M)
    assert got == pytest.approx(_flood_fill_share(world, ROBOT_RADIUS_M))
    # a flat lawn cut in two by a wall 1 m north of the centre: the south part is reachable
    n, res = 61, 0.1
    lawn = GroundModel((-3.0, -3.0), res, np.zeros((n, n)), np.full((n, n), GRASS, np.uint16))
    wall = Primitive(BOX, (0.0, 1.0, 0.5), (3.0, 0.1, 0.5))
    cut = World(lawn, [WorldObject("obstacle", OBSTACLE, (wall,))])
    share = cut.reachable_fraction(ROBOT_RADIUS_M)
    assert share == pytest.approx(_flood_fill_share(cut, ROBOT_RADIUS_M))
    assert 0.55 < share < 0.75  # about 3.5 m of the 6 m lie south of the wall, less its margin


def test_bed_filling_leaves_no_hole_bigger_than_its_limit():
    """The filling updates the holes' sizes near each new plant only; a full distance transform
    of what is left uncovered must find no hole it should have filled."""
    res, n = 0.1, 61
    xs = -3.0 + np.arange(n) * res
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    ground = GroundModel((-3.0, -3.0), res, np.zeros((n, n)), np.full((n, n), TERRAIN, np.uint16))
    bed = (np.abs(gx) < 2.5) & (np.abs(gy) < 2.5) & ~((np.abs(gx) < 0.8) & (gy > 0))
    placer = _Placer(ground, gx, gy)
    plants = _fill_beds(placer, bed, np.random.default_rng(0))
    assert len(plants) > 5
    left = ndimage.distance_transform_edt(bed & ~placer.covered) * res
    assert left.max() < FILL_MIN_RADIUS_M
    assert not (placer.covered & ~bed).any()  # nothing spills out of the bed


def test_generation_is_fast():
    """CPU time, not wall time: the machine is shared. About 0.25 s measured; 1.5 s allowed."""
    import time

    t0 = time.process_time()
    generate(seed=9, layout="3drms")
    assert time.process_time() - t0 < 1.5
