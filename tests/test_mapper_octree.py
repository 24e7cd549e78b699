"""Octree back-ends against a slow, obvious reference (dicts and sets, one ray at a time), against
OctoMap itself (pyoctomap), and on hand-made fusion cases from the paper's description."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.services.mapper.backends.occupancy import OctreeConfig, logodds, sensor_model
from smana.services.mapper.semantic_map import SemanticMap

SEM_IDS = (1, 2, 4, 5, 6, 7, 8)  # garden3drms classes that carry a label
F32 = np.float32


# -- the slow reference ----------------------------------------------------------------------


def ref_ray_keys(o, e, res):
    """OctoMap computeRayKeys, transcribed line by line (float point3d, double tMax)."""

    def key(c):
        return math.floor(float(c) * (1.0 / res))

    ko = tuple(key(c) for c in o)
    ke = tuple(key(c) for c in e)
    if ko == ke:
        return []
    ray = [ko]
    d = [F32(e[i] - o[i]) for i in range(3)]
    length = F32(math.sqrt(float(F32(F32(d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]))))
    d = [F32(c / length) for c in d]
    step, tmax, tdelta = [0] * 3, [0.0] * 3, [0.0] * 3
    cur = list(ko)
    for i in range(3):
        step[i] = 1 if d[i] > 0 else (-1 if d[i] < 0 else 0)
        if step[i]:
            border = (cur[i] + 0.5) * res + float(F32(step[i] * res * 0.5))
            tmax[i] = (border - float(o[i])) / float(d[i])
            tdelta[i] = res / abs(float(d[i]))
        else:
            tmax[i] = tdelta[i] = np.finfo(np.float64).max
    while True:
        if tmax[0] < tmax[1]:
            dim = 0 if tmax[0] < tmax[2] else 2
        else:
            dim = 1 if tmax[1] < tmax[2] else 2
        cur[dim] += step[dim]
        tmax[dim] += tdelta[dim]
        if tuple(cur) == ke or min(tmax) > float(length):
            break
        ray.append(tuple(cur))
    return ray


class RefOctree:
    """OctoMap insertPointCloud + per-point semantic fusion, with Python containers."""

    def __init__(self, res, max_range, ray_m, fusion, config=None):
        self.res, self.max_range, self.ray_m, self.fusion = res, max_range, ray_m, fusion
        self.fp = config or OctreeConfig()
        self.l_hit, self.l_miss, self.c_min, self.c_max = sensor_model(self.fp)
        self.logodds: dict[tuple, np.float32] = {}
        self.sem: dict[tuple, list] = {}  # key -> [[label, prob], ...] best first

    def integrate(self, points, labels, confs, origin):
        o = [F32(c) for c in origin]
        free, occupied = set(), set()
        for p, lab, conf in zip(points, labels, confs, strict=True):
            d = [F32(p[i] - o[i]) for i in range(3)]
            dist = math.sqrt(float(F32(F32(d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])))
            hit = dist <= self.max_range
            ln = F32(dist)
            u = [F32(c / ln) for c in d]
            if hit:
                e = list(p)
            else:
                e = [F32(o[i] + F32(u[i] * F32(self.max_range))) for i in range(3)]
            s = o
            if self.ray_m is not None and (dist if hit else self.max_range) > self.ray_m:
                s = [F32(e[i] - F32(u[i] * F32(self.ray_m))) for i in range(3)]
            free.update(ref_ray_keys(s, e, self.res))
            if hit:
                k = tuple(math.floor(float(c) * (1.0 / self.res)) for c in p)
                occupied.add(k)
                if int(lab) in SEM_IDS:
                    self._fuse(k, int(lab), float(conf))
        for k in free | occupied:
            upd = self.l_hit if k in occupied else self.l_miss
            lo = self.logodds.get(k, F32(0.0))
            if (upd >= 0 and lo >= self.c_max) or (upd <= 0 and lo <= self.c_min):
                continue
            self.logodds[k] = F32(min(max(F32(lo + upd), self.c_min), self.c_max))

    def _fuse(self, k, lab, c):
        cur = self.sem.get(k)
        if self.fusion == "max":
            if cur is None:
                self.sem[k] = [[lab, F32(c)]]
                return
            cl, cp = cur[0][0], float(cur[0][1])
            if self.fp.max_fusion == "average":  # semantics_max.h, line by line
                if cl == lab:
                    cur[0][1] = F32((F32(cur[0][1]) + F32(c)) / 2.0)
                elif cp > float(F32(c)):
                    cur[0][1] = F32(cp * self.fp.max_disagree_factor)
                else:
                    cur[0] = [lab, F32(float(F32(c)) * self.fp.max_disagree_factor)]
                return
            if cl == lab:
                cur[0][1] = F32(cp + self.fp.max_same_gain * c * (1 - cp))
            elif c > cp:
                cur[0] = [lab, F32(self.fp.max_disagree_factor * c)]
            else:
                cur[0][1] = F32(self.fp.max_disagree_factor * cp)
            return
        # Bayes over all K classes explicitly, then keep the top 3
        n = len(SEM_IDS)
        eps = self.fp.bayes_min_confidence
        c = min(max(float(F32(c)), eps), 1 - eps)
        cur = cur or []
        stored = {lab_: float(p) for lab_, p in cur}
        rest = (max(1 - sum(stored.values()), 0.0) / (n - len(stored))) if n > len(stored) else 0
        prior = {cls: stored.get(cls, rest) for cls in SEM_IDS}
        like = {cls: c if cls == lab else (1 - c) / (n - 1) for cls in SEM_IDS}
        post = {cls: prior[cls] * like[cls] for cls in SEM_IDS}
        z = sum(post.values())
        # candidates are the stored classes then the measured one, ties keep that order
        cands = [cls for cls, _ in cur] + ([lab] if lab not in stored else [])
        top = sorted(cands, key=lambda cls: -post[cls])[:3]
        self.sem[k] = [[cls, F32(post[cls] / z)] for cls in top]


def random_cloud(rng, n, spread=3.0):
    pts = rng.uniform(-spread, spread, (n, 3)).astype(np.float32)
    labels = rng.choice(np.array([0, 1, 2, 4, 5, 6, 7, 8, 3]), n).astype(np.uint16)
    conf = rng.uniform(0.3, 1.0, n).astype(np.float32)
    origin = rng.uniform(-0.3, 0.3, 3)
    return pts, labels, conf, origin


def map_state(m: SemanticMap, top_only: bool = False) -> dict:
    """voxel key -> (log-odds, labels, probabilities); `top_only`: what a delta row shows."""
    core = m._core
    g = core.observed_index()
    rows = core.rows(g)
    lab, prob = core.top_classes(g)
    if top_only:
        lab, prob = lab[:, :1], prob[:, :1]
    return {
        tuple(k): (v, tuple(lab[i]), tuple(prob[i]))
        for i, (k, v) in enumerate(zip(rows.keys.tolist(), rows.values, strict=True))
    }


# -- tests ----------------------------------------------------------------------------------


@pytest.mark.parametrize("fusion", ["max", "max@gain", "bayes"])
@pytest.mark.parametrize("ray_m", [None, 0.7])
def test_octree_matches_slow_reference(fusion, ray_m):
    rng = np.random.default_rng(11)
    res, max_range = 0.2, 3.5
    fusion, _, rule = fusion.partition("@")
    config = OctreeConfig(max_fusion=rule or "average")
    m = SemanticMap(f"octree-{fusion}", res, max_range, ray_m or 0.0, config=config)  # 0: whole ray
    ref = RefOctree(res, max_range, ray_m, fusion, config)
    for _ in range(3):
        pts, labels, conf, origin = random_cloud(rng, 400)
        pts[:40] = pts[40:80]  # several points per voxel, labels in conflict
        conf[80:120] = np.round(conf[80:120], 1)  # and confidences that tie
        pts[80:120] = pts[120:160]
        m.integrate(pts, labels, conf, origin)
        ref.integrate(pts, labels, conf, origin.astype(np.float32))
    state = map_state(m)
    assert set(state) == set(ref.logodds)
    for k, (lo, labs, probs) in state.items():
        assert lo == ref.logodds[k], k
        want = ref.sem.get(k, [])
        got = [(lab, p) for lab, p in zip(labs, probs, strict=True) if lab != 0]
        assert [lab for lab, _ in got] == [lab for lab, _ in want], k
        if fusion == "max":  # both rules are float32 arithmetic the reference repeats exactly
            assert [p for _, p in got] == [p for _, p in want], k
        np.testing.assert_allclose([p for _, p in got], [p for _, p in want], rtol=1e-6)


def test_ray_keys_match_reference_on_grazing_rays():
    """Rays along voxel faces and through corners, where float rounding decides."""
    from smana.services.mapper.block_grid import octomap_ray_keys

    res = 0.1
    buf = np.empty((512, 3), np.int64)
    cases = [
        ((0.05, 0.05, 0.05), (2.05, 0.05, 0.05)),
        ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        ((0.1, 0.2, 0.3), (-1.3, 2.2, 0.3)),
        ((-0.05, 0.0, 0.0), (0.95, 1.0, 0.0)),
        ((0.3, 0.3, 0.3), (0.3, 0.3, -4.0)),
    ]
    rng = np.random.default_rng(2)
    for _ in range(200):
        a = np.round(rng.uniform(-2, 2, 3), 1)
        cases.append((tuple(a), tuple(a + np.round(rng.uniform(-3, 3, 3), 1))))
    for o, e in cases:
        o32, e32 = [F32(c) for c in o], [F32(c) for c in e]
        n = octomap_ray_keys(*o32, *e32, res, buf)
        assert [tuple(r) for r in buf[:n].tolist()] == ref_ray_keys(o32, e32, res), (o, e)


def test_octree_full_rays_equal_octomap():
    """Same voxels, same float32 log-odds as OctoMap's own insertPointCloud."""
    pyoctomap = pytest.importorskip("pyoctomap")
    rng = np.random.default_rng(5)
    res, max_range = 0.1, 4.0
    m = SemanticMap("octree-max", res, max_range, 0.0)
    tree = pyoctomap.OcTree(res)
    for _ in range(3):
        pts, labels, conf, origin = random_cloud(rng, 1500, spread=5.0)
        m.integrate(pts, labels, conf, origin)
        tree.insertPointCloud(
            pts.astype(np.float64), origin.astype(np.float32).astype(float), max_range, True
        )
    rows = m._core.rows(m._core.observed_index())
    assert len(rows) == tree.getNumLeafNodes()  # lazy_eval: no pruning, one leaf per voxel
    for k, v in zip(rows.keys.tolist(), rows.values, strict=True):
        node = tree.search(pyoctomap.OcTreeKey(k[0] + 32768, k[1] + 32768, k[2] + 32768))
        assert node is not None, k
        assert np.float32(node.getLogOdds()) == v, k


