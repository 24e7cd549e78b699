"""The run report's honest outcome: usable coverage (the reachable traversable area the final
graph knows as traversable), the false-obstacle and false-free areas, each against a slow,
obvious reference on small hand-made grids; a run that knows under half the reachable area as
usable, or that its own map closed in, says FAILED and exits 1; and the experiments count a robot
that did not move as a failure, never as missing data."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE
from smana.deploy.report import ground_truth as ev
from smana.deploy.report.checks import OUTCOME_WARNINGS, fleet_warnings, run_warnings
from smana.deploy.report.finish import finish
from smana.lab.experiments import exploration as ex
from smana.lab.experiments import navnoise as nn
from tests.test_eval_report import run  # noqa: F401 - the fixture: a small hand-made run

TRAVERSABLE = np.array([False, True, True, False, False])  # unknown, grass, terrain, hedge, water


def _reference(grid, cell_xy, reach, gt_obstacle, lut, area):
    """The same figures, one cell at a time, reading the node over each cell centre by hand."""
    res, (ox, oy) = float(grid["resolution_m"]), grid["origin_xy"]
    nx, ny = grid["flags"].shape
    n = {"usable": 0, "false_obstacle": 0, "false_free": 0, "known_reachable": 0, "doubtful": 0}
    for i in range(reach.shape[0]):
        for j in range(reach.shape[1]):
            x, y = cell_xy[i, j]
            a, b = int(np.floor((x - ox) / res)), int(np.floor((y - oy) / res))
            flags = label = 0
            if 0 <= a < nx and 0 <= b < ny:
                flags, label = int(grid["flags"][a, b]), int(grid["labels"][a, b])
            known = bool(flags & FLAG_KNOWN)
            blocked = known and bool(flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE))
            doubtful = known and not blocked and bool(flags & FLAG_DOUBTFUL)
            traversable = label < len(lut) and bool(lut[label])
            usable = known and not blocked and (traversable or doubtful)
            n["usable"] += usable and reach[i, j]
            n["false_obstacle"] += blocked and reach[i, j]
            n["false_free"] += usable and gt_obstacle[i, j]
            n["known_reachable"] += known and reach[i, j]
            n["doubtful"] += doubtful and reach[i, j]
    total = int(reach.sum())
    return {k: (v * area, v / total) for k, v in n.items()}


def _grid(rng, shape=(6, 5)):
    return {
        "origin_xy": np.array([-0.5, 0.0]),
        "resolution_m": 1.0,
        "flags": rng.integers(0, 16, shape).astype(np.uint8),  # doubtful (8) included
        "labels": rng.integers(0, 7, shape).astype(np.uint16),  # 5, 6: outside the table
    }


@pytest.mark.parametrize("seed", range(6))
def test_usable_false_obstacle_and_false_free_match_a_slow_reference(seed):
    rng = np.random.default_rng(seed)
    grid = _grid(rng)
    # a raster of 0.5 m cells over a larger box than the graph's: cells outside read unknown
    xs, ys = np.meshgrid(np.arange(16) * 0.5 - 1.0, np.arange(14) * 0.5 - 0.75, indexing="ij")
    cell_xy = np.stack([xs, ys], axis=-1)
    gt_obstacle = rng.random(xs.shape) < 0.2
    reach = ~gt_obstacle & (rng.random(xs.shape) < 0.8)
    got = ev.exploration_coverage(grid, cell_xy, reach, 0.25, TRAVERSABLE, gt_obstacle)
    want = _reference(grid, cell_xy, reach, gt_obstacle, TRAVERSABLE, 0.25)
    for name, (area, share) in want.items():
        assert got[f"{name}_area_m2"] == pytest.approx(area), name
        assert got[f"{name}_share"] == pytest.approx(share), name
    assert got["coverage"] == got["usable_share"]
    assert got["reachable_area_m2"] == pytest.approx(reach.sum() * 0.25)


def test_a_field_of_false_obstacles_is_known_but_not_usable():
    # 4 x 4 nodes of 1 m over a raster of 0.5 m cells, all reachable, one true hedge cell
    flags = np.full((4, 4), FLAG_KNOWN, np.uint8)
    labels = np.full((4, 4), 2, np.uint16)  # terrain
    flags[0, :] |= FLAG_OBSTACLE  # a false wall along x in [0, 1)
    flags[1, :] |= FLAG_SAFETY_ZONE  # its zone
    labels[2, 0] = 4  # water: known, no flag, but not traversable
    grid = {"origin_xy": np.zeros(2), "resolution_m": 1.0, "flags": flags, "labels": labels}
    xs, ys = np.meshgrid(np.arange(8) * 0.5 + 0.25, np.arange(8) * 0.5 + 0.25, indexing="ij")
    cell_xy = np.stack([xs, ys], axis=-1)
    gt_obstacle = np.zeros((8, 8), bool)
    gt_obstacle[7, 7] = True  # a true obstacle the graph calls terrain: false free
    reach = ~gt_obstacle
    got = ev.exploration_coverage(grid, cell_xy, reach, 0.25, TRAVERSABLE, gt_obstacle)
    assert got["known_reachable_share"] == pytest.approx(1.0)
    # x in [0, 2): blocked (32 cells); node (2, 0): water (4 cells); the obstacle cell left out
    assert got["false_obstacle_area_m2"] == pytest.approx(32 * 0.25)
    assert got["usable_area_m2"] == pytest.approx((64 - 32 - 4 - 1) * 0.25)
    assert got["usable_share"] == pytest.approx(27 / 63)
    assert got["false_free_area_m2"] == pytest.approx(0.25)
    assert got["false_free_share"] == pytest.approx(1 / 63)


def test_a_doubtful_node_is_usable_and_counted_apart():
    # 2 x 1 nodes of 1 m, both labelled hedge (not traversable); node 0 doubtful (passable at
    # the planner's doubtful cost), node 1 a plain hedge node; raster of 0.5 m cells
    flags = np.array([[FLAG_KNOWN | FLAG_DOUBTFUL], [FLAG_KNOWN]], np.uint8)
    labels = np.full((2, 1), 3, np.uint16)
    grid = {"origin_xy": np.zeros(2), "resolution_m": 1.0, "flags": flags, "labels": labels}
    xs, ys = np.meshgrid(np.arange(4) * 0.5 + 0.25, np.arange(2) * 0.5 + 0.25, indexing="ij")
    cell_xy = np.stack([xs, ys], axis=-1)
    gt_obstacle = np.zeros((4, 2), bool)
    gt_obstacle[0, 0] = True  # a true hedge under the doubtful node: the robot could drive in
    reach = ~gt_obstacle
    got = ev.exploration_coverage(grid, cell_xy, reach, 0.25, TRAVERSABLE, gt_obstacle)
    assert got["usable_area_m2"] == pytest.approx(3 * 0.25)  # node 0's reachable cells
    assert got["doubtful_area_m2"] == pytest.approx(3 * 0.25)
    assert got["false_free_area_m2"] == pytest.approx(0.25)  # the hedge cell under it
    flags[0, 0] |= FLAG_SAFETY_ZONE  # doubtful inside a zone: blocked, neither usable nor doubtful
    got = ev.exploration_coverage(grid, cell_xy, reach, 0.25, TRAVERSABLE, gt_obstacle)
    assert got["usable_area_m2"] == got["doubtful_area_m2"] == 0.0


def test_a_run_without_a_graph_knows_nothing():
    none = ev.no_coverage(12.0)
    assert none["coverage"] == none["usable_share"] == none["false_free_area_m2"] == 0.0
    assert none["reachable_area_m2"] == 12.0


def _metrics(usable=0.8, distance=5.0, done="no_frontier"):
    return {
        "explorer": {"done_reason": done, "path_queries": 3, "path_ok": 3},
        "exploration": {
            "distance_m": distance,
            "usable_share": usable,
            "usable_area_m2": 40 * usable,
            "reachable_area_m2": 40.0,
            "false_obstacle_share": 0.5,
        },
    }


def test_under_half_usable_is_a_warning_naming_why():
    assert run_warnings(_metrics(0.8), True) == []
    assert run_warnings(_metrics(0.5), True) == []  # half is enough
    (w,) = run_warnings(_metrics(0.3), True)
    assert w.startswith("the robot knows only 30.0 % of the reachable area as usable (under 50 %")
    assert "12.0 m2 of 40.0 m2" in w and "50.0 % of it is an obstacle or a safety zone" in w
    assert w.startswith(OUTCOME_WARNINGS)
    assert run_warnings(_metrics(0.3), False) == []  # not an exploration: nothing to judge


def test_an_explorer_closed_in_by_its_own_map_fails():
    (w,) = run_warnings(_metrics(0.8, done="closed_in"), True)
    assert w == "the robot's own map closed it in (explorer ended: closed_in)"
    assert w.startswith(OUTCOME_WARNINGS)


def test_a_fleet_under_half_usable_fails():
    fleet = {"sim": {"summary": "sim.json", "robot_contacts_total": 0}, "members": {}}
    assert fleet_warnings({**fleet, "usable_share": 0.7}) == []
    (w,) = fleet_warnings({**fleet, "usable_share": 0.2, "reachable_area_m2": 10.0})
    assert w.startswith("the fleet knows only 20.0 % of the reachable area as usable")


def test_a_robot_that_never_moved_and_knows_little_fails_and_exits_1(run, capsys):  # noqa: F811
    run_dir, cfg, _ = run
    # the fixture's robot stands at its spawn; its graph now knows a 1.2 m square round it
    with np.load(run_dir / "explorer" / "graph.npz") as g:
        graph = {k: g[k] for k in g.files}
    graph["flags"][:] = 0
    graph["flags"][12:18, 12:18] = FLAG_KNOWN
    np.savez(run_dir / "explorer" / "graph.npz", **graph)
    sup = SimpleNamespace(
        run_dir=run_dir.resolve(),
        config=cfg,
        service_config=cfg,
        procs={"explorer": SimpleNamespace(service="explorer")},
        ended="explorer finished",
        warnings=lambda: [],
    )
    assert finish(sup, run_dir, 0, 12.0) == 1
    out = capsys.readouterr().out
    m = json.loads((run_dir / "metrics.json").read_text())
    ex_ = m["exploration"]
    assert ex_["usable_share"] < 0.5 and ex_["coverage"] == ex_["usable_share"]
    assert "smana up: FAILED" in out
    assert "  warning: the robot did not move (0.00 m travelled)" in out
    assert "  warning: the robot knows only " in out
    usable = f"{ex_['usable_area_m2']:.1f} m2 = {100 * ex_['usable_share']:.1f} % of the reachable"
    (line,) = [w for w in out.splitlines() if "usable coverage (against ground truth)" in w]
    assert line.split("ground truth)")[1].strip().startswith(usable)


# -- experiments --------------------------------------------------------------------------------


def test_an_experiment_run_that_failed_on_its_robot_alone_is_a_counted_result():
    m = {"warnings": ["the robot did not move (0.02 m travelled)"], "exploration": {}}
    assert ex.outcome_failure(1, m)
    assert ex.outcome_failure(1, {"warnings": [run_warnings(_metrics(0.2), True)[0]]})
    assert not ex.outcome_failure(1, {"warnings": ["planner never became ready"]})
    assert not ex.outcome_failure(0, {"warnings": []})
    m = {
        "warnings": ["the robot did not move (0.02 m travelled)"],
        "exploration": {"coverage": 0.3, "distance_m": 0.02, "known_reachable_share": 0.9},
        "explorer": {"done_reason": "no_frontier", "explored_m2": 3.0},
    }
    row = ex.make_row(3, ex.Arm("a", 2.0), 1, m, {}, 1.0, 2.0)
    assert row["ok"] and row["run_failed"] and row["moved"] is False
    assert row["coverage"] == 0.3  # as measured; counted as 0 (a failure) in every number
    assert ex.counted(row, "coverage") == 0.0 and ex.counted(row, "terrain_share") == 0.0
    assert ex.counted(row, "distance_m") == 0.02


def _nav_rows():
    rows = []
    for seed in (3, 4, 5, 6, 7):
        for b in nn.BACKENDS:
            for p, still in (("clean", False), ("noisy", b == "octree-max")):
                rows.append(
                    {
                        "seed": seed,
                        "arm": nn.Condition(b, p).name,
                        "backend": b,
                        "perception": p,
                        "ok": True,
                        "exit_code": 1 if still else 0,
                        "moved": not still,
                        "distance_m": 0.02 if still else 10.0,
                        # a robot that stood still has no path: no true share in the data
                        "terrain_share_true": None if still else 0.9,
                        "coverage": 0.9,  # the old "known" figure a still robot scored
                        "time_to_95_s": None,
                    }
                )
    return rows


def test_navnoise_counts_a_robot_that_sat_still_as_a_failure_not_missing_data():
    rows = _nav_rows()
    assert len(nn.verdicts(rows)) == 5
    for v in nn.verdicts(rows):
        assert "(n = 0)" not in v["smana"], v
    octree = [v for v in nn.verdicts(rows) if v["claim"].startswith("octree-max")]
    assert len(octree) == 2
    for v in octree:
        assert v["verdict"] == "not reproduced", v
        assert "(n = 5)" in v["smana"]
        assert "did not move in 5 of 5 noisy runs, each counted as a failure (0)" in v["evidence"]
    summary = {d["arm"]: d for d in nn.summarise(rows)}
    still = summary["octree_max_noisy"]
    assert still["did_not_move"] == 5 and still["run_failed"] == 5
    assert still["coverage"].n == 5 and still["coverage"].mean == 0.0
    assert still["terrain_share_true"].n == 5 and still["terrain_share_true"].mean == 0.0
    assert summary["tsdf_noisy"]["run_failed"] == 0
    line = next(r for r in nn.arm_table(rows) if r.startswith("| octree-max, noisy"))
    assert "- (n = 0)" in line  # the map's share of a path never driven stays undefined
    assert "0.0 % [0.0, 0.0] (n = 5)" in line


@pytest.mark.parametrize("doc", ["README.md", "docs/tutorial.md"])
def test_the_docs_sample_summary_has_the_rows_the_summary_gives(doc):
    """The sample `smana up: ok` block of the README and the tutorial shows the rows
    `summary_rows` gives a simulated run today, in its order, headed by usable coverage."""
    from smana.deploy.report.render import summary_rows
    from tests.conftest import REPO

    block = (REPO / doc).read_text().split("\nsmana up: ok\n", 1)[1].split("```", 1)[0]
    shown = [line.strip().split("  ")[0] for line in block.splitlines() if line.strip()]
    m = {"exploration": _metrics()["exploration"], "explorer": {"explored_m2": 1.0}}
    assert shown == [a for a, _ in summary_rows(m)][1:]
    assert shown[0] == "usable coverage (against ground truth)"


def _drivable_reference(grid, lut, drove_xy, max_step, radius):
    """Breadth-first search node by node, the planner's rules written out by hand."""
    from collections import deque

    flags, labels, heights = grid["flags"], grid["labels"], grid["heights"]
    nx, ny = flags.shape
    res, (ox, oy) = float(grid["resolution_m"]), grid["origin_xy"]

    def passable(a, b):
        f, lab = int(flags[a, b]), int(labels[a, b])
        if not f & FLAG_KNOWN or f & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE):
            return False
        return bool(f & FLAG_DOUBTFUL) or (lab < len(lut) and bool(lut[lab]))

    seen, queue = set(), deque()
    r = int(radius / res)
    under = [(int(np.floor((x - ox) / res)), int(np.floor((y - oy) / res))) for x, y in drove_xy]
    for i, j in under:
        if 0 <= i < nx and 0 <= j < ny and passable(i, j) and (i, j) not in seen:
            seen.add((i, j))
            queue.append((i, j))
    for i, j in under if not seen else []:  # no passable node under it: those near it
        for a in range(i - r, i + r + 1):
            for b in range(j - r, j + r + 1):
                near = (a - i) ** 2 + (b - j) ** 2 <= r * r
                if near and 0 <= a < nx and 0 <= b < ny and passable(a, b) and (a, b) not in seen:
                    seen.add((a, b))
                    queue.append((a, b))
    while queue:
        i, j = queue.popleft()
        for a in (i - 1, i, i + 1):
            for b in (j - 1, j, j + 1):
                if (a, b) in seen or not (0 <= a < nx and 0 <= b < ny) or not passable(a, b):
                    continue
                if abs(float(heights[a, b]) - float(heights[i, j])) <= max_step:
                    seen.add((a, b))
                    queue.append((a, b))
    out = np.zeros((nx, ny), bool)
    for a, b in seen:
        out[a, b] = True
    return out


