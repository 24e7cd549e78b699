"""Navigation graph core against a slow, obvious reference: a dict of occupied voxels per node,
the highest one shown, and a brute-force distance check for the safety zone."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE
from smana.services.navgraph.graph import NavGraph

CLASSES = ClassTable.load("garden3drms")
GRASS, TERRAIN, HEDGE, TREE = 1, 2, 4, 8
RES, MAP_RES = 0.2, 0.1


class ReferenceGraph:
    """Every occupied voxel by node; a node shows the highest (obstacle first on a tie, then the
    larger sub-column id), is an obstacle by its class or by its column's rise over its lowest
    voxel, and the safety zone is recomputed from scratch by distances."""

    def __init__(
        self, nx, ny, res, radius, map_res, classes=CLASSES, forbidden_margin=True, step_m=0.25
    ):
        self.nx, self.ny, self.res, self.radius, self.map_res = nx, ny, res, radius, map_res
        self.step_m = step_m
        self.classes, self.forbidden_margin = classes, forbidden_margin
        self.columns: dict[tuple[int, int], dict[tuple[int, int], tuple[int, float]]] = {}

    def apply(self, centres, labels, surface):
        for (x, y, z), lab, s in zip(centres.tolist(), labels.tolist(), surface.tolist()):
            ix, iy = math.floor(x / self.res), math.floor(y / self.res)
            if not (0 <= ix < self.nx and 0 <= iy < self.ny):
                continue
            gz = math.floor(np.float32(z) / self.map_res)
            sub = ((math.floor(x / self.map_res) & 255) << 8) | (math.floor(y / self.map_res) & 255)
            col = self.columns.setdefault((ix, iy), {})
            if s:
                col[(gz, sub)] = (lab, float(np.float32(z)))
            else:
                col.pop((gz, sub), None)

    def state(self):
        labels = np.zeros((self.nx, self.ny), np.uint16)
        heights = np.full((self.nx, self.ny), np.nan, np.float32)
        obstacle = np.zeros((self.nx, self.ny), bool)
        known = np.zeros((self.nx, self.ny), bool)
        for (ix, iy), col in self.columns.items():
            if not col:
                continue
            ob = self.classes.obstacle_lut
            (gz, sub), (lab, z) = max(
                col.items(), key=lambda kv: (kv[0][0], ob[kv[1][0]], kv[0][1])
            )
            labels[ix, iy], heights[ix, iy], known[ix, iy] = lab, z, True
            # certain labels (no distribution): an obstacle class blocks at once, and so does a
            # column rising more than the step over its lowest voxel, whatever its label
            rise = z - min(zz for _, zz in col.values())
            obstacle[ix, iy] = ob[lab] or rise > self.step_m
        safety = np.zeros_like(obstacle)
        # the zone's centres: obstacles, and forbidden nodes (water) with the margin
        centre = obstacle | (known & self.classes.forbidden_lut[labels] & self.forbidden_margin)
        ox, oy = np.nonzero(centre)
        for ix in range(self.nx):
            for iy in range(self.ny):
                d = np.hypot(ox - ix, oy - iy) * self.res
                safety[ix, iy] = (not obstacle[ix, iy]) and bool((d <= self.radius + 1e-9).any())
        flags = (known * FLAG_KNOWN + obstacle * FLAG_OBSTACLE + safety * FLAG_SAFETY_ZONE).astype(
            np.uint8
        )
        return labels, heights, flags


def graph(bounds_min_xy, bounds_max_xy, **kw) -> NavGraph:
    config = NavgraphConfig(
        bounds_min_xy=bounds_min_xy, bounds_max_xy=bounds_max_xy, resolution_m=RES, **kw
    )
    return NavGraph(CLASSES, config)


def graph_state(g: NavGraph):
    return g.grid.box(0, 0, *g.grid.shape)


def voxel(ix_map, iy_map, iz, res=MAP_RES):
    return [(ix_map + 0.5) * res, (iy_map + 0.5) * res, (iz + 0.5) * res]


def integrate(g, vox, labels, occupied, **kw):
    return g.integrate(
        np.array(vox, np.float32).reshape(-1, 3),
        np.array(labels, np.uint16),
        np.array(occupied, np.uint8),
        **kw,
    )


def test_first_voxel_sets_then_highest_wins():
    g = graph((0, 0), (4, 4), robot_radius_m=0.0)
    up = integrate(g, [voxel(10, 10, 3)], [GRASS], [1])
    assert up.cells.tolist() == [[5, 5]]
    assert up.labels.tolist() == [GRASS] and up.heights[0] == pytest.approx(0.35)
    assert up.flags.tolist() == [FLAG_KNOWN]
    # A lower voxel does not change the node, a higher one does.
    up = integrate(g, [voxel(11, 10, 1)], [TERRAIN], [1])
    assert len(up.cells) == 0
    # At the same level the result does not depend on arrival order.
    up = integrate(g, [voxel(11, 10, 3)], [TERRAIN], [1])
    assert up.labels.tolist() == [TERRAIN]  # larger sub-column id
    up = integrate(g, [voxel(10, 11, 3)], [HEDGE], [1])
    assert up.labels.tolist() == [HEDGE]  # an obstacle wins a tie
    up = integrate(g, [voxel(11, 11, 7)], [TREE], [1])
    assert up.labels.tolist() == [TREE] and up.flags.tolist() == [FLAG_KNOWN | FLAG_OBSTACLE]
    # The top voxel changing label (fusion changed its mind) relabels the node.
    up = integrate(g, [voxel(11, 11, 7)], [HEDGE], [1])
    assert up.labels.tolist() == [HEDGE]


def test_clearing_recomputes_from_what_remains():
    g = graph((0, 0), (4, 4), robot_radius_m=0.4)
    ground = [voxel(10, 10, 0), voxel(11, 10, 0), voxel(10, 11, 1)]
    person = [voxel(10, 10, k) for k in range(2, 12)]
    integrate(g, ground, [GRASS, GRASS, TERRAIN], [1, 1, 1])
    integrate(g, person, [7] * len(person), [1] * len(person))
    n = g.node(1.1, 1.1)
    assert n["obstacle"] and n["label"] == 7 and n["height"] == pytest.approx(1.15)
    assert g.node(1.5, 1.1)["safety_zone"]  # 2 nodes away = 0.4 m = robot radius
    # The obstacle walks away: the map clears its voxels.
    up = integrate(g, person, [7] * len(person), [0] * len(person))
    n = g.node(1.1, 1.1)
    assert n["label"] == TERRAIN and n["height"] == pytest.approx(0.15) and not n["obstacle"]
    assert not g.node(1.5, 1.1)["safety_zone"]
    changed = {tuple(c) for c in up.cells.tolist()}
    assert (5, 5) in changed and (7, 5) in changed  # the node and its former safety zone
    # Clearing everything leaves an unknown node, not a ghost.
    integrate(g, ground, [GRASS, GRASS, TERRAIN], [0, 0, 0])
    n = g.node(1.1, 1.1)
    assert not n["known"] and n["label"] == 0 and math.isnan(n["height"])
    assert g.n_column_voxels == 0


def test_a_solid_person_leaving_uncovers_the_ground_with_default_capacity():
    g = graph((0, 0), (4, 4), robot_radius_m=0.4)
    ground = [voxel(i, j, 0) for i in (10, 11) for j in (10, 11)]
    person = [voxel(i, j, k) for i in (10, 11) for j in (10, 11) for k in range(1, 18)]
    integrate(g, ground, [GRASS] * 4, [1] * 4)
    integrate(g, person, [7] * len(person), [1] * len(person))
    assert g.node(1.1, 1.1)["obstacle"] and g.n_column_voxels == 4 + 68
    integrate(g, person, [7] * len(person), [0] * len(person))
    n = g.node(1.1, 1.1)
    assert n["known"] and n["label"] == GRASS and not g.node(1.5, 1.1)["safety_zone"]


def test_column_capacity_forgets_lowest_level_and_never_guesses():
    g = graph((0, 0), (4, 4), robot_radius_m=0.0, column_capacity=3)
    levels = [voxel(10, 10, k) for k in range(5)]
    up = integrate(g, levels, [GRASS] * 5, [1] * 5)
    assert g.n_column_voxels == 3 and [c[0] for c in g.column(5, 5)] == [4, 3, 2]
    # A voxel below the floor is ignored (counted); the list stays exact above it.
    up = integrate(g, [voxel(11, 11, 0)], [TERRAIN], [1])
    assert up.n_below_floor == 1 and g.n_column_voxels == 3
    up = integrate(g, levels[2:], [GRASS] * 3, [0] * 3)
    assert up.n_columns_lost == 1
    assert not g.node(1.1, 1.1)["known"]


def test_bad_rows_are_counted_and_bad_arrays_rejected():
    g = graph((0, 0), (4, 4))
    vox = [voxel(10, 10, 0), [np.nan, 1.0, 0.0], [50.0, 1.0, 0.0], voxel(12, 12, 0)]
    up = integrate(g, vox, [GRASS, GRASS, GRASS, 3], [1, 1, 1, 1])
    assert up.n_nonfinite == 1 and up.n_out_of_bounds == 1 and up.n_unknown_labels == 1
    assert g.node(1.25, 1.25)["label"] == 0 and g.node(1.25, 1.25)["known"]
    with pytest.raises(ValueError, match="centres"):
        g.integrate(np.zeros((3, 2), np.float32), np.zeros(3, np.uint16), np.ones(3, np.uint8))
    with pytest.raises(ValueError, match="labels"):
        g.integrate(np.zeros((3, 3), np.float32), np.zeros(2, np.uint16), np.ones(3, np.uint8))
    with pytest.raises(ValueError, match="values_kind"):
        g.integrate_delta(SimpleNamespace(values_kind="voxblox_esdf"))
    with pytest.raises(ValueError, match="robot_radius"):
        NavGraph(CLASSES, NavgraphConfig(robot_radius_m=-1))


def test_memory_follows_the_area_seen_not_the_bounds():
    small = graph((0, 0), (10, 10))
    huge = graph((-500, -500), (500, 500))
    patch = [voxel(i, j, 0) for i in range(40) for j in range(40)]
    for g in (small, huge):
        integrate(g, patch, [GRASS] * len(patch), [1] * len(patch))
    assert huge.grid.n_tiles == small.grid.n_tiles == 1
    # The 1 km bounds cost only their tile map (5000^2 nodes / 32^2 per tile, 4 bytes each).
    assert huge.nbytes - small.nbytes < 4 * (5000 // 32 + 1) ** 2 + 1024


voxel_ops = st.lists(
    st.lists(
        st.tuples(
            # A small graph (6 x 6 nodes of 2 x 2 voxels, 4 levels) so that voxels share
            # nodes and levels often: ties and clearings are the interesting cases.
            st.integers(0, 11),
            st.integers(0, 11),
            st.integers(0, 3),
            st.sampled_from([GRASS, TERRAIN, HEDGE, TREE, 0]),
            st.booleans(),  # occupied / cleared
        ),
        min_size=1,
        max_size=60,
    ),
    min_size=1,
    max_size=6,
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(deltas=voxel_ops, radius=st.sampled_from([0.0, 0.2, 0.3, 0.45]))
def test_random_deltas_match_reference(deltas, radius):
    g = graph((0, 0), (1.2, 1.2), robot_radius_m=radius, tile_size=4)
    ref = ReferenceGraph(6, 6, RES, radius, MAP_RES)
    before = ref.state()
    for delta in deltas:
        vox = np.array([voxel(x, y, z) for x, y, z, _, _ in delta], np.float32)
        labels = np.array([lab for *_, lab, _ in delta], np.uint16)
        occ = np.array([o for *_, o in delta], np.uint8)
        up = g.integrate(vox, labels, occ, map_resolution_m=MAP_RES)
        ref.apply(vox.astype(np.float64), labels, occ.astype(bool))
        after = ref.state()
        got = graph_state(g)
        np.testing.assert_array_equal(got[0], after[0])
        np.testing.assert_array_equal(got[1], after[1])
        np.testing.assert_array_equal(got[2], after[2])
        # The update lists exactly the nodes whose state differs from before.
        diff = (before[0] != after[0]) | (before[2] != after[2])
        diff |= ~((before[1] == after[1]) | (np.isnan(before[1]) & np.isnan(after[1])))
        assert sorted(map(tuple, up.cells.tolist())) == sorted(zip(*map(list, np.nonzero(diff))))
        before = after


def test_safety_zone_matches_brute_force_on_a_bigger_field():
    rng = np.random.default_rng(4)
    g = graph((0, 0), (8, 8), robot_radius_m=0.55, tile_size=8)
    ref = ReferenceGraph(40, 40, RES, 0.55, MAP_RES)
    for _ in range(4):
        xy = rng.integers(0, 80, size=(400, 2))
        vox = np.array([voxel(x, y, int(rng.integers(0, 3))) for x, y in xy], np.float32)
        labels = rng.choice([GRASS, TERRAIN, HEDGE], size=len(vox), p=[0.5, 0.45, 0.05])
        occ = rng.random(len(vox)) < 0.8
        g.integrate(vox, labels.astype(np.uint16), occ.astype(np.uint8))
        ref.apply(vox.astype(np.float64), labels, occ)
        want = ref.state()
        np.testing.assert_array_equal(graph_state(g)[2], want[2])


@pytest.mark.parametrize("margin", [True, False])
def test_safety_zone_surrounds_forbidden_nodes_as_obstacles(margin):
    """`forbidden_margin`: a node labelled water (a forbidden class) is a centre of the safety
    zone like an obstacle, and stops being one when its label changes; without the margin only
    obstacles are, against the brute-force reference, over relabelling and clearing."""
    wet = ClassTable.load("garden3drms_wet")
    water = next(c.id for c in wet.classes.values() if c.forbidden)
    rng = np.random.default_rng(7)
    config = NavgraphConfig(
        bounds_min_xy=(0, 0),
        bounds_max_xy=(6, 6),
        resolution_m=RES,
        robot_radius_m=0.45,
        tile_size=8,
        forbidden_margin=margin,
    )
    g = NavGraph(wet, config)
    ref = ReferenceGraph(30, 30, RES, 0.45, MAP_RES, classes=wet, forbidden_margin=margin)
    n_zone = []
    for _ in range(5):
        xy = rng.integers(0, 60, size=(300, 2))
        vox = np.array([voxel(x, y, int(rng.integers(0, 2))) for x, y in xy], np.float32)
        labels = rng.choice([GRASS, TERRAIN, HEDGE, water], size=len(vox), p=[0.4, 0.4, 0.02, 0.18])
        occ = rng.random(len(vox)) < 0.85
        g.integrate(vox, labels.astype(np.uint16), occ.astype(np.uint8))
        ref.apply(vox.astype(np.float64), labels, occ)
        want = ref.state()
        np.testing.assert_array_equal(graph_state(g)[2], want[2])
        n_zone.append(int((want[2] & FLAG_SAFETY_ZONE).astype(bool).sum()))
    # a lone water node: its neighbours within the radius are in the zone with the margin only
    g = NavGraph(wet, config)
    integrate(g, [voxel(20, 20, 0), voxel(24, 20, 0)], [water, GRASS], [1, 1])
    assert g.node(2.05, 2.05)["safety_zone"] == margin  # the water node (closed by its label)
    assert g.node(2.45, 2.05)["safety_zone"] == margin  # 2 nodes = 0.4 m away
    integrate(g, [voxel(20, 20, 0)], [GRASS], [1])  # relabelled grass: the zone goes
    assert not g.node(2.45, 2.05)["safety_zone"] and not g.node(2.05, 2.05)["safety_zone"]
    assert min(n_zone) > 0
    assert NavgraphConfig().forbidden_margin  # the default (docs/risk.md)


class DoubtingReference:
    """The doubt rule, slowly: per node a dict of voxels (label, probability step, height and
    the voxel's distribution (alt label, p_label, p_alt) steps), and an evidence count moved once
    per integration that changed the node's column."""

    def __init__(self, n, confirm=0, miss=2, step_m=0.25, classes=CLASSES, certain=True):
        """`certain`: labels of probability 1 are certain (the map sends no distribution)."""
        self.n, self.confirm, self.miss, self.step_m = n, confirm, miss, step_m
        self.certain = certain
        self.cap = max(2 * confirm, 8)
        self.ob = classes.obstacle_lut
        self.columns: dict[tuple[int, int], dict] = {}
        self.evidence: dict[tuple[int, int], int] = {}

    def apply(self, centres, labels, dists, occupied):
        """`dists`: per voxel (alt label, p_label, p_alt) in steps of 1/255."""
        changed = set()
        for (x, y, z), lab, d, occ in zip(
            centres.tolist(), labels.tolist(), dists, occupied.tolist()
        ):
            ix, iy = math.floor(x / RES), math.floor(y / RES)
            if not (0 <= ix < self.n and 0 <= iy < self.n):
                continue
            sub = ((math.floor(x / MAP_RES) & 255) << 8) | (math.floor(y / MAP_RES) & 255)
            key = (math.floor(np.float32(z) / MAP_RES), sub)
            col = self.columns.setdefault((ix, iy), {})
            value = (lab, int(d[1]), float(np.float32(z)), tuple(int(v) for v in d))
            if occ:
                old = col.get(key)
                if old is None or (old[0], old[3]) != (lab, value[3]):
                    col[key] = value
                    changed.add((ix, iy))
            elif col.pop(key, None) is not None:
                changed.add((ix, iy))
        for node in changed:
            col = self.columns[node]
            if not col:
                self.evidence[node] = 0
                continue
            vote, certain, _, _ = self._top_level(col)
            ev = self.evidence.get(node, 0)
            if vote:
                ev = self.cap if certain else min(ev + 1, self.cap)
            else:
                ev = max(ev - self.miss, -self.cap)
            self.evidence[node] = ev

    def _top_level(self, col):
        """(votes for an obstacle class, all certain, obstacle voxels, other voxels) of the
        highest level: a vote when all are certain and one has an obstacle class, or when at
        least half of them have one."""
        level = max(k[0] for k in col)
        at = {k: v for k, v in col.items() if k[0] == level}
        obs = {k: v for k, v in at.items() if self.ob[v[0]]}
        others = {k: v for k, v in at.items() if not self.ob[v[0]]}
        certain = self.certain and all(v[1] == 255 for v in at.values())
        vote = bool(obs) and (certain or 2 * len(obs) >= len(at))
        return vote, certain, obs, others

    def shown(self, node):
        """The voxel node shows: the vote's side when the vote is certain, the evidence positive
        or there is no other voxel; then the larger sub-column id."""
        col = self.columns[node]
        vote, certain, obs, others = self._top_level(col)
        pick = obs if vote and (certain or self.evidence[node] > 0 or not others) else others
        return pick[max(pick)]

    def flags(self):
        out = np.zeros((self.n, self.n), np.uint8)
        for node, col in self.columns.items():
            if not col:
                continue
            top = self.shown(node)
            rise = top[2] - min(v[2] for v in col.values())
            f = FLAG_KNOWN
            if rise > self.step_m:
                f |= FLAG_OBSTACLE
            elif self.ob[top[0]]:
                ev = self.evidence[node]
                certain = self.certain and top[1] == 255
                blocks = certain or (self.confirm > 0 and ev >= self.confirm)
                f |= FLAG_OBSTACLE if blocks else FLAG_DOUBTFUL
            out[node] = f
        return out


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    deltas=st.lists(
        st.lists(
            st.tuples(
                st.integers(0, 7),
                st.integers(0, 7),
                st.integers(0, 3),
                st.sampled_from([GRASS, TERRAIN, HEDGE, TREE]),
                st.sampled_from([0.4, 0.7, 1.0]),
                st.booleans(),
            ),
            min_size=1,
            max_size=40,
        ),
        min_size=1,
        max_size=10,
    ),
    confirm=st.sampled_from([0, 1, 3, 5]),
    miss=st.sampled_from([1, 2]),
    with_distribution=st.booleans(),
)
def test_uncertain_obstacle_labels_doubt_until_the_evidence_confirms_them(
    deltas, confirm, miss, with_distribution
):
    """Obstacle, doubtful and free nodes against the slow rule, over certain and uncertain
    labels: a column rising over the step blocks; the top level votes for an obstacle class (all
    certain and one has it, or half of them have one), the vote moves the evidence (+1, or -miss),
    the node shows the vote's side when certain, the evidence positive or nothing else is there;
    an obstacle class blocks when certain or, with `semantic_confirm` > 0, once its evidence
    reaches it. Certain means a label without a distribution: with one, not even a probability of
    1 is (`with_distribution`)."""
    g = graph(
        (0, 0),
        (0.8, 0.8),
        robot_radius_m=0.0,
        tile_size=4,
        semantic_confirm=confirm,
        semantic_miss_weight=miss,
    )
    ref = DoubtingReference(4, confirm, miss, certain=not with_distribution)
    mask = FLAG_KNOWN | FLAG_OBSTACLE | FLAG_DOUBTFUL
    for delta in deltas:
        vox = np.array([voxel(x, y, z) for x, y, z, *_ in delta], np.float32)
        labels = np.array([d[3] for d in delta], np.uint16)
        confs = np.array([d[4] for d in delta], np.float32)
        occ = np.array([d[5] for d in delta], np.uint8)
        if with_distribution:
            g.integrate(vox, labels, occ, map_resolution_m=MAP_RES, confidences=confs)
            steps = [(0, math.floor(min(max(c, 0.0), 1.0) * 255 + 0.5), 0) for c in confs.tolist()]
        else:  # a map without distributions: every label is certain
            g.integrate(vox, labels, occ, map_resolution_m=MAP_RES)
            steps = [(0, 255, 0)] * len(confs)
        ref.apply(vox.astype(np.float64), labels, steps, occ.astype(bool))
        np.testing.assert_array_equal(graph_state(g)[2] & mask, ref.flags())
        for node in ref.columns:
            if ref.columns[node]:
                assert graph_state(g)[0][node] == ref.shown(node)[0]