def test_points_beyond_range_carve_without_hit():
    m = SemanticMap("octree-max", 0.1, 2.0, 0.0)
    d = m.integrate(
        np.array([[5.05, 0.05, 0.05]], np.float32), np.array([1]), None, (0.05, 0.05, 0.05)
    )
    xs = sorted(k[0] for k in d.keys.tolist())
    assert xs == list(range(0, 20))  # free up to (not including) the voxel at 2 m
    assert not d.occupied.any() and (d.labels == 0).all()
    np.testing.assert_array_equal(d.values, logodds(0.4))


def test_ray_length_limits_carving_to_last_metre():
    m = SemanticMap("octree-max", 0.1, 10.0, 1.0)
    d = m.integrate(
        np.array([[5.05, 0.05, 0.05]], np.float32), np.array([2]), None, (0.05, 0.05, 0.05)
    )
    by_x = {k[0]: occ for k, occ in zip(d.keys.tolist(), d.occupied, strict=True)}
    assert sorted(by_x) == list(range(40, 51))
    assert by_x[50] == 1 and not any(by_x[x] for x in range(40, 50))


def test_endpoint_wins_over_free_within_one_cloud():
    m = SemanticMap("octree-max", 0.1, 10.0, 0.0)
    # the second ray passes through the first ray's end voxel
    pts = np.array([[1.05, 0.05, 0.05], [2.05, 0.05, 0.05]], np.float32)
    m.integrate(pts, np.array([1, 1]), None, (0.05, 0.05, 0.05))
    q = m.query(pts)
    assert q.occupied.all()
    np.testing.assert_array_equal(q.values, logodds(0.7))


