"""Label noise as a segmentation network makes it, beside the paper's per-frame redraw
(degrade.py), for `sim.noise = "realistic"`. Configured by `[sim.perception]`
(common/config/sim.py), whose defaults are the realistic preset; the paper's levels use none of
it, so their labels stay the paper's bit for bit.

- Confusion rows: the paper's Table 2 (`table2`), class pairs (`pairs`: grass <-> terrain;
  hedge, topiary and tree among themselves; water <-> grass in the wet garden) at accuracy p, or
  a published network's measured matrix (`rellis3d`, confusion_rellis3d.py).
- Persistent errors: a share of every class's errors is the same from every view. The ground
  plane is cut into cells of `cell_m`; a hash of the cell, the pixel's true class and the seed
  decides whether that class is mislabelled in that cell and as what (drawn from its confusion
  row), so the same bush is called a tree from every view, by every member of a fleet. The rest of
  the error is redrawn per superpixel and frame as the paper does, at the rate that keeps each
  class's total error that of the matrix (`split_matrix`).
- Boundary bleed: labels spill `bleed_px` pixels over class edges; which class wins an edge is
  drawn per frame (`bleed`).

Every draw comes from the seed: the persistent hash from a key derived from it, the per-frame
draws from the finisher's random streams.
"""

from __future__ import annotations

import numpy as np

from smana.common.config.sim import PerceptionConfig

from .degrade import GARDEN_CONFUSABLE, WATER_ID, WET_CONFUSABLE, confusion_matrix

# Class pairs a network confuses (3DRMS garden ids): ground with ground, plant with plant.
PAIR_CONFUSABLE: dict[int, tuple[int, ...]] = {
    1: (2,),  # grass -> terrain
    2: (1,),  # terrain -> grass
    4: (5, 8),  # hedge -> topiary, tree
    5: (4, 8),  # topiary -> hedge, tree
    8: (4, 5),  # tree -> hedge, topiary
}
WET_PAIR_CONFUSABLE: dict[int, tuple[int, ...]] = {
    **PAIR_CONFUSABLE,
    1: (2, WATER_ID),  # grass -> terrain, water
    WATER_ID: (1,),  # water -> grass
}


def perception_matrix(perception: PerceptionConfig, ids: tuple[int, ...], wet: bool) -> np.ndarray:
    """The confusion matrix of `[sim.perception]` over the class ids."""
    if perception.confusion == "rellis3d":
        from .confusion_rellis3d import garden_matrix

        return garden_matrix(ids, wet)
    if perception.confusion == "pairs":
        confusable = WET_PAIR_CONFUSABLE if wet else PAIR_CONFUSABLE
    else:
        confusable = WET_CONFUSABLE if wet else GARDEN_CONFUSABLE
    return confusion_matrix(perception.accuracy, ids, confusable)


def split_matrix(matrix: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray]:
    """(persistent, transient) parts of a confusion matrix whose error e_c is split so that a
    share `share` of it is persistent: a class is persistently wrong with probability share * e_c
    (persistent row: that rate, the wrong class drawn from the off-diagonal row), and the rest is
    redrawn each frame at t_c = (1 - share) e_c / (1 - share e_c), so that the two together are
    wrong with probability e_c and, when wrong, as the matrix says."""
    m = np.asarray(matrix, float)
    diag = np.diag(m)
    err = 1.0 - diag
    off = m - np.diag(diag)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(err[:, None] > 0, off / err[:, None], 0.0)
        persistent_rate = share * err
        t = np.where(persistent_rate < 1, (err - persistent_rate) / (1 - persistent_rate), 0.0)
    persistent = q * persistent_rate[:, None] + np.diag(1 - persistent_rate)
    transient = q * t[:, None] + np.diag(1 - t)
    return persistent, transient


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser on uint64 (wrapping arithmetic): a well-spread hash."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def cell_uniforms(key: int, ix: np.ndarray, iy: np.ndarray, label: np.ndarray, salt: int):
    """Two-dimensional cell (ix, iy), class `label`, `salt` -> a uniform in [0, 1), the same for
    the same arguments in any process."""
    with np.errstate(over="ignore"):
        h = np.uint64(key) ^ (np.uint64(salt) * np.uint64(0x9E3779B97F4A7C15))
        h = _mix64(h ^ ix.astype(np.int64).view(np.uint64) * np.uint64(0xD6E8FEB86659FD93))
        h = _mix64(h ^ iy.astype(np.int64).view(np.uint64) * np.uint64(0xA0761D6478BD642F))
        h = _mix64(h ^ label.astype(np.uint64))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


