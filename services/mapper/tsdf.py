"""Back-end `tsdf`: voxblox's *fast* TSDF integrator with Kimera Semantics' label log-probabilities.

Per point (voxblox `FastTsdfIntegrator`, voxel carving off as in the paper):
- points closer than `min_range_m` are skipped; points beyond `max_range_m` become clearing rays
  that update only the band before the maximum range, with no label;
- start-voxel subsampling: a point whose position falls in a (resolution / 2) cell already used by
  an earlier point of the same cloud is dropped;
- the ray is cast from `truncation` behind the point towards the sensor, over the band
  [point - truncation, point + truncation] (truncation = 2 voxels by default), and stops at the
  first voxel already updated by another ray of this cloud;
- each voxel gets voxblox's projective distance with constant weight 1, the weight drop-off
  behind the surface and the clamping to +-truncation.

Semantics (Kimera): each voxel keeps a log-probability per semantic class, starting uniform. A
point labelled l adds log p to class l and log((1 - p) / (K - 1)) to every other class (p = 0.9
by default); since adding the same constant to every class does not change the normalised
distribution, the kernel adds only log(p / q) to class l and shifts the vector when it grows, so
an update is O(1) instead of O(K). The voxel label is the most probable class.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from smana.services.mapper._grid import (
    DONE,
    GROW_TOUCHED,
    MARK_ANY,
    MARK_FREE,
    MARK_HIT,
    OBSERVED,
    BlockGrid,
    pack_block,
    table_find_or_insert,
    voxblox_ray_keys,
    voxel_index,
)
from smana.services.mapper.delta import Delta

_RENORM_AT = 30.0  # shift a log-probability vector once its top entry exceeds this


@dataclass(frozen=True)
class TsdfParams:
    truncation_voxels: float = 2.0
    max_weight: float = 10000.0
    min_range_m: float = 0.1
    start_voxel_subsampling: float = 2.0  # voxblox default; 0 disables it
    use_weight_dropoff: bool = True
    label_probability: float = 0.9  # Kimera's measurement probability for the measured label

    def __post_init__(self):
        if not self.truncation_voxels > 0:
            raise ValueError("truncation_voxels must be > 0")
        if not self.max_weight > 0:
            raise ValueError("max_weight must be > 0")
        if not self.min_range_m >= 0:
            raise ValueError("min_range_m must be >= 0")
        if not self.start_voxel_subsampling >= 0:
            raise ValueError("start_voxel_subsampling must be >= 0")
        if not 0.0 < self.label_probability < 1.0:
            raise ValueError("label_probability must be inside (0, 1)")


@njit(cache=True, error_model="numpy")
def _set_insert(keys, key):
    """Insert into an open-addressing set; returns False when the key was already there."""
    mask = keys.shape[0] - 1
    s = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(40)) & mask
    while True:
        k = keys[s]
        if k == key:
            return False
        if k == -1:
            keys[s] = key
            return True
        s = (s + 1) & mask


@njit(cache=True, error_model="numpy")
def _set_contains(keys, key):
    mask = keys.shape[0] - 1
    s = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(40)) & mask
    while True:
        k = keys[s]
        if k == key:
            return True
        if k == -1:
            return False
        s = (s + 1) & mask


@njit(cache=True, error_model="numpy")
def _tsdf_integrate(
    points,
    labels,
    origin,
    i0,
    prm,
    sem_idx,
    log_ratio,
    h_keys,
    h_vals,
    hshift,
    block_keys,
    n_blocks,
    bits,
    flags,
    dist_,
    weight_,
    logp,
    touched,
    n_touched,
    startset,
    keybuf,
    gbuf,
    counts,
):
    """Integrate points i0.. ; resumable: every block is allocated before a ray updates anything.
    `counts` accumulates (newly observed voxels, change in the surface-voxel count)."""
    res = prm[0]
    inv_res = prm[1]
    max_range = prm[2]
    trunc = prm[3]
    max_weight = prm[4]
    min_range = prm[5]
    sub_inv = prm[6]
    dropoff = prm[7] > 0
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    vb = 3 * bits
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    for i in range(i0, points.shape[0]):
        px = np.float64(points[i, 0])
        py = np.float64(points[i, 1])
        pz = np.float64(points[i, 2])
        dx = px - ox
        dy = py - oy
        dz = pz - oz
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        if dist < min_range or dist == 0.0:
            continue
        ux = dx / dist
        uy = dy / dist
        uz = dz / dist
        clearing = dist > max_range
        if clearing:
            ex = ox + ux * max_range
            ey = oy + uy * max_range
            ez = oz + uz * max_range
            sx = ex - ux * trunc
            sy = ey - uy * trunc
            sz = ez - uz * trunc
        else:
            ex = px + ux * trunc
            ey = py + uy * trunc
            ez = pz + uz * trunc
            sx = px - ux * trunc
            sy = py - uy * trunc
            sz = pz - uz * trunc
        skey = np.int64(-1)
        if sub_inv > 0:
            skey = pack_block(
                np.int64(np.floor(px * sub_inv)),
                np.int64(np.floor(py * sub_inv)),
                np.int64(np.floor(pz * sub_inv)),
            )
            if _set_contains(startset, skey):
                continue
        # cast from behind the surface towards the sensor, as voxblox does
        nk = voxblox_ray_keys(ex, ey, ez, sx, sy, sz, inv_res, keybuf)
        if n_touched + nk > touched.shape[0]:
            return GROW_TOUCHED, i, n_blocks, n_touched
        for k in range(nk):
            bkey, local = voxel_index(keybuf[k, 0], keybuf[k, 1], keybuf[k, 2], bits)
            if bkey != last_key:
                b, n_blocks = table_find_or_insert(
                    h_keys, h_vals, hshift, block_keys, n_blocks, bkey
                )
                if b < 0:
                    return -b, i, n_blocks, n_touched
                last_key = bkey
                last_b = b
            gbuf[k] = (last_b << vb) | local
        if sub_inv > 0:
            _set_insert(startset, skey)
        label_idx = -1 if clearing else sem_idx[labels[i]]
        for k in range(nk):
            g = gbuf[k]
            f = flags[g]
            if f & MARK_ANY:  # the fast integrator drops the rest of this ray
                break
            flags[g] = f | MARK_FREE
            touched[n_touched] = g
            n_touched += 1
            cx = (np.float64(keybuf[k, 0]) + 0.5) * res
            cy = (np.float64(keybuf[k, 1]) + 0.5) * res
            cz = (np.float64(keybuf[k, 2]) + 0.5) * res
            sdf = dist - ((cx - ox) * dx + (cy - oy) * dy + (cz - oz) * dz) / dist
            w = 1.0
            if dropoff and sdf < -res:
                w = max((trunc + sdf) / (trunc - res), 0.0)
            w_old = np.float64(weight_[g])
            w_new = w_old + w
            if w_new < 1e-6:
                continue
            d_new = (sdf * w + np.float64(dist_[g]) * w_old) / w_new
            if f & OBSERVED == 0:
                counts[0] += 1
            elif abs(dist_[g]) < res and w_old > 0:
                counts[1] -= 1
            dist_[g] = min(trunc, d_new) if d_new > 0 else max(-trunc, d_new)
            weight_[g] = min(max_weight, w_new)
            if abs(dist_[g]) < res:
                counts[1] += 1
            flags[g] = f | MARK_FREE | MARK_HIT | OBSERVED
            if label_idx >= 0:
                v = logp[g, label_idx] + log_ratio
                logp[g, label_idx] = v
                if v > _RENORM_AT:
                    for j in range(logp.shape[1]):
                        logp[g, j] -= v
    return DONE, points.shape[0], n_blocks, n_touched


@njit(cache=True, error_model="numpy")
def _tsdf_finish(touched, n_touched, flags, changed):
    """Clear this cloud's marks; list the voxels that were actually updated."""
    nc = 0
    for t in range(n_touched):
        g = touched[t]
        f = flags[g]
        if f & MARK_HIT:
            changed[nc] = g
            nc += 1
        flags[g] = f & ~MARK_ANY
    return nc


