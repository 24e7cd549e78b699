"""`FleetMap` (services/mapper/fleet.py) against a slow, obvious reference: plain dicts per
voxel, the members' log-odds summed and their labels folded by a plain-Python copy of each
back-end's rule; and against one `SemanticMap` that integrates every member's clouds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.config import ConfigError
from smana.common.config.fleet import FleetConfig
from smana.common.config.mapper import MapperConfig
from smana.services.mapper.backends.occupancy import sensor_model
from smana.services.mapper.delta import Delta
from smana.services.mapper.fleet import FleetMap
from smana.services.mapper.semantic_map import SemanticMap

RES = 0.2
CLASSES = np.array([1, 2, 4, 8], np.uint16)


def cloud(seed: int, x0: float):
    """Points in a 3 m box starting at x0, seen from above its middle."""
    rng = np.random.default_rng(seed)
    n = 300
    pts = np.column_stack(
        [rng.uniform(x0, x0 + 3, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-0.5, 0.5, n)]
    ).astype(np.float32)
    labels = rng.choice(CLASSES, n)
    confs = rng.uniform(0.3, 1.0, n).astype(np.float32)
    return pts, labels, confs, np.array([x0 + 1.5, 0.0, 1.5])


def config(backend: str) -> MapperConfig:
    return MapperConfig(backend=backend, resolution_m=RES)


def member_maps(backend: str, areas):
    """Per member: its SemanticMap and the deltas of its clouds, in order."""
    out = []
    for m, clouds in enumerate(areas):
        sm = SemanticMap.from_config(config(backend))
        deltas = [sm.integrate(*cloud(100 * m + i, x0)) for i, x0 in enumerate(clouds)]
        out.append((sm, deltas))
    return out


def rows(d):
    return d.centres, d.labels, d.confidences, d.values


def as_dict(d) -> dict:
    keys = np.floor(d.centres / RES).astype(np.int64)
    return {
        tuple(k): (float(v), int(lab), float(c))
        for k, v, lab, c in zip(keys, d.values, d.labels, d.confidences)
    }


# -- the reference --------------------------------------------------------------------------------


def fuse_max_ref(state, label, conf, penalty=0.9):
    """Semantic Octomap's SemanticsMax::semanticFusion (mapper.octree.max_fusion "average")."""
    cl, cp = state
    if cl == 0:
        return label, conf
    if cl == label:
        return cl, (cp + conf) / 2
    if cp > conf:
        return cl, penalty * cp
    return label, penalty * conf


def fold_bayes_ref(observations, k: int, eps=1e-3):
    """Full distribution over k classes, uniform prior (exact while at most 3 classes are seen,
    which the top-3 storage keeps)."""
    p = {c: 1.0 / k for c in range(k)}
    for label, conf in observations:
        c = min(max(conf, eps), 1 - eps)
        q = (1 - c) / (k - 1)
        p = {i: v * (c if i == label else q) for i, v in p.items()}
        z = sum(p.values())
        p = {i: v / z for i, v in p.items()}
    best = max(p, key=p.get)
    return best, p[best]


def reference(backend: str, layers: list[dict]) -> dict:
    """key -> (log-odds, label, confidence) of the merged map, voxel by voxel."""
    _, _, c_min, c_max = sensor_model(config(backend).octree)
    ids = SemanticMap.from_config(config(backend)).class_ids  # the table's semantic classes
    out = {}
    for key in set().union(*layers):
        reports = [(m, layer[key]) for m, layer in enumerate(layers) if key in layer]
        lo = min(max(sum(v for _, (v, _, _) in reports), float(c_min)), float(c_max))
        obs = sorted((c, m, lab) for m, (_, lab, c) in reports if lab != 0)
        if not obs:
            label, conf = 0, 0.0
        elif backend == "octree-max":
            state = (0, 0.0)
            for c, _, lab in obs:
                state = fuse_max_ref(state, lab, c)
            label, conf = state
        else:
            idx = {int(c): i for i, c in enumerate(ids)}
            best, conf = fold_bayes_ref([(idx[lab], c) for c, _, lab in obs], len(ids))
            label = int(ids[best])
        out[key] = (lo, label, conf)
    return out