@pytest.mark.parametrize("seed", range(8))
def test_drivable_nodes_match_a_breadth_first_search(seed):
    rng = np.random.default_rng(100 + seed)
    shape = (14, 11)
    grid = {
        "origin_xy": np.array([-1.0, 0.5]),
        "resolution_m": 0.5,
        "flags": np.where(rng.random(shape) < 0.8, FLAG_KNOWN, 0).astype(np.uint8)
        | np.where(rng.random(shape) < 0.1, FLAG_OBSTACLE, 0).astype(np.uint8)
        | np.where(rng.random(shape) < 0.1, FLAG_SAFETY_ZONE, 0).astype(np.uint8)
        | np.where(rng.random(shape) < 0.15, FLAG_DOUBTFUL, 0).astype(np.uint8),
        "labels": rng.integers(0, 7, shape).astype(np.uint16),
        "heights": (rng.random(shape) * 0.6).astype(np.float32),  # steps of 0 to 0.6 m
    }
    grid["heights"][rng.random(shape) < 0.05] = np.nan
    drove = rng.uniform([-1.0, 0.5], [6.0, 6.0], (int(rng.integers(1, 4)), 2))
    radius = [0.0, 0.5, 1.0][seed % 3]
    got = ev.drivable_nodes(grid, TRAVERSABLE, drove, 0.3, radius)
    want = _drivable_reference(grid, TRAVERSABLE, drove, 0.3, radius)
    assert np.array_equal(got, want)


