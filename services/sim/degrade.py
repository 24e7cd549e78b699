"""Degraded inputs, as the paper makes them (section 4.2.1).

Labels: SLIC superpixels on the ground-truth semantic image; each superpixel takes the most
frequent label of its pixels, then that label is redrawn from the row of the confusion matrix
(paper Table 2, its structure as GARDEN_CONFUSABLE holds it; extended by water in the wet
garden, see WET_CONFUSABLE) for the noise level; every point gets a confidence drawn uniformly
in [0.33, 1.0]. Level "off" (not in the paper) skips all of it: true
labels, confidence 1, for tests and ground-truth runs.

Localisation: Gaussian noise of set standard deviation on the published x, y and yaw, and
optionally a drift: a random walk in x, y and yaw (not in the paper).

Level "realistic" (not in the paper) redraws from a published network's confusion matrix and
adds persistent errors and boundary bleed: perception.py.

All randomness comes from the `numpy.random.Generator` passed in, so a seed repeats a run.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

NOISE_LEVELS = {"none": 1.0, "low": 0.9, "medium": 0.8, "high": 0.7}
LABEL_NOISE_CHOICES = ("off", *NOISE_LEVELS, "realistic")

# Table 2's structure: the classes a true class may be mistaken for (each with q = (1 - p) / 2).
# Ids are 3DRMS garden ids; a class not listed here is never confused.
GARDEN_CONFUSABLE: dict[int, tuple[int, int]] = {
    1: (2, 4),  # grass -> terrain, hedge
    2: (1, 4),  # terrain -> grass, hedge
    4: (5, 6),  # hedge -> topiary, rose
    5: (4, 6),  # topiary -> hedge, rose
    6: (5, 7),  # rose -> topiary, obstacle
    7: (6, 8),  # obstacle -> rose, tree
    8: (6, 7),  # tree -> rose, obstacle
}
GARDEN_IDS = (0, 1, 2, 4, 5, 6, 7, 8)

# The wet garden (sim.garden.water_share > 0, class table garden3drms_wet) extends Table 2 by
# water (9), the class only semantics can see: water is mistaken for grass or terrain (q each, as
# every row), and grass and terrain for water (a third share each: q' = (1 - p) / 3 for their
# three confusions). The paper's world keeps Table 2 as it is: no grass ever turns into water.
WATER_ID = 9
WET_CONFUSABLE: dict[int, tuple[int, ...]] = {
    **GARDEN_CONFUSABLE,
    1: (2, 4, WATER_ID),  # grass -> terrain, hedge, water
    2: (1, 4, WATER_ID),  # terrain -> grass, hedge, water
    WATER_ID: (1, 2),  # water -> grass, terrain
}
WET_IDS = (*GARDEN_IDS, WATER_ID)


def confusion_matrix(
    p: float,
    ids: tuple[int, ...] = GARDEN_IDS,
    confusable: dict[int, tuple[int, ...]] | None = None,
) -> np.ndarray:
    """Row-stochastic matrix M[i, j] = P(given ids[j] | true ids[i]) for probability p."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p must be within [0, 1], got {p}")
    confusable = GARDEN_CONFUSABLE if confusable is None else confusable
    index = {cid: k for k, cid in enumerate(ids)}
    m = np.zeros((len(ids), len(ids)))
    for cid, k in index.items():
        others = [index[o] for o in confusable.get(cid, ()) if o in index]
        if not others:
            m[k, k] = 1.0
            continue
        m[k, k] = p
        for o in others:
            m[k, o] += (1.0 - p) / len(others)
    return m


def _cumulative_lut(matrix: np.ndarray, ids: tuple[int, ...], size: int) -> np.ndarray:
    """cum[label] = cumulative confusion row of `label` over `ids`. Labels outside `ids` get a
    placeholder row; `LabelDegrader.redraw` keeps their label as it is."""
    cum = np.ones((size, len(ids)))
    for k, cid in enumerate(ids):
        if cid < size:
            cum[cid] = np.cumsum(matrix[k])
            cum[cid, -1] = 1.0  # guard against rounding: the last bin always closes the row
    return cum


@dataclass
class DegradedLabels:
    labels: np.ndarray  # i4[H, W], -1 where the pixel has no point
    superpixels: np.ndarray | None  # i4[H, W] superpixel index (None for level "off")
    majority: np.ndarray | None  # i8[S] majority true label per superpixel (-1: no valid pixel)
    given: np.ndarray | None  # i8[S] label after the redraw


