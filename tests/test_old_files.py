"""Files written before the label-distribution layers (issue 29, "old files still load"): each
format smana writes that holds a graph or what a graph is built from, made by the code before
the `riskmap` merge (tests/data/oldrisk/, README.md there says how), loaded by today's code.

- the mapper's map file (octree-bayes, octree-max, tsdf) and its journal beside an autosave: the
  format did not change, the voxels always held their distribution, so the graph rebuilt from an
  old file carries it (it is not certain) and is, node for node, the graph the old code built;
  under the default `planner.risk = "label"` it plans the old planner's paths;
- a version-1 MapDelta (a snapshot) and GraphPatch as the old code encoded them, and the
  explorer's `graph.npz` (which holds no distribution, then or now): the graph built from them
  reads as certain (p_label 255, no second class) and every risk mode plans on it exactly as
  `label` does, which is the old planner's path.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.common.config.planner import PlannerConfig
from smana.common.graph_copy import GraphCopy
from smana.common.messages import GraphPatch, MapDelta, decode
from smana.common.navgrid import P_SCALE, NavGrid
from smana.services.mapper.journal import JournalReader
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.navgraph.graph import NavGraph
from smana.services.planner.planner import RISK_MODES, Planner

DATA = Path(__file__).parent / "data" / "oldrisk"
CLASSES = ClassTable.load("garden3drms")
OLD = dict(np.load(DATA / "old_graph.npz"))
PAIRS = json.loads((DATA / "pairs.json").read_text())
BAYES = "octree-bayes"


def snapshot(m: SemanticMap) -> MapDelta:
    """What today's mapper answers on mapper/snapshot (`MapperService._message`)."""
    d = m.occupied_voxels()
    return MapDelta(
        resolution_m=m.resolution_m,
        backend=m.backend,
        centres=d.centres,
        labels=d.labels,
        confidences=d.confidences,
        occupied=d.occupied,
        values=d.values,
        values_kind=m.values_kind,
        alt_labels=d.alt_labels,
        alt_confidences=d.alt_confidences,
    )


def graph_of(delta: MapDelta) -> NavGraph:
    """The navgraph the fixtures' script built (tests/data/oldrisk/make_fixtures.py)."""
    config = NavgraphConfig(
        bounds_min_xy=[-1.0, -1.0], bounds_max_xy=[4.0, 4.0], resolution_m=0.2, robot_radius_m=0.2
    )
    g = NavGraph(CLASSES, config)
    g.integrate_delta(delta)
    return g


def assert_old_graph(grid: NavGrid, backend: str, offset=(0, 0)) -> tuple[int, int, int, int]:
    """The grid's nodes are the ones the old code built from the same file; returns its box."""
    box = tuple(int(v) for v in OLD[f"{backend}_box"])
    ix0, iy0 = box[0] - offset[0], box[1] - offset[1]
    got = grid.box(ix0, iy0, ix0 + box[2] - box[0], iy0 + box[3] - box[1])
    for name, a in zip(("labels", "heights", "flags"), got, strict=True):
        np.testing.assert_array_equal(a, OLD[f"{backend}_{name}"], err_msg=name)
    assert (got[2] & 1).sum() > 30  # known nodes: the comparison is not of two empty graphs
    return box


def assert_old_paths(grid: NavGrid, backend: str, modes, offset=(0, 0)) -> int:
    """Every pair planned under each of `modes` gives the old planner's result (found or not,
    the same cells, the same cost); returns how many paths were found."""
    found = 0
    for mode in modes:
        # the old planner's cost: without the clearance cost beside safety zones (added later)
        planner = Planner(grid, CLASSES, PlannerConfig(risk=mode, clearance_cost=0.0))
        for i, (a, b) in enumerate(PAIRS):
            for unknown in (False, True):
                name = f"{backend}_path{i}{'_unknown' if unknown else ''}"
                r = planner.plan(a, b, allow_unknown=unknown)  # metres in the world frame
                assert r.ok == bool(OLD[f"{name}_ok"]), (mode, name, r.message)
                if r.ok:
                    np.testing.assert_array_equal(
                        r.cells + offset, OLD[f"{name}_cells"], err_msg=f"{mode} {name}"
                    )
                    assert r.cost_total == pytest.approx(float(OLD[f"{name}_cost"]), abs=1e-9)
                    found += 1
    return found


def assert_certain(grid: NavGrid) -> None:
    cells = np.argwhere(np.ones(grid.shape, bool))
    alt, p_label, p_alt = grid.read_risk(cells)
    assert (p_label == P_SCALE).all() and (alt == 0).all() and (p_alt == 0).all()


