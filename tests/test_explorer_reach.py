"""What the explorer counts as reachable joins nodes as the planner does
(`frontier.step_components`): 8-connected, across height steps up to planner.max_step_m.
Against a breadth-first search written out by hand, and in the explorer: a doubtful hedge top
1 m above the lawn is no place to look from."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest

from smana.common.config.explorer import ExplorerConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox


def components_by_hand(free, heights, step):
    """Same partition as step_components: 8 neighbours, |dh| <= step (float32 step, float64
    limit, as the planner tests), NaN joins."""
    nx, ny = free.shape
    out = np.zeros(free.shape, np.int64)
    n = 0
    for i in range(nx):
        for j in range(ny):
            if not free[i, j] or out[i, j]:
                continue
            n += 1
            out[i, j] = n
            todo = deque([(i, j)])
            while todo:
                a, b = todo.popleft()
                for da in (-1, 0, 1):
                    for db in (-1, 0, 1):
                        c, d = a + da, b + db
                        if (da, db) == (0, 0) or not (0 <= c < nx and 0 <= d < ny):
                            continue
                        if not free[c, d] or out[c, d]:
                            continue
                        dh = abs(np.float32(heights[c, d]) - np.float32(heights[a, b]))
                        if float(dh) > step:  # in float64, as numba compares in the planner
                            continue
                        out[c, d] = n
                        todo.append((c, d))
    return out


def same_partition(a, b) -> bool:
    """Two labellings name the same sets (ids may differ), 0 alike."""
    if ((a == 0) != (b == 0)).any():
        return False
    pairs = set(zip(a[a > 0].tolist(), b[b > 0].tolist(), strict=True))
    return len(pairs) == len({p[0] for p in pairs}) == len({p[1] for p in pairs})


def test_components_match_a_search_by_hand():
    rng = np.random.default_rng(4)
    for _ in range(60):
        shape = tuple(rng.integers(1, 25, 2))
        free = rng.random(shape) < rng.uniform(0.3, 0.95)
        heights = np.round(rng.normal(0, 0.3, shape), 1).astype(np.float32)
        heights[rng.random(shape) < 0.1] = np.nan
        step = float(rng.choice([0.1, 0.3, 0.5]))
        got = fr.step_components(free, heights, step)
        assert same_partition(got, components_by_hand(free, heights, step))
    # no heights, or no step limit: plain 8-connected components
    free = rng.random((20, 20)) < 0.6
    plain = components_by_hand(free, np.zeros((20, 20)), math.inf)
    assert same_partition(fr.step_components(free, None, 0.3), plain)
    assert same_partition(fr.step_components(free, np.ones((20, 20)), math.inf), plain)
    with pytest.raises(ValueError):
        fr.step_components(free, np.zeros((3, 3)), 0.3)


def test_a_hedge_top_above_the_lawn_is_not_reachable():
    trav = np.array([False, True, True, False, False])
    labels = np.full((30, 30), 2, np.uint16)
    flags = np.full((30, 30), fr.KNOWN, np.uint8)
    heights = np.zeros((30, 30), np.float32)
    heights[20:25, 5:25] = 1.0  # a raised patch the map calls terrain: no step climbs it
    grid = GridBox(np.zeros(2), 0.2, labels, flags, heights)
    ex = Explorer(ExplorerConfig(), trav, 5)
    ex.update_grid(grid)
    free = fr.traversable_mask(labels, flags, ex.traversable_lut)
    _, reach, _ = ex._starts(free, (1.0, 1.0))
    assert reach[22, 10]  # without the step rule (a core on its own): the patch too
    ex.max_step_m = 0.3  # the service sets the planner's
    _, reach, _ = ex._starts(free, (1.0, 1.0))
    assert reach[2, 2] and reach[19, 10] and not reach[22, 10]
