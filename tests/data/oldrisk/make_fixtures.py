"""Writes the files of tests/data/oldrisk/ with smana as it was BEFORE the label-distribution
layers (the parent of the `riskmap` merge, b4ef303): files written by code that knew nothing of
`alt_labels`, `p_label` or `p_alt`, for tests/test_old_files.py to load with today's code.

Run it against that tree, never today's (it refuses to, below; README.md beside it has the
commands): `smana` is a namespace package, so the old tree goes first on PYTHONPATH as `smana`.

Every file is made the way the product makes it: `SemanticMap.save` (the mapper's map file, per
back-end), `JournalWriter` (the mapper's journal beside an autosave), the explorer's and the
replay's `graph.npz` (their `np.savez_compressed` of `NavGrid.box`, copied here: that code sits
inside the services), and `encode` of a MapDelta snapshot and of a GraphPatch (version 1 on the
wire). `old_graph.npz` keeps what the old code built and planned, to compare with.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

import smana.common.navgrid as navgrid
from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.common.config.planner import PlannerConfig
from smana.common.messages import MapDelta, encode
from smana.services.mapper.journal import JournalWriter
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.navgraph.graph import NavGraph
from smana.services.navgraph.service import to_patch
from smana.services.planner.planner import Planner

if hasattr(navgrid, "RISK_LAYERS") or not navgrid.__file__.startswith("/tmp/oldrisk_pp/"):
    sys.exit(f"not the code before the risk layers: {navgrid.__file__}")

BACKENDS = ("octree-bayes", "octree-max", "tsdf")
MAP_RES = 0.2
# ground over x 0.4 to 2.8 m, y 0.3 to 1.3 m at z 0.62 and a trunk: inside 2 x 1 x 1 of the
# map's 1.6 m blocks with the TSDF's band (2 voxels), which keeps the files small (blocks are dense)
X_M, Y_M, GROUND_Z = (0.4, 2.8), (0.3, 1.3), 0.62
TRUNK_XY, TRUNK_R = (1.6, 0.8), 0.15
GRASS, TERRAIN, TREE = 1, 2, 8
# six clouds: the TSDF shows a surface voxel once it has weight 3 (min_weight) on both sides
ORIGINS = ((0.7, 0.8, 1.5), (2.5, 0.8, 1.5), (1.6, 1.2, 1.5)) * 2
AUTOSAVED = 4  # octree-bayes: the autosave after 4 clouds, the journal holds the last 2
# start -> goal pairs planned on every graph (m)
PAIRS = (((0.6, 0.5), (2.6, 1.1)), ((0.6, 1.1), (2.6, 0.5)), ((0.6, 0.8), (2.6, 0.8)))


def clouds():
    """Six clouds of a 2.4 x 1 m flat patch (terrain, a grass stripe) with a tree trunk; in each, a
    quarter of the ground points carry another ground class, so the maps hold doubt."""
    rng = np.random.default_rng(29)
    gx, gy = (np.arange(lo + 0.025, hi, 0.05) for lo, hi in (X_M, Y_M))
    x, y = (a.ravel() for a in np.meshgrid(gx, gy, indexing="ij"))
    ground = np.stack([x, y, np.full_like(x, GROUND_Z)], 1)
    truth = np.where(np.abs(x - 1.6) < 0.3, GRASS, TERRAIN)
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    z = np.arange(GROUND_Z + 0.1, 1.15, 0.05)
    tt, zz = (a.ravel() for a in np.meshgrid(t, z, indexing="ij"))
    cx, cy = TRUNK_XY
    trunk = np.stack([cx + TRUNK_R * np.cos(tt), cy + TRUNK_R * np.sin(tt), zz], 1)
    for origin in ORIGINS:
        noisy = truth.copy()
        flip = rng.random(len(noisy)) < 0.25
        noisy[flip] = np.where(noisy[flip] == GRASS, TERRAIN, GRASS)
        pts = np.concatenate([ground, trunk]).astype(np.float32)
        labels = np.concatenate([noisy, np.full(len(trunk), TREE)]).astype(np.uint16)
        conf = np.full(len(pts), 0.8, np.float32)
        yield pts, labels, conf, np.array(origin)


def snapshot(m: SemanticMap) -> MapDelta:
    """What the mapper answers on mapper/snapshot (its `_message` of `occupied_voxels()`)."""
    d = m.occupied_voxels()
    return MapDelta(
        stamp_s=3.0,
        seq=3,
        cloud_seq=3,
        backend=m.backend,
        resolution_m=m.resolution_m,
        centres=d.centres,
        labels=d.labels,
        confidences=d.confidences,
        occupied=d.occupied,
        values=d.values,
        producer="oldrisk",
        values_kind=m.values_kind,
    )


def graph_of(delta: MapDelta, classes: ClassTable) -> NavGraph:
    config = NavgraphConfig(
        bounds_min_xy=[-1.0, -1.0], bounds_max_xy=[4.0, 4.0], resolution_m=0.2, robot_radius_m=0.2
    )
    g = NavGraph(classes, config)
    g.integrate_delta(delta)
    return g


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    classes = ClassTable.load("garden3drms")
    reference = {}
    for backend in BACKENDS:
        m = SemanticMap(backend, MAP_RES, 6.0, raycast_range_m=0.6)
        journal = None
        for k, (pts, labels, conf, origin) in enumerate(clouds()):
            delta = m.integrate(pts, labels, conf, origin)
            if backend == "octree-bayes" and k + 1 == AUTOSAVED:
                m.save(out / "autosave.npz")
                journal = JournalWriter(out / "autosave.journal", m, {"clouds": k + 1})
            elif journal is not None:
                journal.append(delta.keys, {"clouds": k + 1})
        if journal is not None:
            journal.close()
        m.save(out / f"map_{backend}.npz")
        snap = snapshot(m)
        g = graph_of(snap, classes)
        box = g.grid.known_box()
        labels, heights, flags = g.grid.box(*box)
        reference[f"{backend}_box"] = np.array(box)
        reference[f"{backend}_labels"] = labels
        reference[f"{backend}_heights"] = heights
        reference[f"{backend}_flags"] = flags
        planner = Planner(g.grid, classes, PlannerConfig())
        for i, (a, b) in enumerate(PAIRS):
            for unknown in (False, True):  # through unknown nodes too: the TSDF's is sparse
                r = planner.plan(a, b, allow_unknown=unknown)
                name = f"{backend}_path{i}{'_unknown' if unknown else ''}"
                reference[f"{name}_ok"] = np.array(r.ok)
                reference[f"{name}_cells"] = r.cells
                reference[f"{name}_cost"] = np.array(r.cost_total)
        if backend == "octree-bayes":
            (out / "delta_v1.msgpack").write_bytes(encode(snap))
            (out / "patch_v1.msgpack").write_bytes(
                encode(to_patch(g, *g.export(), seq=7, stamp_s=3.0, producer="oldrisk"))
            )
            # the explorer's graph.npz (services/explorer/service.py, its final save), as is
            origin = g.grid.origin_xy + np.array(box[:2]) * g.grid.resolution_m
            np.savez_compressed(
                out / "graph.npz",
                origin_xy=origin,
                resolution_m=g.grid.resolution_m,
                labels=labels,
                heights=heights,
                flags=flags,
            )
    np.savez_compressed(out / "old_graph.npz", **reference)
    (out / "pairs.json").write_text(json.dumps([[list(a), list(b)] for a, b in PAIRS]) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