@pytest.mark.parametrize("backend", ["octree-bayes", "octree-max", "tsdf"])
def test_an_old_map_file_loads_and_its_graph_is_the_old_one_with_the_voxels_distribution(backend):
    m = SemanticMap.load(DATA / f"map_{backend}.npz")
    assert m.backend == backend
    g = graph_of(snapshot(m))
    assert_old_graph(g.grid, backend)
    # the default planner (label) plans as the old one did
    assert assert_old_paths(g.grid, backend, ["label"]) >= 3
    # the voxels' distribution reaches the graph: an old map file is not read as certain
    known = np.argwhere(g.grid.box(0, 0, *g.grid.shape, layers=("flags",))[0] & 1)
    alt, p_label, p_alt = g.grid.read_risk(known)
    assert (p_label < P_SCALE).any()
    if backend == "octree-max":  # its label and confidence, no second class
        assert (alt == 0).all() and (p_alt == 0).all()
    else:
        assert (alt > 0).any() and (p_alt > 0).any()


def test_an_old_autosave_and_its_journal_replay_into_the_old_map():
    reader = JournalReader(DATA / "autosave.journal")
    reader.attach(SemanticMap.load(DATA / "autosave.npz"))
    reader.finish()
    reader.close()
    m = reader.map
    m.recount()
    books = reader.books
    assert books.skipped == "" and books.records == 2 and books.torn_bytes == 0
    assert books.service == {"clouds": 6}
    # the map the old code saved after the same six clouds, and so its graph, distributions too
    full = SemanticMap.load(DATA / f"map_{BAYES}.npz")
    a, b = m.observed_voxels(), full.observed_voxels()
    order_a, order_b = (np.lexsort(d.keys.T) for d in (a, b))
    for name in ("keys", "labels", "confidences", "alt_labels", "values"):
        np.testing.assert_array_equal(
            getattr(a, name)[order_a], getattr(b, name)[order_b], err_msg=name
        )
    # not to the bit: a voxel whose lower ranks alone move is in no delta, so in no journal
    # record (`_fuse_bayes`: "not a visible change"); here by less than 1e-9, far below a step
    # of p_alt (1 / 255), and today's code does the same with its own journal
    np.testing.assert_allclose(a.alt_confidences[order_a], b.alt_confidences[order_b], atol=1e-9)
    grid = graph_of(snapshot(m)).grid
    assert_old_graph(grid, BAYES)
    want = graph_of(snapshot(full)).grid
    every = np.argwhere(np.ones(grid.shape, bool))
    for got, expected in zip(grid.read_risk(every), want.read_risk(every), strict=True):
        np.testing.assert_array_equal(got, expected)


def test_an_old_snapshot_delta_builds_a_certain_graph_that_plans_as_label_in_every_mode():
    delta = decode((DATA / "delta_v1.msgpack").read_bytes(), MapDelta)
    assert not delta.has_distribution
    g = graph_of(delta)
    assert g.grid.has_risk()  # today's graph keeps the layers: they read certain
    assert_certain(g.grid)
    assert_old_graph(g.grid, BAYES)
    assert assert_old_paths(g.grid, BAYES, RISK_MODES) == 6 * len(RISK_MODES)


def test_an_old_patch_reads_certain_in_the_planners_copy_and_plans_as_label_in_every_mode():
    patch = decode((DATA / "patch_v1.msgpack").read_bytes(), GraphPatch)
    grid = NavGrid.from_bounds([-1.0, -1.0], [4.0, 4.0], patch.resolution_m)
    grid.add_risk_layers()  # the planner service's copy keeps the distributions patches carry
    notes = []
    GraphCopy(grid, lambda kind, msg: notes.append(kind)).receive(patch)
    assert notes == []
    assert_certain(grid)
    assert_old_graph(grid, BAYES)
    assert assert_old_paths(grid, BAYES, RISK_MODES) == 6 * len(RISK_MODES)


def test_an_old_graph_file_reads_certain_and_plans_as_label_in_every_mode():
    """The explorer's (and the replay's) graph.npz: dense labels, heights and flags over the
    known box; it never held a distribution. A grid made from it, with the risk layers as the
    planner keeps them, reads certain."""
    with np.load(DATA / "graph.npz") as f:
        g = {k: f[k] for k in f.files}
    assert set(g) == {"origin_xy", "resolution_m", "labels", "heights", "flags"}
    grid = NavGrid(g["origin_xy"], g["labels"].shape, float(g["resolution_m"]))
    grid.add_risk_layers()
    cells = np.argwhere(g["flags"] != 0)
    grid.apply_patch(
        cells, *(g[k][cells[:, 0], cells[:, 1]] for k in ("labels", "heights", "flags"))
    )
    assert_certain(grid)
    box = tuple(int(v) for v in OLD[f"{BAYES}_box"])
    assert_old_graph(grid, BAYES, offset=box[:2])
    assert assert_old_paths(grid, BAYES, RISK_MODES, offset=box[:2]) == 6 * len(RISK_MODES)