class TsdfBackend:
    """Semantic TSDF voxel map; `integrate` returns the Delta of one cloud."""

    def __init__(
        self,
        resolution_m: float,
        max_range_m: float,
        class_ids: np.ndarray,
        params: TsdfParams = TsdfParams(),
        block_bits: int = 3,
    ):
        self.resolution_m = float(resolution_m)
        self.max_range_m = float(max_range_m)
        self.params = params
        self.class_ids = np.asarray(class_ids, np.uint16)
        k = len(self.class_ids)
        if k < 2:
            raise ValueError("tsdf needs at least 2 semantic classes")
        self.sem_idx = np.full(65536, -1, np.int16)
        self.sem_idx[self.class_ids] = np.arange(k)
        p = params.label_probability
        self.log_ratio = float(np.log(p / ((1.0 - p) / (k - 1))))
        self.trunc_m = params.truncation_voxels * self.resolution_m
        self.grid = BlockGrid(
            block_bits,
            {
                "distance": (np.float32, ()),
                "weight": (np.float32, ()),
                "logp": (np.float32, (k,)),
                "flags": (np.uint8, ()),
            },
        )
        self._touched = np.empty(1 << 16, np.int64)
        self.last_updates = 0
        self.n_observed = 0  # kept up to date by the kernel: stats() never scans the map
        self.n_occupied = 0
        band = 2 * self.trunc_m + self.resolution_m
        n_buf = 3 * int(np.ceil(band / self.resolution_m)) + 16
        self._keybuf = np.empty((n_buf, 3), np.int64)
        self._gbuf = np.empty(n_buf, np.int64)
        sub = params.start_voxel_subsampling
        self._prm = np.array(
            [
                self.resolution_m,
                1.0 / self.resolution_m,
                self.max_range_m,
                self.trunc_m,
                params.max_weight,
                params.min_range_m,
                sub / self.resolution_m if sub > 0 else 0.0,
                1.0 if params.use_weight_dropoff else 0.0,
            ]
        )

    def integrate(self, points, labels, confs, origin) -> Delta:
        del confs  # Kimera's fast integrator uses a fixed measurement probability
        grid = self.grid
        size = 1 << max(4, int(2 * points.shape[0]).bit_length())
        startset = np.full(size, -1, np.int64)
        counts = np.zeros(2, np.int64)
        i, n_touched = 0, 0
        while True:
            c = grid.cols
            status, i, grid.n_blocks, n_touched = _tsdf_integrate(
                points,
                labels,
                origin,
                i,
                self._prm,
                self.sem_idx,
                self.log_ratio,
                grid.h_keys,
                grid.h_vals,
                grid.hshift,
                grid.block_keys,
                grid.n_blocks,
                grid.bits,
                c["flags"],
                c["distance"],
                c["weight"],
                c["logp"],
                self._touched,
                n_touched,
                startset,
                self._keybuf,
                self._gbuf,
                counts,
            )
            if status == DONE:
                break
            if status == GROW_TOUCHED:
                new = np.empty(self._touched.shape[0] * 2, np.int64)
                new[:n_touched] = self._touched[:n_touched]
                self._touched = new
            else:
                grid.handle(status)
        changed = np.empty(n_touched, np.int64)
        nc = _tsdf_finish(self._touched, n_touched, grid.cols["flags"], changed)
        self.last_updates = nc  # voxels whose distance was fused this cloud
        self.n_observed += int(counts[0])
        self.n_occupied += int(counts[1])
        return self._rows(changed[:nc])

    def labels_of(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(label, probability of that label) from the log-probability vectors."""
        lp = self.grid.cols["logp"][g].astype(np.float64)
        if lp.shape[0] == 0:
            return np.zeros(0, np.uint16), np.zeros(0, np.float32)
        top = lp.argmax(axis=1)
        mx = lp[np.arange(lp.shape[0]), top]
        prob = 1.0 / np.exp(lp - mx[:, None]).sum(axis=1)
        labels = self.class_ids[top]
        labels[(lp == lp[:, :1]).all(axis=1)] = 0  # never labelled: uniform vector
        return labels, prob.astype(np.float32)

    def probabilities(self, g: np.ndarray) -> np.ndarray:
        """Normalised class probabilities (rows follow `class_ids`)."""
        lp = self.grid.cols["logp"][g].astype(np.float64)
        e = np.exp(lp - lp.max(axis=1, keepdims=True))
        return e / e.sum(axis=1, keepdims=True)

    def _rows(self, g: np.ndarray) -> Delta:
        c = self.grid.cols
        keys = self.grid.coords(g)
        d = c["distance"][g]
        labels, prob = self.labels_of(g)
        surface = (np.abs(d) < self.resolution_m) & (c["weight"][g] > 0)
        return Delta(
            keys.astype(np.int32),
            ((keys + 0.5) * self.resolution_m).astype(np.float32),
            labels,
            prob,
            surface.astype(np.uint8),
            d,
        )

    # -- queries ---------------------------------------------------------------------------

    def recount(self) -> None:
        """Recompute the counters from the columns (after a load)."""
        self.n_observed = int(self.observed_index().shape[0])
        self.n_occupied = int(self.occupied_index().shape[0])

    def observed_index(self) -> np.ndarray:
        return np.flatnonzero(self.grid.used("flags") & OBSERVED)

    def occupied_index(self) -> np.ndarray:
        used = self.grid.used
        surf = (np.abs(used("distance")) < self.resolution_m) & (used("weight") > 0)
        return np.flatnonzero(surf & (used("flags") & OBSERVED).astype(bool))

    def rows(self, g: np.ndarray) -> Delta:
        return self._rows(np.asarray(g, np.int64))

    def known(self, g: np.ndarray) -> np.ndarray:
        return (self.grid.cols["flags"][g] & OBSERVED).astype(bool)

    def bytes_per_voxel(self) -> int:
        return sum(
            col.dtype.itemsize * int(np.prod(col.shape[1:])) for col in self.grid.cols.values()
        )