def test_one_wrong_label_on_the_lawn_is_doubtful_and_clears_when_views_disagree():
    """A single uncertain hedge label on flat ground makes no obstacle and no safety zone; with
    `semantic_confirm` 4, the hedge seen again and again is confirmed; the lawn seen again clears
    it; a real step (a column rising 0.4 m) blocks at once whatever its label."""
    g = graph((0, 0), (4, 4), robot_radius_m=0.4, semantic_confirm=4)
    lawn = [voxel(10, 10, 0)]
    integrate(g, lawn, [HEDGE], [1], confidences=np.array([0.9], np.float32))
    n = g.node(1.05, 1.05)
    assert n["doubtful"] and not n["obstacle"]
    assert not g.node(1.25, 1.05)["safety_zone"]  # no zone round a doubtful node
    for c in (0.8, 0.7, 0.6):  # three more views agree: evidence 4 = semantic_confirm
        integrate(g, lawn, [HEDGE], [1], confidences=np.array([c], np.float32))
    n = g.node(1.05, 1.05)
    assert n["obstacle"] and not n["doubtful"] and n["obstacle_evidence"] == 4
    assert NavgraphConfig().semantic_confirm == 0  # by default it would stay doubtful
    assert g.node(1.25, 1.05)["safety_zone"]
    for c in (0.5, 0.6):  # the lawn seen twice: 4 - 2 x 2 = 0 < 4
        integrate(g, lawn, [GRASS], [1], confidences=np.array([c], np.float32))
    n = g.node(1.05, 1.05)
    assert not n["obstacle"] and not n["doubtful"] and not g.node(1.25, 1.05)["safety_zone"]
    # a step: ground and a voxel 0.4 m over it, labelled grass, uncertain
    step = [voxel(20, 20, 0), voxel(20, 20, 4)]
    integrate(g, step, [GRASS, GRASS], [1, 1], confidences=np.array([0.5, 0.5], np.float32))
    assert g.node(2.05, 2.05)["obstacle"]