def _one_voxel(fusion, observations, config=None):
    m = SemanticMap(f"octree-{fusion}", 0.1, 10.0, 0.0, config=config)
    p = np.array([[1.05, 0.05, 0.05]], np.float32)
    for lab, conf in observations:
        m.integrate(p, np.array([lab]), np.array([conf], np.float32), (0.05, 0.05, 0.05))
    return m, m.query(p)


def test_max_fusion_is_semantic_octomaps_semantics_max():
    """`SemanticsMax::semanticFusion(stored, observed)`, worked by hand: same label averages
    (so agreement never raises c above the larger of the two), a different label keeps the more
    confident one times 0.9, the observation winning a tie."""
    f32 = np.float32
    _, q = _one_voxel("max", [(1, 0.6), (1, 0.8)])
    assert q.labels[0] == 1 and q.confidences[0] == f32(f32(f32(0.6) + f32(0.8)) / 2)
    _, q = _one_voxel("max", [(1, 0.6), (1, 0.6), (1, 0.6)])
    assert q.confidences[0] == f32(0.6)  # agreement holds c, it does not raise it
    _, q = _one_voxel("max", [(1, 0.6), (4, 0.8)])
    assert q.labels[0] == 4 and q.confidences[0] == f32(float(f32(0.8)) * 0.9)
    _, q = _one_voxel("max", [(1, 0.6), (4, 0.5)])
    assert q.labels[0] == 1 and q.confidences[0] == f32(float(f32(0.6)) * 0.9)
    _, q = _one_voxel("max", [(1, 0.5), (4, 0.5)])
    assert q.labels[0] == 4 and q.confidences[0] == f32(0.45)  # a tie: the observation