# -- the tests ------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["octree-max", "octree-bayes"])
def test_merged_map_is_the_sum_and_the_fold(backend):
    # r1 maps x in [0, 5], r2 x in [3, 8] and [9, 12]: overlapping and disjoint areas; two clouds
    # a place at most, so no value reaches a clamp
    members = member_maps(backend, [[0.0, 2.0], [3.0, 9.0]])
    fm = FleetMap(config(backend), ["r1", "r2"])
    for name, (_, deltas) in zip(["r1", "r2"], members):
        for d in deltas:
            fm.apply(name, *rows(d))
    got = as_dict(fm.observed_voxels())
    want = reference(backend, [as_dict(sm.observed_voxels()) for sm, _ in members])
    assert got.keys() == want.keys()
    for key, (lo, lab, conf) in want.items():
        g = got[key]
        assert g[0] == pytest.approx(lo, abs=1e-5), key
        assert g[1] == lab, key
        assert g[2] == pytest.approx(conf, rel=1e-4, abs=1e-6), key

    # occupancy equals one map that integrated every member's clouds
    single = SemanticMap.from_config(config(backend))
    for m, clouds in enumerate([[0.0, 2.0], [3.0, 9.0]]):
        for i, x0 in enumerate(clouds):
            single.integrate(*cloud(100 * m + i, x0))
    one = as_dict(single.observed_voxels())
    assert one.keys() == got.keys()
    for key, (lo, _, _) in one.items():
        assert got[key][0] == pytest.approx(lo, abs=1e-5)
    occ = fm.stats()
    assert occ["voxels_occupied"] == single.stats()["voxels_occupied"]
    assert occ["voxels_observed"] == len(got)
    assert occ["members"]["r1"]["deltas_applied"] == 2


def test_arrival_order_does_not_matter():
    members = member_maps("octree-max", [[0.0, 1.0, 2.0], [1.0, 2.0, 3.0]])
    streams = [[("r1", d) for d in members[0][1]], [("r2", d) for d in members[1][1]]]
    results = []
    for pattern in ([0, 0, 0, 1, 1, 1], [1, 1, 1, 0, 0, 0], [1, 0, 1, 0, 0, 1]):
        fm = FleetMap(config("octree-max"), ["r1", "r2"])
        at = [0, 0]
        for s in pattern:
            name, d = streams[s][at[s]]
            at[s] += 1
            fm.apply(name, *rows(d))
        results.append(as_dict(fm.observed_voxels()))
    assert results[0] == results[1] == results[2]


def test_deltas_report_what_changed():
    members = member_maps("octree-max", [[0.0, 1.0], [1.0]])
    fm = FleetMap(config("octree-max"), ["r1", "r2"])
    mirror: dict = {}
    for name, d in [("r1", members[0][1][0]), ("r2", members[1][1][0]), ("r1", members[0][1][1])]:
        mirror.update(as_dict(fm.apply(name, *rows(d))))
    assert mirror == as_dict(fm.observed_voxels())


def test_start_pose_frame_lands_where_the_world_frame_does():
    x, y, yaw = 1.0, -2.0, 0.5
    c, s = math.cos(yaw), math.sin(yaw)

    def to_odom(p):  # world -> the member's frame (it started at (x, y, yaw))
        d = p[..., :2] - [x, y]
        out = np.array(p, np.float64)
        out[..., 0] = c * d[..., 0] + s * d[..., 1]
        out[..., 1] = -s * d[..., 0] + c * d[..., 1]
        return out

    def to_world(p):
        out = np.array(p, np.float64)
        out[..., 0] = c * p[..., 0] - s * p[..., 1] + x
        out[..., 1] = s * p[..., 0] + c * p[..., 1] + y
        return out

    world = SemanticMap.from_config(config("octree-max"))
    odom = SemanticMap.from_config(config("octree-max"))
    fleet = FleetConfig(robots=["r1"], frame="start_pose", start_poses=[[x, y, yaw]])
    fm = FleetMap(config("octree-max"), ["r1"], fleet)
    for i, x0 in enumerate([0.0, 2.0]):
        pts, lab, conf, org = cloud(i, x0)
        world.integrate(pts, lab, conf, org)
        d = odom.integrate(to_odom(pts).astype(np.float32), lab, conf, to_odom(org))
        fm.apply("r1", *rows(d))
    want = np.floor(world.occupied_voxels().centres / RES).astype(np.int64)
    got = np.floor(fm.occupied_voxels().centres / RES).astype(np.int64)
    assert len(got) > 100
    near = np.abs(got[:, None, :] - want[None, :, :]).max(axis=2).min(axis=1) <= 1
    assert near.mean() > 0.95, near.mean()
    # every member voxel lands where its centre goes (several may share a fleet voxel), and the
    # fleet voxel sums their log-odds
    src = odom.observed_voxels()
    moved = to_world(src.centres.astype(np.float64))
    keys = [tuple(k) for k in np.floor(moved / RES).astype(np.int64)]
    want: dict = {}
    for k, v in zip(keys, src.values):
        want[k] = want.get(k, 0.0) + float(v)
    merged = {k: v[0] for k, v in as_dict(fm.observed_voxels()).items()}
    assert merged.keys() == want.keys()
    _, _, c_min, c_max = sensor_model(config("octree-max").octree)
    for k, v in want.items():
        assert merged[k] == pytest.approx(min(max(v, c_min), c_max), abs=1e-5)