def test_a_lawn_mislabelled_now_and_then_stays_a_lawn():
    """Four lawn voxels seen four times, then for one update three of them come back as hedge
    (max fusion keeps such a label a while): the node's evidence is negative, so it shows its
    lawn voxel and is neither doubtful nor an obstacle; the hedge labels kept for three more
    updates do not turn it either (the evidence climbs from -8 by one a time)."""
    g = graph((0, 0), (4, 4), robot_radius_m=0.4)
    lawn = [voxel(10, 10, 0), voxel(11, 10, 0), voxel(10, 11, 0), voxel(11, 11, 0)]
    for c in (0.5, 0.6, 0.7, 0.8):
        integrate(g, lawn, [GRASS] * 4, [1] * 4, confidences=np.full(4, c, np.float32))
    assert g.node(1.05, 1.05)["obstacle_evidence"] == -8
    for c in (0.9, 0.8, 0.7, 0.6):
        conf = np.array([c, c, c, 0.5], np.float32)
        integrate(g, lawn, [HEDGE, HEDGE, HEDGE, GRASS], [1] * 4, confidences=conf)
        n = g.node(1.05, 1.05)
        assert n["label"] == GRASS and not n["doubtful"] and not n["obstacle"]
    assert g.node(1.05, 1.05)["obstacle_evidence"] == -4