class PersistentErrors:
    """The same wrong label from every view: per point, from its world position and true class."""

    def __init__(self, matrix: np.ndarray, ids: tuple[int, ...], cell_m: float, key: int):
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m}")
        self.cell_m = float(cell_m)
        self.key = int(key) & 0xFFFFFFFFFFFFFFFF
        self.ids = np.array(ids, np.int64)
        size = int(max(ids)) + 1
        m = np.asarray(matrix, float)
        # per true label: the rate it is persistently wrong, and the cumulative wrong-class row
        self._wrong = np.zeros(size)
        self._cum = np.ones((size, len(ids)))
        for k, cid in enumerate(ids):
            off = m[k].copy()
            off[k] = 0.0
            rate = off.sum()
            self._wrong[cid] = rate
            if rate > 0:
                self._cum[cid] = np.cumsum(off / rate)
                self._cum[cid, -1] = 1.0

    @property
    def enabled(self) -> bool:
        return bool(self._wrong.any())

    def labels(self, true: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The persistent label of each point (its true label, or the wrong one its cell and class
        keep): `true` i8[N] true class ids, `xy` f[N, 2] world positions."""
        true = np.asarray(true, np.int64)
        out = true.copy()
        known = (true >= 0) & (true < len(self._wrong))
        if not known.any():
            return out
        lab = true[known]
        ix = np.floor(xy[known, 0] / self.cell_m)
        iy = np.floor(xy[known, 1] / self.cell_m)
        wrong = cell_uniforms(self.key, ix, iy, lab, 0) < self._wrong[lab]
        if wrong.any():
            u = cell_uniforms(self.key, ix[wrong], iy[wrong], lab[wrong], 1)
            pick = (self._cum[lab[wrong]] <= u[:, None]).sum(axis=1)
            lab[wrong] = self.ids[np.minimum(pick, len(self.ids) - 1)]
            out[known] = lab
        return out


def bleed(labels: np.ndarray, bleed_px: int, ranks: np.ndarray) -> np.ndarray:
    """Labels spilled `bleed_px` pixels over class edges: each pixel with a point takes, of the
    labels within `bleed_px` (a square window, clipped at the image's border), the one whose
    `ranks[label]` is highest. No-point pixels (-1) stay so and spill nothing. `ranks`: a
    permutation of 1..n over the label ids (the frame's draw of which side wins each edge)."""
    import cv2

    labels = np.asarray(labels)
    if bleed_px <= 0:
        return labels
    valid = labels >= 0
    ranks = np.asarray(ranks)
    if len(ranks) > 255:
        raise ValueError("bleed: at most 255 classes")
    rank_img = np.where(valid, ranks[np.clip(labels, 0, len(ranks) - 1)], 0).astype(np.uint8)
    kernel = np.ones((2 * bleed_px + 1, 2 * bleed_px + 1), np.uint8)
    grown = cv2.dilate(rank_img, kernel)
    by_rank = np.zeros(256, np.int32)
    by_rank[ranks] = np.arange(len(ranks))
    return np.where(valid, by_rank[grown], -1).astype(np.int32)


class LabelNoise:
    """The persistent errors and bleed of a frame, after the degrader's per-frame redraw."""

    def __init__(
        self,
        perception: PerceptionConfig,
        persistent_matrix: np.ndarray | None,
        ids: tuple[int, ...],
        size: int,
        key: int,
        rng: np.random.Generator,
    ):
        self.perception = perception
        self.persistent = None
        if persistent_matrix is not None:
            self.persistent = PersistentErrors(persistent_matrix, ids, perception.cell_m, key)
        self.bleed_px = int(perception.bleed_px)
        self.size = int(size)
        self.rng = rng

    def apply(
        self,
        degraded: np.ndarray,
        true: np.ndarray,
        world_xy,
        timings: dict | None = None,
    ) -> np.ndarray:
        """`degraded` i4[H, W] (the per-frame redraw) with the persistent labels put back where
        their cell and class are wrong and the bleed applied. `true` i4[H, W] true labels,
        `world_xy` f[H, W, 2] (or f[N, 2] for the valid pixels in row-major order) the pixels'
        true world positions, or a function giving them (called only for persistent errors)."""
        import time

        t0 = time.perf_counter()
        out = np.asarray(degraded, np.int32)
        if self.persistent is not None:
            valid = true >= 0
            if callable(world_xy):
                world_xy = world_xy()
            xy = world_xy[valid] if world_xy.ndim == 3 else world_xy
            t = true[valid]
            persistent = self.persistent.labels(t, xy)
            out = out.copy()
            wrong = persistent != t
            vals = out[valid]
            vals[wrong] = persistent[wrong]
            out[valid] = vals
        t1 = time.perf_counter()
        if self.bleed_px > 0:
            out = bleed(out, self.bleed_px, self.rng.permutation(self.size) + 1)
        if timings is not None:
            timings["persistent_ms"] = 1e3 * (t1 - t0)
            timings["bleed_ms"] = 1e3 * (time.perf_counter() - t1)
        return out
