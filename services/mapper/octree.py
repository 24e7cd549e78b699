"""Occupancy back-ends `octree-max` and `octree-bayes`: OctoMap's occupancy with Semantic Octomap's
label fusion, stored in a hashed block grid (see `_grid.py`) instead of a pointer octree.

Occupancy follows OctoMap's `insertPointCloud` exactly: for one cloud every ray's voxels are
collected first; a voxel is updated at most once as free and at most once as occupied, and a
voxel that is some ray's end point is never freed by another ray of the same cloud. Log-odds are
float32 and clamped as OctoMap does, so the same rays give the same values.

Two departures from OctoMap, both from the paper's setting:
- `ray_length_m`: free space is carved only over the last metres before the end point (1 m in
  the paper); `None` carves the whole ray as OctoMap does. (Semantic Octomap's own generator
  instead carves the first metre from the sensor and marks farther end points occupied without a
  ray; carving next to the surface is what clears moved obstacles, so we carve there.)
- semantics: every point fuses its label into its end voxel (points labelled 0 or with a label
  outside the semantic classes update occupancy only).

Max fusion (Semantic Octomap `SemanticsMax`, with the paper's wording that agreement raises the
confidence): same label -> c += gain * c_obs * (1 - c); other label with higher confidence ->
(label_obs, penalty * c_obs); other label with lower confidence -> c *= penalty.

Bayesian fusion (Semantic Octomap `SemanticsBayesian`, with the rest of the mass spread evenly as
the paper says): the voxel keeps its 3 most probable classes; each of the K - 3 others holds an
equal share of the remaining mass. A point (label l, confidence c) is the likelihood c for l and
(1 - c) / (K - 1) for every other class; the posterior is renormalised and the top 3 kept.
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
    MARK_SEM,
    OBSERVED,
    BlockGrid,
    coord_to_key,
    key_in_range,
    octomap_ray_keys,
    table_find_or_insert,
    unpack_block,
    voxel_index,
)
from smana.services.mapper.delta import Delta

FUSION_MAX = 0
FUSION_BAYES = 1
FUSIONS = {"max": FUSION_MAX, "bayes": FUSION_BAYES}


def logodds(p: float) -> np.float32:
    """OctoMap's logodds(): computed in double, stored as float."""
    return np.float32(np.log(p / (1.0 - p)))


@dataclass(frozen=True)
class OccupancyParams:
    """OctoMap's sensor model; the defaults are OctoMap's own (clamping 0.1192 / 0.971)."""

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971

    def __post_init__(self):
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"{name} must be inside (0, 1), got {v}")
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise ValueError("need prob_miss < 0.5 < prob_hit")
        if not self.clamp_min < 0.5 < self.clamp_max:
            raise ValueError("need clamp_min < 0.5 < clamp_max")

    @property
    def logs(self) -> tuple[np.float32, np.float32, np.float32, np.float32]:
        return (
            logodds(self.prob_hit),
            logodds(self.prob_miss),
            logodds(self.clamp_min),
            logodds(self.clamp_max),
        )


@dataclass(frozen=True)
class FusionParams:
    """Label fusion constants (see the module docstring)."""

    max_same_gain: float = 0.5
    max_disagree_factor: float = 0.9
    bayes_min_confidence: float = 1e-3  # keeps c in [eps, 1 - eps] so no class reaches 0 or 1

    def __post_init__(self):
        if not 0.0 <= self.max_same_gain <= 1.0:
            raise ValueError(f"max_same_gain must be in [0, 1], got {self.max_same_gain}")
        if not 0.0 < self.max_disagree_factor <= 1.0:
            raise ValueError(
                f"max_disagree_factor must be in (0, 1], got {self.max_disagree_factor}"
            )
        if not 0.0 < self.bayes_min_confidence < 0.5:
            raise ValueError("bayes_min_confidence must be in (0, 0.5)")


# -- label fusion ------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _fuse_max(sem_l, sem_p, g, label, conf, gain, penalty):
    cl = sem_l[g, 0]
    old = sem_p[g, 0]
    cp = np.float64(old)
    c = np.float64(conf)
    if cl == 0:
        sem_l[g, 0] = label
        sem_p[g, 0] = c
        return True
    if cl == label:
        sem_p[g, 0] = cp + gain * c * (1.0 - cp)
    elif c > cp:
        sem_l[g, 0] = label
        sem_p[g, 0] = penalty * c
        return True
    else:
        sem_p[g, 0] = penalty * cp
    return sem_p[g, 0] != old


