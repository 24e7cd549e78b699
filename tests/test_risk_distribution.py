"""Issue 29, item 2: the label distribution carried from the map to the graph.

Each back-end's delta rows against its slow reference (`RefOctree`, `RefTsdf`: the full Bayes
rule with Python containers), the graph's nodes against a dict of columns that keeps each voxel's
distribution, and old (version 1) deltas and patches reading as certain.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from smana.common.graph_copy import GraphCopy
from smana.common.messages import GraphPatch, MapDelta, MessageError, decode, encode
from smana.common.navgrid import RISK_LAYER_NAMES, NavGrid
from smana.services.mapper.semantic_map import SemanticMap
from smana.services.navgraph.service import to_patch
from tests.test_mapper_octree import RefOctree, random_cloud
from tests.test_mapper_tsdf import SEM_IDS, RefTsdf
from tests.test_navgraph_graph import CLASSES, MAP_RES, DoubtingReference, graph


def _rows_by_key(m: SemanticMap):
    core = m._core
    rows = core.rows(core.observed_index())
    return rows, [tuple(k) for k in rows.keys.tolist()]


def test_octree_bayes_delta_carries_its_top_two():
    rng = np.random.default_rng(5)
    m = SemanticMap("octree-bayes", 0.2, 3.5, 0.0)
    ref = RefOctree(0.2, 3.5, None, "bayes")
    for _ in range(3):
        pts, labels, conf, origin = random_cloud(rng, 400)
        pts[:80] = pts[80:160]  # several observations per voxel: a second class to carry
        d = m.integrate(pts, labels, conf, origin)
        ref.integrate(pts, labels, conf, origin.astype(np.float32))
        # what the delta of this cloud says about each voxel it lists is the voxel's state now
        for i, k in enumerate(d.keys.tolist()):
            want = ref.sem.get(tuple(k), [])
            want = want + [[0, 0.0]] * (2 - len(want))
            assert (d.labels[i], d.alt_labels[i]) == (want[0][0], want[1][0]), k
            np.testing.assert_allclose(
                [d.confidences[i], d.alt_confidences[i]], [want[0][1], want[1][1]], rtol=1e-6
            )
    rows, keys = _rows_by_key(m)
    assert (rows.alt_labels != 0).sum() > 20  # the case the test is about happened
    assert (rows.confidences + rows.alt_confidences <= 1 + 1e-6).all()


def test_octree_max_delta_carries_its_label_and_confidence_and_no_second_class():
    rng = np.random.default_rng(6)
    m = SemanticMap("octree-max", 0.2, 3.5, 0.0)
    ref = RefOctree(0.2, 3.5, None, "max")
    for _ in range(2):
        pts, labels, conf, origin = random_cloud(rng, 300)
        pts[:60] = pts[60:120]
        m.integrate(pts, labels, conf, origin)
        ref.integrate(pts, labels, conf, origin.astype(np.float32))
    rows, keys = _rows_by_key(m)
    assert (rows.alt_labels == 0).all() and (rows.alt_confidences == 0).all()
    for i, k in enumerate(keys):
        want = ref.sem.get(k, [[0, 0.0]])
        assert rows.labels[i] == want[0][0] and rows.confidences[i] == want[0][1], k


def test_tsdf_delta_carries_the_top_two_of_its_label_vector():
    rng = np.random.default_rng(21)
    m = SemanticMap("tsdf", 0.2, 4.0)
    ref = RefTsdf(0.2, 4.0)
    base = rng.uniform(-3, 3, (150, 3)).astype(np.float32)
    for _ in range(6):  # the same surfaces seen again with other labels: a second class to carry
        pts = base + rng.normal(0, 0.02, base.shape).astype(np.float32)
        labels = rng.choice([0, 1, 2, 4, 5, 6, 7, 8, 3], 150, p=[0.1, 0.4, 0.2] + [0.05] * 6)
        origin = rng.uniform(-0.3, 0.3, 3)
        m.integrate(pts, labels, None, origin)
        ref.integrate(pts, labels, origin)
    rows, keys = _rows_by_key(m)
    checked = 0
    for i, k in enumerate(keys):
        p = ref.vox[k][2]
        order = sorted(range(len(p)), key=lambda c: (-p[c], c))  # first most probable first
        if np.ptp(p) == 0:  # never labelled: no class, no second class
            assert rows.labels[i] == 0 and rows.alt_labels[i] == 0, k
            continue
        assert rows.confidences[i] == pytest.approx(p[order[0]], rel=2e-4), k
        assert rows.alt_confidences[i] == pytest.approx(p[order[1]], rel=2e-4, abs=1e-7), k
        if p[order[1]] - p[order[2]] > 1e-6 and p[order[0]] - p[order[1]] > 1e-6:
            assert rows.labels[i] == SEM_IDS[order[0]], k
            assert rows.alt_labels[i] == SEM_IDS[order[1]], k
            checked += 1
    assert checked > 50


@pytest.mark.parametrize("backend", ["octree-bayes", "tsdf"])
def test_a_saved_map_keeps_the_distribution(tmp_path, backend):
    rng = np.random.default_rng(2)
    m = SemanticMap(backend, 0.2, 4.0)
    for _ in range(3):
        pts, labels, conf, origin = random_cloud(rng, 300)
        pts[:80] = pts[80:160]
        m.integrate(pts, labels, conf, origin)
    before, keys = _rows_by_key(m)
    loaded = SemanticMap.load(m.save(tmp_path / "map.npz"))
    after, keys_after = _rows_by_key(loaded)
    assert keys == keys_after and (before.alt_labels != 0).any()
    for name in ("labels", "confidences", "alt_labels", "alt_confidences"):
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name), err_msg=name)


# -- the graph -----------------------------------------------------------------------------


def to_probability_steps(labels, confidences, alt_labels, alt_confidences, valid=CLASSES.valid_lut):
    """The slow reference of the kernel's rule: probabilities x 255, rounded, p_alt capped so the
    two never pass 255; a second class outside the table or of probability 0 is none; no
    confidences: certain."""
    m = len(labels)
    if confidences is None:
        return np.zeros(m, np.uint16), np.full(m, 255, np.uint8), np.zeros(m, np.uint8)
    steps = []
    for c, a, ac in zip(confidences.tolist(), alt_labels.tolist(), alt_confidences.tolist()):
        c = 1.0 if math.isnan(c) else min(max(c, 0.0), 1.0)
        p = math.floor(c * 255.0 + 0.5)
        ac = 0.0 if math.isnan(ac) else min(max(ac, 0.0), 1.0)
        pa = min(math.floor(ac * 255.0 + 0.5), 255 - p)
        if a == 0 or a >= len(valid) or not valid[a] or pa == 0:
            a, pa = 0, 0
        steps.append((a, p, pa))
    alt, p, pa = (np.array(v) for v in zip(*steps))
    return alt.astype(np.uint16), p.astype(np.uint8), pa.astype(np.uint8)


class ReferenceRiskGraph(DoubtingReference):
    """The doubting reference graph (tests/test_navgraph_graph.py), each voxel with its
    distribution; a node shows the one of the voxel that sets its label."""

    def risk(self):
        out = [np.zeros((self.n, self.n), np.uint16), np.full((self.n, self.n), 255, np.uint8)]
        out.append(np.zeros((self.n, self.n), np.uint8))
        for node, col in self.columns.items():
            if not col:
                continue
            for a, v in zip(out, self.shown(node)[3], strict=True):
                a[node] = v
        return out


def _random_update(rng, n, nx_map):
    ix = rng.integers(0, nx_map, n)
    iy = rng.integers(0, nx_map, n)
    iz = rng.integers(0, 4, n)
    centres = (np.stack([ix, iy, iz], 1) + 0.5) * MAP_RES
    labels = rng.choice([1, 2, 4, 8], n).astype(np.uint16)
    conf = rng.uniform(0.3, 1.0, n).astype(np.float32)
    alt = rng.choice([0, 1, 2, 4, 8, 3], n).astype(np.uint16)  # 3: not in the table
    alt_conf = (rng.uniform(0, 1, n) * (1 - conf)).astype(np.float32)
    occupied = (rng.uniform(size=n) < 0.8).astype(np.uint8)
    return centres.astype(np.float32), labels, conf, alt, alt_conf, occupied


def test_nodes_keep_the_distribution_of_the_voxel_that_sets_their_label():
    rng = np.random.default_rng(9)
    g = graph((0, 0), (2.4, 2.4), robot_radius_m=0.2)
    nx = g.grid.shape[0]
    ref = ReferenceRiskGraph(nx)
    seen = {}
    for step in range(12):
        centres, labels, conf, alt, alt_conf, occ = _random_update(rng, 60, 2 * nx)
        if step % 4 == 3:  # a delta without a distribution: certain voxels
            up = g.integrate(centres, labels, occ, map_resolution_m=MAP_RES)
            risk = to_probability_steps(labels, None, None, None)
        else:
            up = g.integrate(
                centres,
                labels,
                occ,
                map_resolution_m=MAP_RES,
                confidences=conf,
                alt_labels=alt,
                alt_confidences=alt_conf,
            )
            risk = to_probability_steps(labels, conf, alt, alt_conf)
        ref.apply(centres, labels, list(zip(*risk, strict=True)), occ)
        # what an update reports is the grid's state of those nodes
        for name in RISK_LAYER_NAMES:
            now = g.grid.read_risk(up.cells)[RISK_LAYER_NAMES.index(name)]
            np.testing.assert_array_equal(getattr(up, name), now, err_msg=name)
        for c, *r in zip(up.cells.tolist(), up.alt_labels, up.p_label, up.p_alt, strict=True):
            seen[tuple(c)] = r
    want = ref.risk()
    got = g.grid.box(0, 0, nx, nx, layers=RISK_LAYER_NAMES)
    for name, a, b in zip(RISK_LAYER_NAMES, got, want, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert (want[1] < 255).sum() > 20 and (want[0] > 0).sum() > 10
    # every node's last reported distribution is its state: consumers of the updates agree
    for (ix, iy), r in seen.items():
        assert [int(v) for v in r] == [int(a[ix, iy]) for a in got]


def test_probability_steps_round_and_never_exceed_one():
    g = graph((0, 0), (2.4, 2.4), robot_radius_m=0.0)
    centres = (np.array([[k, 0, 0] for k in range(6)]) * 2 + 0.5) * MAP_RES
    labels = np.array([1, 1, 2, 2, 1, 2], np.uint16)
    conf = np.array([1.0, 0.5, 0.7, 0.2, np.nan, 1.5], np.float32)
    alt = np.array([2, 2, 3, 1, 2, 1], np.uint16)  # 3: not in the table
    alt_conf = np.array([0.0, 0.5, 0.3, 0.9, 0.5, np.nan], np.float32)
    up = g.integrate(
        centres.astype(np.float32),
        labels,
        np.ones(6, np.uint8),
        map_resolution_m=MAP_RES,
        confidences=conf,
        alt_labels=alt,
        alt_confidences=alt_conf,
    )
    order = np.argsort(up.cells[:, 0])
    assert up.p_label[order].tolist() == [255, 128, 178, 51, 255, 255]
    assert up.alt_labels[order].tolist() == [0, 2, 0, 1, 0, 0]
    assert up.p_alt[order].tolist() == [0, 127, 0, 204, 0, 0]
    want = to_probability_steps(labels, conf, alt, alt_conf)
    for a, b in zip((up.alt_labels, up.p_label, up.p_alt), want, strict=True):
        assert a[order].tolist() == b.tolist()


def _delta(**over) -> MapDelta:
    d = MapDelta(
        resolution_m=MAP_RES,
        centres=np.array([[0.55, 0.55, 0.05], [1.05, 0.55, 0.05]], np.float32),
        labels=np.array([1, 2], np.uint16),
        confidences=np.array([0.6, 0.9], np.float32),
        occupied=np.ones(2, np.uint8),
        values=np.ones(2, np.float32),
        alt_labels=np.array([2, 0], np.uint16),
        alt_confidences=np.array([0.4, 0.0], np.float32),
    )
    for k, v in over.items():
        setattr(d, k, v)
    return d


def _as_version_1(msg) -> bytes:
    raw = msgpack.unpackb(encode(msg), raw=False)
    raw["_v"] = 1
    for name in ("alt_labels", "alt_confidences", "p_label", "p_alt"):
        raw.pop(name, None)
    return msgpack.packb(raw, use_bin_type=True)


def test_an_old_delta_reads_as_certain_and_a_new_one_as_sent():
    g = graph((0, 0), (2.4, 2.4), robot_radius_m=0.0)
    old = decode(_as_version_1(_delta()), MapDelta)
    assert not old.has_distribution and old.alt_labels.tolist() == [0, 0]
    up = g.integrate_delta(old)
    assert up.p_label.tolist() == [255, 255] and up.alt_labels.tolist() == [0, 0]
    new = decode(encode(_delta()), MapDelta)
    assert new.has_distribution
    up = g.integrate_delta(new)  # only the distribution changed: the nodes are reported
    assert sorted(up.p_label.tolist()) == [153, 229]  # float32 0.9 is 0.89999998
    node = g.node(0.55, 0.55)
    assert (node["alt_labels"], node["p_label"], node["p_alt"]) == (2, 153, 102)
    # a delta made without a distribution travels as one (it stays certain at the receiver)
    bare = MapDelta(
        resolution_m=MAP_RES,
        centres=np.zeros((1, 3), np.float32),
        labels=np.ones(1, np.uint16),
        confidences=np.full(1, 0.5, np.float32),
        occupied=np.ones(1, np.uint8),
        values=np.ones(1, np.float32),
    )
    assert not decode(encode(bare), MapDelta).has_distribution
    # a version-1 message carrying a version-2 field is refused, not half read
    raw = msgpack.unpackb(encode(_delta()), raw=False)
    raw["_v"] = 1
    with pytest.raises(MessageError) as err:
        decode(msgpack.packb(raw, use_bin_type=True), MapDelta)
    assert err.value.kind == "unknown_field"


def test_patches_carry_the_distribution_to_the_planners_copy_and_old_ones_read_certain():
    g = graph((0, 0), (2.4, 2.4), robot_radius_m=0.0)
    g.integrate_delta(_delta())
    patch = decode(encode(to_patch(g, *g.export(), seq=1, stamp_s=0.0)), GraphPatch)
    grid = NavGrid(g.grid.origin_xy, g.grid.shape, g.resolution_m, g.grid.tile_size)
    grid.add_risk_layers()
    copy = GraphCopy(grid, lambda kind, msg: None)
    copy.receive(patch)
    cells = patch.cells
    for a, b in zip(grid.read_risk(cells), g.grid.read_risk(cells), strict=True):
        np.testing.assert_array_equal(a, b)
    assert 153 in grid.read_risk(cells)[1].tolist()
    # the same nodes from a version-1 patch: certain again
    old = decode(_as_version_1(to_patch(g, *g.export(), seq=2, stamp_s=0.0)), GraphPatch)
    copy.receive(old)
    alt, p, pa = grid.read_risk(cells)
    assert (p == 255).all() and (alt == 0).all() and (pa == 0).all()
    # a copy without the layers (the explorer's) takes the patch and reads certain
    plain = GraphCopy(NavGrid(g.grid.origin_xy, g.grid.shape, g.resolution_m), lambda k, m: None)
    plain.receive(patch)
    assert not plain.grid.has_risk() and (plain.grid.read_risk(cells)[1] == 255).all()


def test_the_services_carry_the_distribution_from_map_to_patch(fake_stack):
    """mapper (octree-bayes) and navgraph on the fake zenoh: the graph navgraph answers with holds
    the distribution of the mapper's voxels, as a graph built from the mapper's snapshot does."""
    import dataclasses
    import sys
    from pathlib import Path

    from smana.common import keys
    from smana.common.query import request
    from tests.conftest import wait_for

    sys.path.insert(0, str(Path(__file__).parent / "support"))
    from publish_clouds import patch_cloud

    s = fake_stack
    s.service("mapper", "--set", 'mapper.backend="octree-bayes"', "--set", 'mapper.load=""')
    s.service("navgraph")
    s.wait_alive("mapper")
    s.wait_alive("navgraph")
    first = patch_cloud(0, 1)
    ground = first.labels == 2
    first.confidences = np.where(ground, 0.5, 0.9).astype(np.float32)
    # the same ground seen again as grass, as sure: each voxel now holds two classes
    second = dataclasses.replace(
        first, seq=2, labels=np.where(ground, 1, first.labels).astype(np.uint8)
    )
    for cloud in (first, second):
        s.session.put(keys.cloud(s.robot), encode(cloud))
        assert s.drained("mapper")
    graph_key = keys.query(s.robot, "navgraph", "graph")

    def graph_risk():
        reply = request(s.session, graph_key)
        return {
            tuple(c): (int(a), int(p), int(q))
            for c, a, p, q in zip(reply.cells.tolist(), *reply.risk(), strict=True)
        }

    def matches_mapper():
        ref = _default_graph()
        ref.integrate_delta(request(s.session, keys.query(s.robot, "mapper", "snapshot")))
        cells = ref.export()[0]
        want = {
            tuple(c): (int(a), int(p), int(q))
            for c, a, p, q in zip(cells.tolist(), *ref.grid.read_risk(cells), strict=True)
        }
        # the 2 m patch is 100 nodes, most of them ground that both classes share
        return graph_risk() == want and sum(1 for _, p, _ in want.values() if p < 200) >= 80

    assert wait_for(matches_mapper, 20), s.log("navgraph")
    alts = [a for a, _, _ in graph_risk().values()]
    assert alts.count(1) >= 80  # grass, second to terrain on the ground


def _default_graph():
    from smana.common.config import SmanaConfig
    from smana.services.navgraph.graph import NavGraph

    return NavGraph(CLASSES, SmanaConfig().navgraph)
