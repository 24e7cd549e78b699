"""TSDF back-end against a slow reference: rays walked by dense sampling (not a DDA), voxels in a
dict, label posteriors by the full Bayes rule over every class with explicit normalisation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.services.mapper.backends.tsdf import TsdfConfig
from smana.services.mapper.semantic_map import SemanticMap

SEM_IDS = [1, 2, 4, 5, 6, 7, 8]


def sampled_ray(start, end, res):
    """Voxels met walking from start to end in steps of res / 4000, in order, each once."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    n = int(math.ceil(np.linalg.norm(end - start) / res * 4000)) + 1
    t = np.linspace(0.0, 1.0, n)[:, None]
    keys = np.floor((start + t * (end - start)) / res).astype(np.int64)
    keep = np.ones(n, bool)
    keep[1:] = (keys[1:] != keys[:-1]).any(axis=1)
    return [tuple(k) for k in keys[keep].tolist()]


class RefTsdf:
    def __init__(self, res, max_range, p=0.9, trunc_vox=2.0, min_range=0.1, sub=2.0):
        self.res, self.max_range, self.p = res, max_range, p
        self.trunc, self.min_range, self.sub = trunc_vox * res, min_range, sub
        self.vox: dict[tuple, list] = {}

    def integrate(self, points, labels, origin):
        o = np.asarray(origin, np.float32).astype(float)
        starts, updated = set(), set()
        k = len(SEM_IDS)
        for pt, lab in zip(points.astype(float), labels, strict=True):
            d = pt - o
            dist = float(np.sqrt(d @ d))
            if dist < self.min_range:
                continue
            u = d / dist
            clearing = dist > self.max_range
            end = o + u * self.max_range if clearing else pt
            s = tuple(np.floor(pt * (self.sub / self.res)).astype(int))
            if s in starts:
                continue
            starts.add(s)
            for key in sampled_ray(
                end + u * self.trunc if not clearing else end, end - u * self.trunc, self.res
            ):
                if key in updated:
                    break  # the fast integrator drops the rest of the ray
                updated.add(key)
                c = (np.array(key) + 0.5) * self.res
                sdf = dist - (c - o) @ d / dist
                w = (
                    1.0
                    if sdf >= -self.res
                    else max((self.trunc + sdf) / (self.trunc - self.res), 0)
                )
                vd, vw, probs = self.vox.get(key, (0.0, 0.0, np.full(k, 1.0 / k)))
                if vw + w < 1e-6:
                    continue
                nd = (sdf * w + vd * vw) / (vw + w)
                nd = min(self.trunc, nd) if nd > 0 else max(-self.trunc, nd)
                if not clearing and int(lab) in SEM_IDS:
                    like = np.full(k, (1 - self.p) / (k - 1))
                    like[SEM_IDS.index(int(lab))] = self.p
                    probs = probs * like / (probs * like).sum()
                self.vox[key] = (nd, vw + w, probs)


def test_tsdf_matches_slow_reference():
    rng = np.random.default_rng(21)
    res, max_range = 0.2, 4.0
    m = SemanticMap("tsdf", res, max_range)
    ref = RefTsdf(res, max_range)
    for _ in range(3):
        pts = rng.uniform(-5, 5, (300, 3)).astype(np.float32)
        pts[:60] = pts[60:120] + rng.normal(0, 0.05, (60, 3)).astype(np.float32)
        labels = rng.choice([0, 1, 2, 4, 5, 6, 7, 8, 3], 300)
        origin = rng.uniform(-0.3, 0.3, 3)
        m.integrate(pts, labels, None, origin)
        ref.integrate(pts, labels, origin)
    core = m._core
    g = core.observed_index()
    rows = core.rows(g)
    keys = [tuple(k) for k in rows.keys.tolist()]
    assert set(keys) == set(ref.vox)
    probs = core.probabilities(g)
    weights = core.grid.cols["weight"][g]
    for i, key in enumerate(keys):
        d, w, p = ref.vox[key]
        assert rows.values[i] == pytest.approx(d, abs=2e-6), key
        assert weights[i] == pytest.approx(w, rel=1e-6), key
        np.testing.assert_allclose(probs[i], p, rtol=2e-4, atol=1e-7)
        srt = np.sort(p)
        if srt[-1] - srt[-2] > 1e-6:  # a clear winner: same label
            assert rows.labels[i] == SEM_IDS[int(np.argmax(p))], key
        elif np.ptp(p) == 0:
            assert rows.labels[i] == 0  # never labelled