def test_a_voxel_hit_once_makes_no_geometric_obstacle():
    """An occupancy map's voxel 0.4 m over the lawn (a wall smeared there by one noisy pose) makes
    no obstacle while its log-odds are under `solid_log_odds` (one hit: 0.85, two: 1.69), and
    does once they reach it (a third hit: 2.54); a signed-distance map's surface is solid as it
    is."""
    g = graph((0, 0), (4, 4), robot_radius_m=0.4)
    assert g.config.solid_log_odds == 2.0

    def delta(values, kind="log_odds"):
        centres = np.array([voxel(10, 10, 0), voxel(10, 10, 4)], np.float32)
        return SimpleNamespace(
            values_kind=kind,
            centres=centres,
            labels=np.array([GRASS, GRASS], np.uint16),
            occupied=np.ones(2, np.uint8),
            resolution_m=MAP_RES,
            values=np.array(values, np.float32),
        )

    g.integrate_delta(delta([3.5, 0.85]))
    assert not g.node(1.05, 1.05)["obstacle"]
    # and it does not set the node's height: the lawn's solid voxel does (a step to a smeared
    # voxel would cut the planner's edges on flat ground)
    assert g.node(1.05, 1.05)["height"] == pytest.approx(voxel(10, 10, 0)[2])
    g.integrate_delta(delta([3.5, 1.69]))
    assert not g.node(1.05, 1.05)["obstacle"]
    g.integrate_delta(delta([3.5, 2.54]))
    assert g.node(1.05, 1.05)["obstacle"]
    assert g.node(1.05, 1.05)["height"] == pytest.approx(voxel(10, 10, 4)[2])
    g.integrate_delta(delta([3.5, 1.69]))  # missed twice since: no longer solid
    assert not g.node(1.05, 1.05)["obstacle"]
    tsdf = graph((0, 0), (4, 4), robot_radius_m=0.4)
    tsdf.integrate_delta(delta([0.01, -0.02], "signed_distance"))
    assert tsdf.node(1.05, 1.05)["obstacle"]


def test_a_probability_of_one_from_a_map_is_no_certainty():
    """A hedge label on the lawn at probability 1 (Bayesian fusion saturates after two views
    that agree; noise-free labels come at 1) is doubtful when the map sends a distribution, and
    makes no safety zone; the same label from a map that sends none (a version-1 delta) is
    certain and blocks at once."""
    for with_distribution, blocks in ((True, False), (False, True)):
        g = graph((0, 0), (4, 4), robot_radius_m=0.4)
        conf = {"confidences": np.ones(1, np.float32)} if with_distribution else {}
        g.integrate(
            np.array([voxel(10, 10, 0)], np.float32),
            np.array([HEDGE], np.uint16),
            np.ones(1, np.uint8),
            map_resolution_m=MAP_RES,
            **conf,
        )
        n = g.node(1.05, 1.05)
        assert n["obstacle"] is blocks and n["doubtful"] is not blocks, n
        assert g.node(1.25, 1.05)["safety_zone"] is blocks