class LabelDegrader:
    """SLIC + majority + confusion redraw + confidences, for one noise level."""

    def __init__(
        self,
        level: str,
        rng: np.random.Generator,
        colour_lut: np.ndarray,
        *,
        region_px: int = 20,
        ruler: float = 10.0,
        iterations: int = 3,
        confidence_range: tuple[float, float] = (0.33, 1.0),
        ids: tuple[int, ...] = GARDEN_IDS,
        confusable: dict[int, tuple[int, ...]] | None = None,
        matrix: np.ndarray | None = None,
    ):
        """`matrix`: the redraw's confusion matrix over `ids`, in place of the level's Table 2
        (perception.py gives it for the other confusions and the persistent errors' split)."""
        if level not in LABEL_NOISE_CHOICES:
            raise ValueError(f"label noise must be one of {LABEL_NOISE_CHOICES}, got {level!r}")
        if region_px < 2 or iterations < 1:
            raise ValueError("SLIC needs region_px >= 2 and iterations >= 1")
        lo, hi = confidence_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"confidence range must be within [0, 1], got {confidence_range}")
        self.level = level
        self.rng = rng
        self.colour_lut = np.asarray(colour_lut, np.uint8)
        self.region_px = int(region_px)
        self.ruler = float(ruler)
        self.iterations = int(iterations)
        self.confidence_range = (float(lo), float(hi))
        self.ids = tuple(ids)
        self.size = max(len(self.colour_lut), max(self.ids) + 1)
        if matrix is None:
            matrix = confusion_matrix(NOISE_LEVELS.get(level, 1.0), self.ids, confusable)
        elif np.shape(matrix) != (len(self.ids), len(self.ids)):
            raise ValueError(f"matrix must be {len(self.ids)} x {len(self.ids)} over ids")
        self.matrix = np.asarray(matrix, float)
        self._cum = _cumulative_lut(self.matrix, self.ids, self.size)
        self._ids = np.array(self.ids, np.int64)
        self._in_table = np.zeros(self.size, bool)
        self._in_table[[i for i in self.ids if i < self.size]] = True

    def degrade(
        self,
        labels: np.ndarray,
        timings: dict | None = None,
        superpixels: np.ndarray | None = None,
    ) -> DegradedLabels:
        """Degrade a true label image (i4[H, W], -1 where there is no point). With `timings`,
        the SLIC and the vote-and-redraw times go in it (ms). `superpixels`: this image's SLIC
        segmentation from an earlier call (`DegradedLabels.superpixels`); SLIC depends on the
        image alone, so a caller degrading one image at several levels computes it once."""
        labels = np.asarray(labels)
        if labels.ndim != 2:
            raise ValueError(f"label image must be 2D, got shape {labels.shape}")
        valid = labels >= 0
        if valid.any() and labels[valid].max() >= self.size:
            raise ValueError(f"label ids must be below {self.size}")
        if self.level == "off":
            return DegradedLabels(labels.astype(np.int32), None, None, None)
        t0 = time.perf_counter()
        if superpixels is None:
            sp = self.superpixels(labels)
        elif superpixels.shape != labels.shape:
            raise ValueError(f"superpixels {superpixels.shape} do not match labels {labels.shape}")
        else:
            sp = superpixels
        t1 = time.perf_counter()
        majority = superpixel_majority(sp, labels, self.size)
        given = self.redraw(majority)
        out = np.where(valid, given[sp], -1).astype(np.int32)
        if timings is not None:
            timings["slic_ms"] = 1e3 * (t1 - t0)
            timings["redraw_ms"] = 1e3 * (time.perf_counter() - t1)
        return DegradedLabels(out, sp, majority, given)

    def superpixels(self, labels: np.ndarray) -> np.ndarray:
        """SLIC superpixels of the label image, coloured by class (no-point pixels black)."""
        import cv2

        image = self.colour_lut[np.clip(labels, 0, len(self.colour_lut) - 1)]
        image[labels < 0] = 0
        slic = cv2.ximgproc.createSuperpixelSLIC(
            np.ascontiguousarray(image),
            algorithm=cv2.ximgproc.SLIC,
            region_size=self.region_px,
            ruler=self.ruler,
        )
        slic.iterate(self.iterations)
        return slic.getLabels().astype(np.int32)

    def redraw(self, majority: np.ndarray) -> np.ndarray:
        """Draw each superpixel's given label from its majority label's confusion row."""
        majority = np.asarray(majority, np.int64)
        out = majority.copy()
        ok = majority >= 0
        lab = majority[ok]
        u = self.rng.random(len(lab))
        pick = (self._cum[lab] <= u[:, None]).sum(axis=1)
        drawn = self._ids[np.minimum(pick, len(self._ids) - 1)]
        # ids outside the confusion table keep their label
        out[ok] = np.where(self._in_table[lab], drawn, lab)
        return out

    def confidences(self, n: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """Per-point confidences: U[lo, hi] (1 for level "off"), from `rng` if given."""
        if self.level == "off":
            return np.ones(n, np.float32)
        lo, hi = self.confidence_range
        return (rng or self.rng).uniform(lo, hi, n).astype(np.float32)


def superpixel_majority(superpixels: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """Most frequent label of each superpixel's valid (>= 0) pixels; -1 if it has none.
    Ties go to the smallest id."""
    sp = np.asarray(superpixels, np.int64).ravel()
    lab = np.asarray(labels, np.int64).ravel()
    valid = lab >= 0
    n_sp = int(sp.max()) + 1 if sp.size else 0
    votes = np.bincount(sp[valid] * n_labels + lab[valid], minlength=n_sp * n_labels)
    votes = votes.reshape(n_sp, n_labels)
    majority = np.argmax(votes, axis=1)
    majority[votes.sum(axis=1) == 0] = -1
    return majority


class PoseNoise:
    """Gaussian noise on the published x, y (each with `sigma_xy_m`) and yaw (`sigma_yaw_rad`).
    Each call draws afresh: white noise, as the paper adds it to every ground-truth pose.

    Drift (not in the paper): a random walk added under the white noise, as odometry drifts. Its
    offsets in x, y (each) and yaw after t seconds have standard deviations `drift_xy_m_per_sqrt_s`
    * sqrt(t) and `drift_yaw_rad_per_sqrt_s` * sqrt(t); each call with a later `time_s` walks on
    by the time since the last, drawn from `drift_rng` (its own stream: switching drift on does
    not change the white noise's draws)."""

    def __init__(
        self,
        sigma_xy_m: float,
        sigma_yaw_rad: float,
        rng: np.random.Generator,
        drift_xy_m_per_sqrt_s: float = 0.0,
        drift_yaw_rad_per_sqrt_s: float = 0.0,
        drift_rng: np.random.Generator | None = None,
    ):
        if not (sigma_xy_m >= 0 and sigma_yaw_rad >= 0):
            raise ValueError("pose noise standard deviations must be >= 0")
        if not (drift_xy_m_per_sqrt_s >= 0 and drift_yaw_rad_per_sqrt_s >= 0):
            raise ValueError("pose drift rates must be >= 0")
        self.sigma_xy_m = float(sigma_xy_m)
        self.sigma_yaw_rad = float(sigma_yaw_rad)
        self.rng = rng
        self.drift_xy = float(drift_xy_m_per_sqrt_s)
        self.drift_yaw = float(drift_yaw_rad_per_sqrt_s)
        if self.drifts and drift_rng is None:
            raise ValueError("pose drift needs its random stream (drift_rng)")
        self.drift_rng = drift_rng
        self.drift = np.zeros(3)  # x, y, yaw offsets of the walk so far
        self._drift_t: float | None = None

    @property
    def drifts(self) -> bool:
        return self.drift_xy > 0 or self.drift_yaw > 0

    @property
    def enabled(self) -> bool:
        return self.sigma_xy_m > 0 or self.sigma_yaw_rad > 0 or self.drifts

    def walk_to(self, time_s: float) -> np.ndarray:
        """Advance the drift to `time_s` (an earlier or equal time leaves it); its (x, y, yaw)."""
        if self.drifts:
            if self._drift_t is None:
                self._drift_t = float(time_s)
            elif time_s > self._drift_t:
                dt = float(time_s) - self._drift_t
                sd = np.array([self.drift_xy, self.drift_xy, self.drift_yaw]) * math.sqrt(dt)
                self.drift += self.drift_rng.normal(0.0, 1.0, 3) * sd
                self._drift_t = float(time_s)
        return self.drift.copy()

    def apply(self, world_from_base: np.ndarray, time_s: float | None = None) -> np.ndarray:
        """A noisy copy of a 4x4 pose: shifted in x, y and turned about the world z axis. With
        drift, `time_s` (simulated) moves the walk on first; without it the walk stays."""
        m = np.array(world_from_base, float)
        if not self.enabled:
            return m
        dx, dy = self.rng.normal(0.0, self.sigma_xy_m, 2) if self.sigma_xy_m > 0 else (0.0, 0.0)
        dyaw = self.rng.normal(0.0, self.sigma_yaw_rad) if self.sigma_yaw_rad > 0 else 0.0
        if self.drifts:
            wx, wy, wyaw = self.walk_to(time_s) if time_s is not None else self.drift
            dx, dy, dyaw = dx + wx, dy + wy, dyaw + wyaw
        c, s = math.cos(dyaw), math.sin(dyaw)
        m[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ m[:3, :3]
        m[0, 3] += dx
        m[1, 3] += dy
        return m