def test_single_ray_distances_and_surface():
    m = SemanticMap("tsdf", 0.1, 10.0, config=TsdfConfig(min_weight=1e-4))  # a one-ray surface
    d = m.integrate(
        np.array([[2.03, 0.05, 0.05]], np.float32), np.array([2]), None, (0.05, 0.05, 0.05)
    )
    by_x = dict(zip((k[0] for k in d.keys.tolist()), d.values, strict=True))
    assert sorted(by_x) == [18, 19, 20, 21]  # voxel 22 (sdf = -2 voxels) gets weight 0
    for x, v in by_x.items():
        assert v == pytest.approx(2.03 - (x + 0.5) * 0.1, abs=1e-6)
    surface = {k[0] for k, s in zip(d.keys.tolist(), d.occupied, strict=True) if s}
    # the sign changes between 19 (+0.08 m) and 20 (-0.02 m): 20 is nearer the crossing
    assert surface == {20}
    assert set(d.labels.tolist()) == {2}
    assert d.confidences == pytest.approx(0.9)


def test_fast_integrator_drops_rays_entering_updated_voxels():
    m = SemanticMap("tsdf", 0.1, 10.0)
    pts = np.array([[2.05, 0.05, 0.05], [2.17, 0.05, 0.05]], np.float32)
    m.integrate(pts, np.array([1, 4]), None, (0.05, 0.05, 0.05))
    core = m._core
    g = core.observed_index()
    keys = core.grid.coords(g)[:, 0].tolist()
    w = dict(zip(keys, core.grid.cols["weight"][g], strict=True))
    # the second ray starts at voxel 23, enters voxel 22 (met by the first ray) and stops:
    # without the drop, voxels 21..19 would carry weight 2
    assert 0 < w[23] < 1
    assert max(w[21], w[20], w[19]) <= 1.0 and w[20] == 1.0
    labels, _ = core.labels_of(g)
    assert dict(zip(keys, labels.tolist(), strict=True))[20] == 1


def test_points_beyond_range_clear_without_labels():
    m = SemanticMap("tsdf", 0.1, 3.0)
    d = m.integrate(
        np.array([[6.05, 0.05, 0.05]], np.float32), np.array([4]), None, (0.05, 0.05, 0.05)
    )
    assert len(d) > 0 and np.allclose(d.values, 0.2)
    assert (d.labels == 0).all() and not d.occupied.any()
    assert max(k[0] for k in d.keys.tolist()) == 30


def test_label_steps_are_int16_and_saturate():
    m = SemanticMap("tsdf", 0.1, 10.0, config=TsdfConfig(min_weight=1e-4))
    core = m._core
    pt, origin = np.array([[2.03, 0.05, 0.05]], np.float32), (0.05, 0.05, 0.05)
    m.integrate(pt, np.array([2]), None, origin)
    g = core.observed_index()
    logp = core.grid.cols["logp"]
    assert logp.dtype == np.int16 and core.bytes_per_voxel() <= 32
    col = SEM_IDS.index(2)
    logp[g] = -32760  # as if other classes had won for hours
    logp[g, col] = core._consts.renorm_steps - 1
    m.integrate(pt, np.array([2]), None, origin)  # reaches the shift: others go to the floor
    assert (logp[g, col] == 0).all()
    assert (np.delete(logp[g], col, axis=1) == -32767).all()
    labels, prob = core.labels_of(g)
    assert set(labels.tolist()) == {2} and prob == pytest.approx(1.0)


def test_a_map_saved_with_float_log_probabilities_loads(tmp_path):
    rng = np.random.default_rng(3)
    m = SemanticMap("tsdf", 0.2, 4.0)
    pts = rng.uniform(-3, 3, (400, 3)).astype(np.float32)
    for _ in range(12):  # the same rays: enough updates per voxel for the vector shift
        m.integrate(pts, rng.choice(SEM_IDS, 400, p=[0.7] + [0.05] * 6), None, (0.0, 0.0, 0.0))
    path = m.save(tmp_path / "map.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    steps = arrays["col_logp"]
    assert steps.min() < 0  # shifted vectors are part of the check
    # the layout before int16 step counts: float32 log-probabilities in nats
    arrays["col_logp"] = (steps * m._core.log_ratio).astype(np.float32)
    np.savez(tmp_path / "old.npz", **arrays)
    old = SemanticMap.load(tmp_path / "old.npz")
    np.testing.assert_array_equal(old._core.grid.used("logp"), steps)