def test_a_resync_replaces_a_layer_as_if_no_delta_was_lost():
    members = member_maps("octree-bayes", [[0.0, 2.0], [1.0, 2.5, 4.0]])
    full = FleetMap(config("octree-bayes"), ["r1", "r2"])
    lossy = FleetMap(config("octree-bayes"), ["r1", "r2"])
    for name, (_, deltas) in zip(["r1", "r2"], members):
        for i, d in enumerate(deltas):
            full.apply(name, *rows(d))
            if name == "r1" or i != 1:  # r2's second delta is lost
                lossy.apply(name, *rows(d))
    assert as_dict(lossy.observed_voxels()) != as_dict(full.observed_voxels())
    mirror = as_dict(lossy.observed_voxels())
    mirror.update(as_dict(lossy.replace("r2", *rows(members[1][0].observed_voxels()))))
    assert as_dict(lossy.observed_voxels()) == as_dict(full.observed_voxels()) == mirror
    assert lossy.replaced == [0, 1]

    # a member whose map restarted empty: its voxels leave the merged map (unknown again)
    gone = lossy.replace("r2", *rows(Delta.empty()))
    only_r1 = FleetMap(config("octree-bayes"), ["r1", "r2"])
    for d in members[0][1]:
        only_r1.apply("r1", *rows(d))
    assert as_dict(lossy.observed_voxels()) == as_dict(only_r1.observed_voxels())
    assert len(gone) > 0


def test_save_and_load_keep_the_layers(tmp_path):
    members = member_maps("octree-max", [[0.0], [2.0]])
    fm = FleetMap(config("octree-max"), ["r1", "r2"])
    for name, (_, deltas) in zip(["r1", "r2"], members):
        fm.apply(name, *rows(deltas[0]))
    path = fm.save(tmp_path / "fleet.npz")
    back = FleetMap.load(path, config("octree-max"), ["r1", "r2"])
    assert as_dict(back.observed_voxels()) == as_dict(fm.observed_voxels())
    assert back.stats()["members"] == fm.stats()["members"]
    assert back.stats()["members"]["r1"]["voxels"] > 0
    # the file is also the merged map for whoever reads maps
    assert as_dict(SemanticMap.load(path).observed_voxels()) == as_dict(fm.observed_voxels())
    with pytest.raises(ValueError, match="not a fleet map"):
        FleetMap.load(members[0][0].save(tmp_path / "r1.npz"), config("octree-max"), ["r1"])


def test_the_fusion_rule_is_the_cloud_kernels():
    """`fuse_labels` (what the fleet uses) and the cloud kernel fuse the same sequence the
    same way: points of one cloud all ending in one voxel, fused in point order (here the
    canonical one, by confidence)."""
    rng = np.random.default_rng(7)
    for backend in ("octree-max", "octree-bayes"):
        sm = SemanticMap.from_config(config(backend))
        n = 6
        pts = np.tile(np.float32([[1.01, 1.01, 0.01]]), (n, 1))
        labels = rng.choice(CLASSES, n)
        confs = np.sort(rng.uniform(0.2, 1.0, n)).astype(np.float32)  # the canonical order
        d = sm.integrate(pts, labels, confs, (0.0, 0.0, 1.0))
        hit = d.subset(d.occupied.astype(bool))
        sem_l, sem_p = sm._core.fuse_labels(1, np.zeros(n), labels, confs)
        assert hit.labels[0] == sem_l[0, 0] and hit.confidences[0] == sem_p[0, 0]


def test_tsdf_is_refused_in_one_line():
    with pytest.raises(ConfigError, match='mapper.source = "fleet".*tsdf'):
        FleetMap(config("tsdf"), ["r1"])


def test_an_auto_load_that_is_no_fleet_map_starts_empty(tmp_path):
    """`mapper.load = "auto"` finding a robot's map where the fleet's should be: the fleet map
    starts empty (the members' snapshots fill it in); a named file is an error."""
    import dataclasses

    from smana.common.config import SmanaConfig
    from smana.services.mapper.takeover import build_map

    robot_map = SemanticMap.from_config(config("octree-max"))
    robot_map.integrate(*cloud(0, 0.0))
    path = robot_map.save(tmp_path / "map.npz")
    base = SmanaConfig()
    fleet = FleetConfig(robots=["r1", "r2"])
    for load in ("auto", str(path)):
        mc = dataclasses.replace(
            config("octree-max"), source="fleet", load=load, save_path=str(path)
        )
        cfg = dataclasses.replace(base, mapper=mc, fleet=fleet)
        if load == "auto":
            fm = build_map(cfg, robot_map.class_table)
            assert isinstance(fm, FleetMap) and fm.stats()["voxels_observed"] == 0
        else:
            with pytest.raises(ValueError, match="not a fleet map"):
                build_map(cfg, robot_map.class_table)