@njit(cache=True, error_model="numpy")
def _fuse_bayes(sem_l, sem_p, g, label, conf, n_classes, eps):
    c = min(max(np.float64(conf), eps), 1.0 - eps)
    q = (1.0 - c) / (n_classes - 1)
    n_set = 0
    mass = 0.0
    found = False
    for s in range(3):
        if sem_l[g, s] != 0:
            n_set += 1
            mass += np.float64(sem_p[g, s])
            if sem_l[g, s] == label:
                found = True
    n_rest = n_classes - n_set
    r = max(1.0 - mass, 0.0) / n_rest if n_rest > 0 else 0.0
    # unnormalised posteriors of the stored classes, the new class and the rest
    z = 0.0
    # top-3 insertion, stable: an earlier candidate wins a tie
    l0 = l1 = l2 = np.uint16(0)
    p0 = p1 = p2 = -1.0
    for s in range(4):
        if s < 3:
            cl = sem_l[g, s]
            if cl == 0:
                continue
            cp = np.float64(sem_p[g, s]) * (c if cl == label else q)
        else:
            if found:
                break
            cl = np.uint16(label)
            cp = r * c
            n_rest -= 1
        z += cp
        if cp > p0:
            l2, p2 = l1, p1
            l1, p1 = l0, p0
            l0, p0 = cl, cp
        elif cp > p1:
            l2, p2 = l1, p1
            l1, p1 = cl, cp
        elif cp > p2:
            l2, p2 = cl, cp
    z += n_rest * r * q
    old_l0 = sem_l[g, 0]
    old_p0 = sem_p[g, 0]
    sem_l[g, 0] = l0
    sem_p[g, 0] = p0 / z
    sem_l[g, 1] = l1
    sem_p[g, 1] = p1 / z if p1 >= 0 else 0.0
    sem_l[g, 2] = l2
    sem_p[g, 2] = p2 / z if p2 >= 0 else 0.0
    # the map exposes the top class; lower ranks moving alone is not a visible change
    return sem_l[g, 0] != old_l0 or sem_p[g, 0] != old_p0