def test_a_hedge_top_the_map_doubts_is_not_drivable():
    # a row of nodes: lawn at 0 m, a hedge edge (obstacle), hedge tops at 1 m the map doubts
    flags = np.array(
        [[FLAG_KNOWN], [FLAG_KNOWN], [FLAG_KNOWN | FLAG_OBSTACLE]]
        + [[FLAG_KNOWN | FLAG_DOUBTFUL]] * 3,
        np.uint8,
    )
    labels = np.array([[1], [1], [3], [3], [3], [3]], np.uint16)
    heights = np.array([[0.0], [0.05], [0.9], [1.0], [1.0], [1.0]], np.float32)
    grid = {
        "origin_xy": np.zeros(2),
        "resolution_m": 1.0,
        "flags": flags,
        "labels": labels,
        "heights": heights,
    }
    drivable = ev.drivable_nodes(grid, TRAVERSABLE, np.array([[0.5, 0.5]]), 0.3)
    assert drivable[:, 0].tolist() == [True, True, False, False, False, False]
    xs = np.arange(6) + 0.5
    cell_xy = np.stack([xs, np.full(6, 0.5)], axis=-1)[:, None, :]
    reach = np.zeros((6, 1), bool)
    reach[:2] = True
    gt_obstacle = ~reach
    got = ev.exploration_coverage(grid, cell_xy, reach, 1.0, TRAVERSABLE, gt_obstacle, drivable)
    assert got["usable_area_m2"] == 2.0 and got["false_free_area_m2"] == 0.0
    # without the step rule the hedge tops were usable: three cells falsely free
    got = ev.exploration_coverage(grid, cell_xy, reach, 1.0, TRAVERSABLE, gt_obstacle)
    assert got["false_free_area_m2"] == 3.0