def test_max_fusion_gain_variant_keeps_the_earlier_rule():
    """`mapper.octree.max_fusion = "gain"`: agreement raises c by gain * c_obs * (1 - c); a tie
    keeps the stored label."""
    config = OctreeConfig(max_fusion="gain")
    _, q = _one_voxel("max", [(1, 0.6), (1, 0.6)], config)
    assert q.labels[0] == 1 and q.confidences[0] == pytest.approx(0.6 + 0.5 * 0.6 * 0.4)
    _, q = _one_voxel("max", [(1, 0.6), (4, 0.8)], config)
    assert q.labels[0] == 4 and q.confidences[0] == pytest.approx(0.72)
    _, q = _one_voxel("max", [(1, 0.5), (4, 0.5)], config)
    assert q.labels[0] == 1 and q.confidences[0] == pytest.approx(0.45)


def test_bayes_fusion_keeps_top3_and_renormalises():
    k = len(SEM_IDS)
    m, q = _one_voxel("bayes", [(1, 0.8)])
    # uniform prior: posterior of the measured class is its likelihood share
    assert q.labels[0] == 1
    assert q.confidences[0] == pytest.approx(0.8, rel=1e-6)
    m, q = _one_voxel("bayes", [(1, 0.8), (2, 0.7), (4, 0.6), (5, 0.9)])
    labels, probs = m._core.top_classes(m._core.observed_index()[-1:])
    labels, probs = labels[0], probs[0].astype(float)
    assert len(set(labels.tolist())) == 3 and 0 not in labels
    assert list(probs) == sorted(probs, reverse=True)
    assert probs.sum() < 1.0  # the rest is spread over the other classes
    rest = (1 - probs.sum()) / (k - 3)
    assert (rest < probs).all()
    # a confident disagreement then flips the most probable class
    m, q = _one_voxel("bayes", [(1, 0.6), (2, 0.95), (2, 0.95)])
    assert q.labels[0] == 2


def test_delta_is_exactly_what_changed():
    rng = np.random.default_rng(3)
    for backend in ("octree-max", "octree-bayes"):
        m = SemanticMap(backend, 0.25, 3.0, 1.0)
        pts, labels, conf, origin = random_cloud(rng, 300)
        for it in range(4):
            before = map_state(m, top_only=True)
            d = m.integrate(pts if it % 2 else pts[::-1], labels, conf, origin)
            after = map_state(m, top_only=True)
            moved = {k for k, v in after.items() if before.get(k) != v}
            keys = [tuple(k) for k in d.keys.tolist()]
            assert len(keys) == len(set(keys))
            assert set(keys) == moved
            for k, lab, v in zip(keys, d.labels, d.values, strict=True):
                assert after[k][0] == v and after[k][1][0] == lab
            np.testing.assert_array_equal(d.occupied, (d.values > 0).astype(np.uint8))
            np.testing.assert_allclose(d.centres, (d.keys + 0.5) * 0.25, rtol=1e-6)