# -- integration kernels -------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _octree_collect(
    points,
    labels,
    confs,
    origin,
    i0,
    prm,
    mode,
    n_classes,
    sem_ok,
    h_keys,
    h_vals,
    hshift,
    block_keys,
    n_blocks,
    bits,
    flags,
    sem_l,
    sem_p,
    touched,
    n_touched,
    keybuf,
):
    """Phase 1: walk every ray, mark free / hit voxels, fuse labels. Resumable at point i."""
    res = prm[0]
    inv_res = prm[1]
    max_range = prm[2]
    ray_m = prm[3]
    gain = prm[4]
    penalty = prm[5]
    eps = prm[6]
    ox = np.float32(origin[0])
    oy = np.float32(origin[1])
    oz = np.float32(origin[2])
    vb = 3 * bits
    n_cap = touched.shape[0]
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    for i in range(i0, points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        dx = np.float32(px - ox)
        dy = np.float32(py - oy)
        dz = np.float32(pz - oz)
        dist = np.sqrt(np.float64(np.float32(np.float32(dx * dx + dy * dy) + dz * dz)))
        hit = max_range < 0 or dist <= max_range
        ln = np.float32(dist)
        if hit:
            ex, ey, ez = px, py, pz
        else:  # OctoMap: carve up to origin + direction * maxrange, no end point
            mr = np.float32(max_range)
            ex = np.float32(ox + np.float32(np.float32(dx / ln) * mr))
            ey = np.float32(oy + np.float32(np.float32(dy / ln) * mr))
            ez = np.float32(oz + np.float32(np.float32(dz / ln) * mr))
        sx, sy, sz = ox, oy, oz
        if ray_m > 0 and (dist if hit else max_range) > ray_m:
            rm = np.float32(ray_m)
            sx = np.float32(ex - np.float32(np.float32(dx / ln) * rm))
            sy = np.float32(ey - np.float32(np.float32(dy / ln) * rm))
            sz = np.float32(ez - np.float32(np.float32(dz / ln) * rm))
        nk = octomap_ray_keys(sx, sy, sz, ex, ey, ez, res, inv_res, keybuf)
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
            g = (last_b << vb) | local
            f = flags[g]
            if f & MARK_ANY == 0:  # first time this cloud: remember it for phase 2
                if n_touched >= n_cap:
                    return GROW_TOUCHED, i, n_blocks, n_touched
                flags[g] = f | MARK_FREE
                touched[n_touched] = g
                n_touched += 1
        if not hit:
            continue
        kx = coord_to_key(px, inv_res)
        ky = coord_to_key(py, inv_res)
        kz = coord_to_key(pz, inv_res)
        if not key_in_range(kx, ky, kz):
            continue
        bkey, local = voxel_index(kx, ky, kz, bits)
        if bkey != last_key:
            b, n_blocks = table_find_or_insert(h_keys, h_vals, hshift, block_keys, n_blocks, bkey)
            if b < 0:
                return -b, i, n_blocks, n_touched
            last_key = bkey
            last_b = b
        g = (last_b << vb) | local
        f = flags[g]
        if f & MARK_ANY == 0:
            if n_touched >= n_cap:
                return GROW_TOUCHED, i, n_blocks, n_touched
            touched[n_touched] = g
            n_touched += 1
        flags[g] = f | MARK_HIT
        label = labels[i]
        if sem_ok[label]:
            if mode == FUSION_MAX:
                moved = _fuse_max(sem_l, sem_p, g, label, confs[i], gain, penalty)
            else:
                moved = _fuse_bayes(sem_l, sem_p, g, label, confs[i], n_classes, eps)
            if moved:
                flags[g] |= MARK_SEM
    return DONE, points.shape[0], n_blocks, n_touched


@njit(cache=True, error_model="numpy")
def _octree_apply(touched, n_touched, flags, logodds_, l_hit, l_miss, c_min, c_max, changed):
    """Phase 2: one OctoMap log-odds update per marked voxel (hit wins); list what changed.
    Returns (changed count, newly observed voxels, change in the occupied count)."""
    nc = 0
    d_obs = 0
    d_occ = 0
    for t in range(n_touched):
        g = touched[t]
        f = flags[g]
        lo = logodds_[g]
        upd = l_hit if f & MARK_HIT else l_miss
        new = lo
        # OctoMap's early abort: a node already at the clamping bound does not move
        if not ((upd >= 0 and lo >= c_max) or (upd <= 0 and lo <= c_min)):
            new = np.float32(lo + upd)
            if new < c_min:
                new = c_min
            elif new > c_max:
                new = c_max
        is_changed = new != lo or f & OBSERVED == 0 or f & MARK_SEM != 0
        if f & OBSERVED == 0:
            d_obs += 1
        elif lo > 0:
            d_occ -= 1
        if new > 0:
            d_occ += 1
        logodds_[g] = new
        flags[g] = (f & ~MARK_ANY) | OBSERVED
        if is_changed:
            changed[nc] = g
            nc += 1
    return nc, d_obs, d_occ


@njit(cache=True, error_model="numpy")
def _delta_rows(
    g, block_keys, bits, res, logodds_, sem_l, sem_p, keys, centres, labels, confs, occupied, values
):
    """Fill the Delta columns of voxels g in one pass (cheaper than numpy fancy indexing)."""
    vb = 3 * bits
    bm = (1 << bits) - 1
    for i in range(g.shape[0]):
        gi = g[i]
        bx, by, bz = unpack_block(block_keys[gi >> vb])
        local = gi & ((1 << vb) - 1)
        kx = (bx << bits) | (local & bm)
        ky = (by << bits) | ((local >> bits) & bm)
        kz = (bz << bits) | ((local >> (2 * bits)) & bm)
        keys[i, 0] = kx
        keys[i, 1] = ky
        keys[i, 2] = kz
        centres[i, 0] = (kx + 0.5) * res
        centres[i, 1] = (ky + 0.5) * res
        centres[i, 2] = (kz + 0.5) * res
        v = logodds_[gi]
        values[i] = v
        occupied[i] = 1 if v > 0 else 0
        labels[i] = sem_l[gi, 0]
        confs[i] = sem_p[gi, 0]


def ray_buffer(max_len_m: float, resolution_m: float) -> np.ndarray:
    """Key buffer long enough for any DDA walk of `max_len_m` (3 steps per voxel length)."""
    return np.empty((3 * int(np.ceil(max_len_m / resolution_m)) + 16, 3), np.int64)


class OctreeBackend:
    """Occupancy + semantic voxel map; `integrate` returns the Delta of one cloud.

    Inputs are validated by `SemanticMap`; this class trusts its arguments.
    """

    def __init__(
        self,
        resolution_m: float,
        fusion: str,
        max_range_m: float,
        ray_length_m: float | None,
        semantic_lut: np.ndarray,
        n_classes: int,
        occupancy: OccupancyParams = OccupancyParams(),
        fusion_params: FusionParams = FusionParams(),
        block_bits: int = 3,
    ):
        if fusion not in FUSIONS:
            raise ValueError(f"fusion must be one of {sorted(FUSIONS)}, got {fusion!r}")
        if fusion == "bayes" and n_classes < 2:
            raise ValueError("bayes fusion needs at least 2 semantic classes")
        self.resolution_m = float(resolution_m)
        self.fusion = fusion
        self.max_range_m = float(max_range_m)
        self.ray_length_m = ray_length_m
        self.semantic_lut = semantic_lut
        self.n_classes = int(n_classes)
        self.occupancy = occupancy
        self.fusion_params = fusion_params
        n_sem = 1 if fusion == "max" else 3
        self.grid = BlockGrid(
            block_bits,
            {
                "logodds": (np.float32, ()),
                "label": (np.uint16, (n_sem,)),
                "prob": (np.float32, (n_sem,)),
                "flags": (np.uint8, ()),
            },
        )
        self._touched = np.empty(1 << 16, np.int64)
        self.last_updates = 0
        self.n_observed = 0  # kept up to date by the kernels: stats() never scans the map
        self.n_occupied = 0
        self._keybuf = ray_buffer(self.max_range_m, self.resolution_m)
        self._prm = np.array(
            [
                self.resolution_m,
                1.0 / self.resolution_m,
                self.max_range_m,
                -1.0 if ray_length_m is None else float(ray_length_m),
                fusion_params.max_same_gain,
                fusion_params.max_disagree_factor,
                fusion_params.bayes_min_confidence,
            ]
        )

    def _grow_touched(self) -> None:
        new = np.empty(self._touched.shape[0] * 2, np.int64)
        new[: self._touched.shape[0]] = self._touched
        self._touched = new

    def integrate(self, points, labels, confs, origin) -> Delta:
        grid = self.grid
        i, n_touched = 0, 0
        mode = FUSIONS[self.fusion]
        while True:
            c = grid.cols
            status, i, grid.n_blocks, n_touched = _octree_collect(
                points,
                labels,
                confs,
                origin,
                i,
                self._prm,
                mode,
                self.n_classes,
                self.semantic_lut,
                grid.h_keys,
                grid.h_vals,
                grid.hshift,
                grid.block_keys,
                grid.n_blocks,
                grid.bits,
                c["flags"],
                c["label"],
                c["prob"],
                self._touched,
                n_touched,
                self._keybuf,
            )
            if status == DONE:
                break
            if status == GROW_TOUCHED:
                self._grow_touched()
            else:
                grid.handle(status)
        self.last_updates = n_touched  # voxel log-odds updates of this cloud
        l_hit, l_miss, c_min, c_max = self.occupancy.logs
        changed = np.empty(n_touched, np.int64)
        c = grid.cols
        nc, d_obs, d_occ = _octree_apply(
            self._touched, n_touched, c["flags"], c["logodds"], l_hit, l_miss, c_min, c_max, changed
        )
        self.n_observed += d_obs
        self.n_occupied += d_occ
        return self._rows(changed[:nc])

    def _rows(self, g: np.ndarray) -> Delta:
        n = g.shape[0]
        d = Delta(
            np.empty((n, 3), np.int32),
            np.empty((n, 3), np.float32),
            np.empty(n, np.uint16),
            np.empty(n, np.float32),
            np.empty(n, np.uint8),
            np.empty(n, np.float32),
        )
        c, grid = self.grid.cols, self.grid
        _delta_rows(
            g,
            grid.block_keys,
            grid.bits,
            self.resolution_m,
            c["logodds"],
            c["label"],
            c["prob"],
            d.keys,
            d.centres,
            d.labels,
            d.confidences,
            d.occupied,
            d.values,
        )
        return d

    # -- queries ---------------------------------------------------------------------------

    def recount(self) -> None:
        """Recompute the counters from the columns (after a load)."""
        self.n_observed = int(self.observed_index().shape[0])
        self.n_occupied = int(self.occupied_index().shape[0])

    def observed_index(self) -> np.ndarray:
        return np.flatnonzero(self.grid.used("flags") & OBSERVED)

    def occupied_index(self) -> np.ndarray:
        used = self.grid.used
        return np.flatnonzero((used("flags") & OBSERVED).astype(bool) & (used("logodds") > 0))

    def rows(self, g: np.ndarray) -> Delta:
        return self._rows(np.asarray(g, np.int64))

    def known(self, g: np.ndarray) -> np.ndarray:
        return (self.grid.cols["flags"][g] & OBSERVED).astype(bool)

    def top_classes(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.grid.cols["label"][g], self.grid.cols["prob"][g]

    def bytes_per_voxel(self) -> int:
        return sum(
            col.dtype.itemsize * int(np.prod(col.shape[1:])) for col in self.grid.cols.values()
        )
