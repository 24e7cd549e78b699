"""Degradation as in the paper: SLIC majority labels, confusion redraw, confidences, pose noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from smana.common.classes import ClassTable
from smana.services.sim.degrade import (
    GARDEN_IDS,
    NOISE_LEVELS,
    LabelDegrader,
    PoseNoise,
    confusion_matrix,
    superpixel_majority,
)

COLOURS = ClassTable.load("garden3drms").colour_lut


def _blocks(rng: np.random.Generator, size: int = 160, block: int = 16) -> np.ndarray:
    """A label image of constant square blocks of random garden classes, some with no point."""
    ids = np.array([-1, 1, 2, 4, 5, 6, 7, 8])
    grid = rng.choice(ids, size=(size // block, size // block))
    return np.kron(grid, np.ones((block, block), np.int64)).astype(np.int32)


def test_confusion_matrix_is_table_2():
    for level, p in NOISE_LEVELS.items():
        m = confusion_matrix(p)
        q = (1 - p) / 2
        assert np.allclose(m.sum(axis=1), 1.0), level
        idx = {c: k for k, c in enumerate(GARDEN_IDS)}
        assert m[idx[0], idx[0]] == 1.0
        # REFERENCE.md, row by row: the two classes each true class may be mistaken for
        expected_pairs = {
            1: (2, 4),
            2: (1, 4),
            4: (5, 6),
            5: (4, 6),
            6: (5, 7),
            7: (6, 8),
            8: (6, 7),
        }
        for true, others in expected_pairs.items():
            row = m[idx[true]]
            assert row[idx[true]] == pytest.approx(p)
            for o in others:
                assert row[idx[o]] == pytest.approx(q)
            assert np.count_nonzero(row) == (1 if p == 1.0 else 3)
    with pytest.raises(ValueError):
        confusion_matrix(1.5)


def test_majority_matches_a_slow_reference():
    rng = np.random.default_rng(0)
    labels = rng.integers(-1, 9, (40, 50)).astype(np.int32)
    sp = rng.integers(0, 30, (40, 50)).astype(np.int32)
    got = superpixel_majority(sp, labels, 9)
    for s in range(30):
        vals = labels[(sp == s) & (labels >= 0)]
        if len(vals) == 0:
            assert got[s] == -1
            continue
        counts = np.bincount(vals, minlength=9)
        assert got[s] == int(np.flatnonzero(counts == counts.max())[0])  # ties: smallest id


def test_level_off_is_identity_and_none_keeps_majorities():
    rng = np.random.default_rng(1)
    labels = _blocks(rng)
    off = LabelDegrader("off", np.random.default_rng(0), COLOURS).degrade(labels)
    assert np.array_equal(off.labels, labels)
    assert np.all(LabelDegrader("off", rng, COLOURS).confidences(10) == 1.0)
    none = LabelDegrader("none", np.random.default_rng(0), COLOURS, region_px=8).degrade(labels)
    assert np.array_equal(none.given, none.majority)  # p = 1: no redraw changes a label
    valid = labels >= 0
    assert np.array_equal(none.labels >= 0, valid)  # no point appears or vanishes
    # SLIC on constant blocks: superpixels follow the block edges, so labels barely move
    assert np.mean(none.labels[valid] == labels[valid]) > 0.97


@pytest.mark.parametrize("level", ["low", "high"])
def test_measured_confusion_matches_the_table(level):
    """Count (majority -> given) over many superpixels and frames; each cell must lie within
    4.5 binomial standard deviations of the table, and each row must pass a chi-square test."""
    deg = LabelDegrader(level, np.random.default_rng(7), COLOURS, region_px=8)
    counts = np.zeros((9, 9), np.int64)
    rng = np.random.default_rng(3)
    for _ in range(12):
        out = deg.degrade(_blocks(rng))
        ok = out.majority >= 0
        np.add.at(counts, (out.majority[ok], out.given[ok]), 1)
    table = confusion_matrix(NOISE_LEVELS[level])
    for k, true in enumerate(GARDEN_IDS):
        if true == 0:
            continue
        n = counts[true].sum()
        assert n > 300, (true, n)
        expected = np.zeros(9)
        expected[list(GARDEN_IDS)] = table[k]
        observed = counts[true] / n
        sd = np.sqrt(expected * (1 - expected) / n)
        assert np.all(np.abs(observed - expected) <= 4.5 * sd + 1e-12), (true, observed)
        nz = expected > 0
        chi2 = stats.chisquare(counts[true][nz], expected[nz] * n)
        assert chi2.pvalue > 1e-4, (true, chi2)


def test_pixel_labels_follow_their_superpixel_and_are_repeatable():
    labels = _blocks(np.random.default_rng(4))
    a = LabelDegrader("high", np.random.default_rng(9), COLOURS, region_px=10).degrade(labels)
    b = LabelDegrader("high", np.random.default_rng(9), COLOURS, region_px=10).degrade(labels)
    assert np.array_equal(a.labels, b.labels)
    valid = labels >= 0
    assert np.array_equal(a.labels[valid], a.given[a.superpixels][valid])
    c = LabelDegrader("high", np.random.default_rng(10), COLOURS, region_px=10).degrade(labels)
    assert not np.array_equal(a.labels, c.labels)


def test_confidences_are_uniform_on_the_paper_range():
    deg = LabelDegrader("medium", np.random.default_rng(0), COLOURS)
    conf = deg.confidences(20000)
    assert conf.dtype == np.float32
    assert conf.min() >= 0.33 and conf.max() <= 1.0
    assert stats.kstest(conf, stats.uniform(0.33, 0.67).cdf).pvalue > 1e-3


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="label noise"):
        LabelDegrader("extreme", np.random.default_rng(0), COLOURS)
    deg = LabelDegrader("low", np.random.default_rng(0), COLOURS)
    with pytest.raises(ValueError, match="2D"):
        deg.degrade(np.zeros(5, np.int32))
    with pytest.raises(ValueError, match="below"):
        deg.degrade(np.full((4, 4), 300, np.int32))


def test_ids_outside_the_table_keep_their_label():
    deg = LabelDegrader("high", np.random.default_rng(0), np.zeros((20, 3), np.uint8))
    assert np.all(deg.redraw(np.full(1000, 15)) == 15)


def _yaw(m):
    return math.atan2(m[1, 0], m[0, 0])


def test_pose_noise_has_the_set_standard_deviation():
    base = np.eye(4)
    c, s = math.cos(0.3), math.sin(0.3)
    base[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    base[:3, 3] = [1.0, -2.0, 0.2]
    noise = PoseNoise(0.1, 0.02, np.random.default_rng(0))
    samples = [noise.apply(base) for _ in range(20000)]
    dx = np.array([m[0, 3] - 1.0 for m in samples])
    dy = np.array([m[1, 3] + 2.0 for m in samples])
    dyaw = np.array([_yaw(m) - 0.3 for m in samples])
    n = len(samples)
    # the sample std of a Gaussian has a relative standard error of 1/sqrt(2n) (0.5 % here)
    for d, sigma in ((dx, 0.1), (dy, 0.1), (dyaw, 0.02)):
        assert abs(d.std() / sigma - 1) < 4 / math.sqrt(2 * n)
        assert abs(d.mean()) < 4 * sigma / math.sqrt(n)
    assert all(m[2, 3] == 0.2 for m in samples[:100])  # height untouched
    assert np.allclose(samples[0][:3, :3] @ samples[0][:3, :3].T, np.eye(3))
    assert np.corrcoef(dx, dy)[0, 1] < 0.05
    assert np.array_equal(PoseNoise(0, 0, np.random.default_rng(0)).apply(base), base)
    with pytest.raises(ValueError):
        PoseNoise(-1, 0, np.random.default_rng(0))


def test_superpixels_from_an_earlier_call_give_the_same_degradation():
    """The noise experiment segments each frame once and reuses it at every level."""
    labels = _blocks(np.random.default_rng(3))
    first = LabelDegrader("medium", np.random.default_rng(5), COLOURS).degrade(labels)
    again = LabelDegrader("medium", np.random.default_rng(5), COLOURS).degrade(
        labels, superpixels=first.superpixels
    )
    assert np.array_equal(first.labels, again.labels)
    with pytest.raises(ValueError, match="do not match"):
        LabelDegrader("low", np.random.default_rng(5), COLOURS).degrade(
            labels, superpixels=first.superpixels[:10]
        )