def test_growth_mid_cloud_gives_the_same_map():
    """Tiny initial storage forces resumes in the middle of clouds; the result must not change."""
    rng = np.random.default_rng(8)
    clouds = [random_cloud(rng, 2000, spread=6.0) for _ in range(2)]
    a = SemanticMap("octree-max", 0.15, 8.0, 0.0)
    b = SemanticMap("octree-max", 0.15, 8.0, 0.0)
    b._core._touched = np.empty(8, np.int64)
    for c in clouds:
        da, db = a.integrate(*c), b.integrate(*c)
        np.testing.assert_array_equal(da.keys, db.keys)  # same order: same walk
        np.testing.assert_array_equal(da.values, db.values)
    assert b._core.grid.n_blocks > 16  # the block columns grew too
    ra, rb = (m._core.rows(m._core.observed_index()) for m in (a, b))
    oa, ob = np.lexsort(ra.keys.T), np.lexsort(rb.keys.T)
    for f in ("keys", "labels", "confidences", "values"):
        np.testing.assert_array_equal(getattr(ra, f)[oa], getattr(rb, f)[ob])


@pytest.mark.parametrize(
    "points, labels, conf, msg",
    [
        (np.zeros((3, 2)), np.zeros(3), None, "N x 3"),
        (np.array([[0, 0, np.nan]], float), np.zeros(1), None, "NaN"),
        (np.zeros((2, 3)), np.zeros(3), None, "labels must have shape"),
        (np.zeros((2, 3)), np.array([0, 70000]), None, "0..65535"),
        (np.zeros((2, 3)), np.zeros(2, int), np.array([0.5, 1.5]), "confidences"),
        (np.zeros((2, 3), int), np.zeros(2, int), None, "floating"),
    ],
)
def test_bad_input_is_rejected_with_a_clear_error(points, labels, conf, msg):
    m = SemanticMap("octree-max", 0.1)
    with pytest.raises(ValueError, match=msg):
        m.integrate(points, labels, conf, (0, 0, 0))
    assert m.stats()["voxels_observed"] == 0


def test_memory_per_allocated_voxel_within_target():
    rng = np.random.default_rng(4)
    for backend in ("octree-max", "octree-bayes"):
        m = SemanticMap(backend, 0.1, 5.0, 1.0)
        m.integrate(*random_cloud(rng, 2000))
        assert m.stats()["bytes_per_allocated_voxel"] <= 32


def _kitti_scan() -> np.ndarray:
    from pathlib import Path

    path = Path(__file__).parent / "data" / "kitti" / "000000.bin"
    return np.fromfile(path, np.float32).reshape(-1, 4)[:, :3].copy()


def test_ray_walk_from_a_shared_origin_matches_reference_on_real_and_random_rays():
    """The per-scan set-up (`octomap_ray_origin` once, `octomap_ray_from` per ray, as the
    carving kernel walks a scan) visits exactly the keys of the slow transcription of OctoMap's
    computeRayKeys, on a real KITTI scan's rays and on random ones from an off-grid origin."""
    from smana.services.mapper.block_grid import octomap_ray_keys

    pts = _kitti_scan()[::97]  # ~1300 rays over the whole scan, every range
    rng = np.random.default_rng(7)
    rand = rng.uniform(-6, 6, (600, 3)).astype(F32)
    rand[:100] = np.round(rand[:100], 1)  # ends on voxel faces and corners
    buf = np.empty((4096, 3), np.int64)
    for res, origin, cloud in (
        (0.1, (0.0, 0.0, 0.0), pts[np.linalg.norm(pts, axis=1) < 25]),
        (0.3, (0.0, 0.0, 0.0), pts),
        (0.1, (0.137, -0.42, 1.73), rand),
        (0.2, (0.1, 0.2, 0.3), rand),
    ):
        o32 = [F32(c) for c in origin]
        for e in cloud:
            e32 = [F32(c) for c in e]
            n = octomap_ray_keys(*o32, *e32, res, buf)
            assert [tuple(r) for r in buf[:n].tolist()] == ref_ray_keys(o32, e32, res), (res, e)


@pytest.mark.parametrize(
    "res, max_range, ray_m", [(0.3, 30.0, None), (0.2, 12.0, None), (0.3, 30.0, 2.0)]
)
def test_octree_on_a_real_scan_matches_slow_reference(res, max_range, ray_m):
    """A KITTI scan (rays cut at max_range, and a ray_m limit) gives the reference's map: the
    carving kernel's shared-origin set-up walks what OctoMap walks, voxel for voxel."""
    pts = _kitti_scan()[::60]
    rng = np.random.default_rng(3)
    labels = rng.choice(np.array(SEM_IDS), len(pts)).astype(np.uint16)
    conf = rng.uniform(0.3, 1.0, len(pts)).astype(F32)
    origin = np.array([0.05, -0.02, 0.0])
    m = SemanticMap("octree-max", res, max_range, ray_m or 0.0)
    ref = RefOctree(res, max_range, ray_m, "max", OctreeConfig())
    m.integrate(pts, labels, conf, origin)
    ref.integrate(pts, labels, conf, origin.astype(F32))
    state = map_state(m)
    assert set(state) == set(ref.logodds)
    assert all(lo == ref.logodds[k] for k, (lo, _, _) in state.items())


def _carved_by_the_walk(points, origin, res, max_range, ray_m):
    """The voxels the carving kernel must mark for one cloud, in the order it first meets them,
    built ray by ray from `octomap_ray_keys` (the walk of `octomap_ray_next`, which the kernel
    transcribes inline) and OctoMap's end-point rule: key -> hit or not, and how many rays
    stopped on their length (every next crossing beyond the end) before the end's key."""
    from smana.services.mapper.block_grid import octomap_ray_keys

    o = np.asarray(origin, F32)
    inv_res = 1.0 / res
    buf = np.empty((4096, 3), np.int64)
    voxels: dict[tuple, bool] = {}
    stopped_on_length = 0
    for p in points:
        d = (p - o).astype(F32)
        dist = math.sqrt(float(F32(F32(d[0] * d[0] + d[1] * d[1]) + d[2] * d[2])))
        hit = dist <= max_range
        with np.errstate(invalid="ignore"):  # a ray of length 0 needs no direction
            u = (d / F32(dist)).astype(F32)
        e = p if hit else (o + (u * F32(max_range)).astype(F32)).astype(F32)
        s = o
        if ray_m and (dist if hit else max_range) > ray_m:
            s = (e - (u * F32(ray_m)).astype(F32)).astype(F32)
        n = octomap_ray_keys(*s, *e, res, buf)
        for key in map(tuple, buf[: max(n, 0)].tolist()):
            voxels.setdefault(key, False)
        end = tuple(math.floor(float(c) * inv_res) for c in e)
        if n > 0 and np.abs(buf[n - 1] - end).sum() != 1:
            stopped_on_length += 1
        if hit:
            voxels[tuple(math.floor(float(c) * inv_res) for c in p)] = True
    return voxels, stopped_on_length


@pytest.mark.parametrize("res", [0.1, 0.3])
@pytest.mark.parametrize("ray_m", [None, 1.0])
def test_carving_kernel_walks_what_the_ray_walk_yields(res, ray_m):
    """The carving kernel's inline walk (index strides, a block look-up only on entering a
    block) against the walk it replaced, ray by ray: the same voxels in the same order, the same
    log-odds, the same Delta. Rays of every length from 0 (the end in the sensor's voxel) to
    beyond the range, along the axes and the diagonals, ending on voxel faces and corners
    (where the walk stops on its length, not on the end's key), from origins on and off the
    grid."""
    rng = np.random.default_rng(17)
    max_range = 6.0
    l_hit, l_miss, _, _ = sensor_model(OctreeConfig())
    axes = np.concatenate([np.eye(3), -np.eye(3), [[1, 1, 1], [-1, 1, -1], [1, -1, 0]]])
    total_on_length = 0
    for origin in ((0.0, 0.0, 0.8), (0.137, -0.42, 1.73), (-0.3, 0.6, 0.0)):
        o = np.array(origin, F32)
        lengths = rng.choice([0.0, 0.01, 0.05, 0.5, 1.0, 2.5, 5.0, 9.0], (len(axes), 4))
        along = o + (axes[:, None, :] * lengths[:, :, None]).reshape(-1, 3)
        on_grid = np.round((o + rng.uniform(-7, 7, (700, 3))) / res) * res  # faces, corners
        anywhere = o + rng.uniform(-7, 7, (300, 3))
        near = o + rng.uniform(-res, res, (50, 3))  # often in the sensor's own voxel
        pts = np.concatenate([along, on_grid, anywhere, near, [o, o]]).astype(F32)
        m = SemanticMap("octree-max", res, max_range, ray_m or 0.0)
        d = m.integrate(pts, np.zeros(len(pts), np.uint16), None, origin)
        want, on_length = _carved_by_the_walk(pts, origin, res, max_range, ray_m)
        total_on_length += on_length
        assert [tuple(k) for k in d.keys.tolist()] == list(want)
        assert m._core.last_updates == len(want)
        np.testing.assert_array_equal(d.values, [l_hit if h else l_miss for h in want.values()])
    assert total_on_length > 100  # the length rule decided often enough to be tested
