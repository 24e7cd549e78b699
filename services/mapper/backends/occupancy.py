"""What `octree-max` and `octree-bayes` share: OctoMap's occupancy with Semantic Octomap's label
fusion, stored in a hashed block grid (see `block_grid.py`) instead of a pointer octree. The two
back-ends (`octree_max.py`, `octree_bayes.py`) differ only in their fusion rule.

Occupancy follows OctoMap's `insertPointCloud` exactly: for one cloud every ray's voxels are
collected first; a voxel is updated at most once as free and at most once as occupied, and a
voxel that is some ray's end point is never freed by another ray of the same cloud. Log-odds are
float32 and clamped as OctoMap does, so the same rays give the same values.

Two departures from OctoMap, both from the paper's setting:
- `raycast_range_m`: free space is carved only over the last metres before the end point (1 m in
  the paper); 0 carves the whole ray as OctoMap does. (Semantic Octomap's own generator
  instead carves the first metre from the sensor and marks farther end points occupied without a
  ray; carving next to the surface is what clears moved obstacles, so we carve there.)
- semantics: every point fuses its label into its end voxel (points labelled 0 or with a label
  outside the semantic classes update occupancy only).

Max fusion, `max_fusion = "average"` (the default), exactly Semantic Octomap's
`SemanticsMax::semanticFusion(stored, observed)` (floatlazer/semantic_slam,
`semantics_octree/semantics_max.h`): same label -> c = (c + c_obs) / 2; other label -> the one of
higher confidence (the observation on a tie) is kept, its confidence times `max_disagree_factor`
(0.9 there). `max_fusion = "gain"`, smana's earlier rule after the paper's wording that agreement
raises the confidence: same label -> c += max_same_gain * c_obs * (1 - c); other label with a
strictly higher confidence -> (label_obs, penalty * c_obs), else c *= penalty.

Bayesian fusion (Semantic Octomap `SemanticsBayesian`, with the rest of the mass spread evenly as
the paper says): the voxel keeps its 3 most probable classes; each of the K - 3 others holds an
equal share of the remaining mass. A point (label l, confidence c) is the likelihood c for l and
(1 - c) / (K - 1) for every other class; the posterior is renormalised and the top 3 kept.
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import numpy as np
from numba import njit

from smana.services.mapper.backends.base import MapBackend
from smana.services.mapper.backends.params import OctreeConfig
from smana.services.mapper.block_grid import (
    DONE,
    GROW_TOUCHED,
    MARK_ANY,
    MARK_FREE,
    MARK_HIT,
    MARK_SEM,
    OBSERVED,
    Grid,
    coord_to_key,
    key_in_range,
    octomap_ray_from,
    octomap_ray_origin,
    octomap_ray_start,
    put_key_centre,
    voxel_slot,
)
from smana.services.mapper.delta import Delta

FUSION_MAX = 0
FUSION_BAYES = 1
# octree-max's rule for a same-label observation (`OctreeConfig.max_fusion`)
MAX_AVERAGE = 0
MAX_GAIN = 1
MAX_RULES = {"average": MAX_AVERAGE, "gain": MAX_GAIN}


def logodds(p: float) -> np.float32:
    """OctoMap's logodds(): computed in double, stored as float."""
    return np.float32(np.log(p / (1.0 - p)))


def sensor_model(config: OctreeConfig) -> tuple[np.float32, np.float32, np.float32, np.float32]:
    """(hit, miss, clamp min, clamp max) as float32 log-odds, as OctoMap stores them."""
    return (
        logodds(config.prob_hit),
        logodds(config.prob_miss),
        logodds(config.clamp_min),
        logodds(config.clamp_max),
    )


class OccupancyState(NamedTuple):
    """The map as the kernels see it: the block hash, the voxel columns and scratch buffers."""

    grid: Grid
    flags: np.ndarray  # u1 [voxels]: OBSERVED and this cloud's marks
    logodds: np.ndarray  # f4 [voxels]
    label: np.ndarray  # u2 [voxels, 1 or 3]: the top classes
    prob: np.ndarray  # f4 [voxels, 1 or 3]: their confidence or probability
    touched: np.ndarray  # i8: voxels marked this cloud, in order
    keybuf: np.ndarray  # i8 [n, 3]: one ray's voxel keys
    semantic: np.ndarray  # bool [65536]: labels worth fusing


class OccupancyConsts(NamedTuple):
    """Per-map constants of the kernels."""

    res: float
    inv_res: float
    max_range: float  # < 0: no limit
    ray_m: float  # < 0: carve the whole ray
    max_rule: int  # MAX_AVERAGE | MAX_GAIN
    gain: float
    penalty: float
    eps: float
    mode: int  # FUSION_MAX | FUSION_BAYES
    n_classes: int
    l_hit: np.float32
    l_miss: np.float32
    c_min: np.float32
    c_max: np.float32


# -- label fusion ------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _fuse_max(sem_l, sem_p, g, label, conf, rule, gain, penalty):
    cl = sem_l[g, 0]
    old = sem_p[g, 0]
    cp = np.float64(old)
    c = np.float64(conf)
    if cl == 0:
        sem_l[g, 0] = label
        sem_p[g, 0] = c
        return True
    if rule == MAX_AVERAGE:
        if cl == label:
            # C++: (float + float) / 2. -- the sum rounds to float first
            sem_p[g, 0] = np.float64(np.float32(old + np.float32(conf))) / 2.0
        elif cp > c:
            sem_p[g, 0] = cp * penalty
        else:  # the observation wins a tie, as `s1.c > s2.c ? s1 : s2` does
            sem_l[g, 0] = label
            sem_p[g, 0] = c * penalty
            return True
        return sem_p[g, 0] != old
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


@njit(cache=True, error_model="numpy")
def _fuse_observations(sem_l, sem_p, rows, labels, confs, sources, k):
    """Fuse observation i (labels[i], confs[i]) into row rows[i] of (sem_l, sem_p) by the map's
    rule (`_fuse_max` / `_fuse_bayes`, the ones the cloud kernel calls). A row's observations
    are fused in a canonical order whatever their order here: by confidence, then by
    `sources[i]` (who made the observation). Grouped by row with a counting sort, each group
    sorted by insertion (a handful of observations a voxel)."""
    n = sem_l.shape[0]
    start = np.zeros(n + 1, np.int64)
    for i in range(rows.shape[0]):
        start[rows[i] + 1] += 1
    for r in range(n):
        start[r + 1] += start[r]
    fill = start[:n].copy()
    idx = np.empty(rows.shape[0], np.int64)
    for i in range(rows.shape[0]):
        idx[fill[rows[i]]] = i
        fill[rows[i]] += 1
    for r in range(n):
        a = start[r]
        b = start[r + 1]
        for j in range(a + 1, b):
            x = idx[j]
            t = j
            while t > a:
                y = idx[t - 1]
                if confs[y] < confs[x] or (confs[y] == confs[x] and sources[y] <= sources[x]):
                    break
                idx[t] = y
                t -= 1
            idx[t] = x
        for j in range(a, b):
            i = idx[j]
            if k.mode == FUSION_MAX:
                _fuse_max(sem_l, sem_p, r, labels[i], confs[i], k.max_rule, k.gain, k.penalty)
            else:
                _fuse_bayes(sem_l, sem_p, r, labels[i], confs[i], k.n_classes, k.eps)


# -- integration kernels -------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _octree_collect(points, labels, confs, origin, st, k, i0, n_touched):
    """Phase 1: walk every ray, mark free / hit voxels, fuse labels. Resumable at point i.
    Returns (status, i, n_touched)."""
    res = k.res
    inv_res = k.inv_res
    max_range = k.max_range
    ray_m = k.ray_m
    grid = st.grid
    flags = st.flags
    touched = st.touched
    max_keys = st.keybuf.shape[0]  # octomap_ray_keys' bound on a walk
    ox = np.float32(origin[0])
    oy = np.float32(origin[1])
    oz = np.float32(origin[2])
    n_cap = touched.shape[0]
    side = 1 << grid.bits  # voxels along a block's edge
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    # Every full ray starts at the sensor: its keys and tMax numerators are computed once here,
    # not once per ray.
    at_origin = octomap_ray_origin(ox, oy, oz, res, inv_res)
    # the sensor's voxel (its index and block), looked up by the first walk that starts there
    origin_g = np.int64(-1)
    origin_key = np.int64(-1)
    origin_b = np.int64(-1)
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
        if ray_m > 0 and (dist if hit else max_range) > ray_m:  # the ray's last ray_m only
            rm = np.float32(ray_m)
            sx = np.float32(ex - np.float32(np.float32(dx / ln) * rm))
            sy = np.float32(ey - np.float32(np.float32(dy / ln) * rm))
            sz = np.float32(ez - np.float32(np.float32(dz / ln) * rm))
            first, walk = octomap_ray_start(sx, sy, sz, ex, ey, ez, res, inv_res)
            from_origin = False
        elif hit:  # from the sensor to the point: dx, dy, dz and ln are the walk's own
            first, walk = octomap_ray_from(at_origin, ex, ey, ez, dx, dy, dz, ln)
            from_origin = True
        else:  # from the sensor to max_range along the ray
            cx = np.float32(ex - ox)
            cy = np.float32(ey - oy)
            cz = np.float32(ez - oz)
            c_len = np.float32(
                np.sqrt(np.float64(np.float32(np.float32(cx * cx + cy * cy) + cz * cz)))
            )
            first, walk = octomap_ray_from(at_origin, ex, ey, ez, cx, cy, cz, c_len)
            from_origin = True
        if first > 0:
            if from_origin and origin_g >= 0:  # every walk from the sensor starts in its voxel
                g, last_key, last_b = origin_g, origin_key, origin_b
            else:
                g, last_key, last_b = voxel_slot(grid, walk[0], walk[1], walk[2], last_key, last_b)
                if g < 0:
                    return -g, i, n_touched
                if from_origin:
                    origin_g, origin_key, origin_b = g, last_key, last_b
            # Mark the walk's voxels free: the keys of `octomap_ray_next`, in its order, with
            # its stops, cheaper per voxel. A step moves the voxel's index by one stride (1,
            # the block side or its square); only a step into the next block looks one up.
            _, _, _, kex, key_, kez, stx, sty, stz, tmx, tmy, tmz, tdx, tdy, tdz, flen = walk
            kx, ky, kz = walk[0], walk[1], walk[2]
            # the local coordinate a step lands on when it enters the next block, and a step's
            # stride in voxel indices (x, y, z: 1, side, side**2 voxels a block)
            enter_x = 0 if stx > 0 else side - 1
            enter_y = 0 if sty > 0 else side - 1
            enter_z = 0 if stz > 0 else side - 1
            stride_y = sty * side
            stride_z = stz * side * side
            n_keys = 0
            while True:
                f = flags[g]
                if f & MARK_ANY == 0:  # first time this cloud: remember it for phase 2
                    if n_touched >= n_cap:
                        return GROW_TOUCHED, i, n_touched
                    flags[g] = f | MARK_FREE
                    touched[n_touched] = g
                    n_touched += 1
                n_keys += 1
                if n_keys >= max_keys:
                    break
                # OctoMap's step: along the axis of the smallest tMax (a tie goes to the later
                # axis); the walk stops at the end's key or when every next crossing lies
                # beyond the ray's length, both tested on the moved axis first (the others
                # rarely decide). OctoMap tests after the step, before the key is used: so here
                # (a block looked up early would be allocated for nothing).
                if tmx < tmy and tmx < tmz:
                    kx += stx
                    tmx += tdx
                    if tmx > flen and tmy > flen and tmz > flen:
                        break
                    if kx == kex and ky == key_ and kz == kez:
                        break
                    if kx & (side - 1) != enter_x:  # still in the block
                        g += stx
                        continue
                elif tmy <= tmx and tmy < tmz:
                    ky += sty
                    tmy += tdy
                    if tmy > flen and tmx > flen and tmz > flen:
                        break
                    if ky == key_ and kx == kex and kz == kez:
                        break
                    if ky & (side - 1) != enter_y:
                        g += stride_y
                        continue
                else:
                    kz += stz
                    tmz += tdz
                    if tmz > flen and tmx > flen and tmy > flen:
                        break
                    if kz == kez and kx == kex and ky == key_:
                        break
                    if kz & (side - 1) != enter_z:
                        g += stride_z
                        continue
                g, last_key, last_b = voxel_slot(grid, kx, ky, kz, last_key, last_b)
                if g < 0:
                    return -g, i, n_touched
        if not hit:
            continue
        kx = coord_to_key(px, inv_res)
        ky = coord_to_key(py, inv_res)
        kz = coord_to_key(pz, inv_res)
        if not key_in_range(kx, ky, kz):
            continue
        g, last_key, last_b = voxel_slot(grid, kx, ky, kz, last_key, last_b)
        if g < 0:
            return -g, i, n_touched
        f = flags[g]
        if f & MARK_ANY == 0:
            if n_touched >= n_cap:
                return GROW_TOUCHED, i, n_touched
            touched[n_touched] = g
            n_touched += 1
        flags[g] = f | MARK_HIT
        label = labels[i]
        if st.semantic[label]:
            if k.mode == FUSION_MAX:
                moved = _fuse_max(
                    st.label, st.prob, g, label, confs[i], k.max_rule, k.gain, k.penalty
                )
            else:
                moved = _fuse_bayes(st.label, st.prob, g, label, confs[i], k.n_classes, k.eps)
            if moved:
                flags[g] |= MARK_SEM
    return DONE, points.shape[0], n_touched


@njit(cache=True, error_model="numpy")
def _octree_apply(st, k, n_touched, changed):
    """Phase 2: one OctoMap log-odds update per marked voxel (hit wins); list what changed.
    Returns (changed count, newly observed voxels, change in the occupied count)."""
    touched = st.touched
    flags = st.flags
    logodds_ = st.logodds
    l_hit = k.l_hit
    l_miss = k.l_miss
    c_min = k.c_min
    c_max = k.c_max
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
def _delta_rows(st, res, g, rows):
    """Fill the Delta columns (`DeltaColumns`) of voxels g in one pass (cheaper than numpy fancy
    indexing). The distribution is the voxel's top two classes (octree-max: its one label)."""
    keys, centres, labels, confs, occupied, values, alt_labels, alt_confs = rows
    second = st.label.shape[1] > 1  # bayes keeps its top 3; max one label, the rest unknown
    for i in range(g.shape[0]):
        gi = g[i]
        put_key_centre(st.grid, gi, res, keys, centres, i)
        v = st.logodds[gi]
        values[i] = v
        occupied[i] = 1 if v > 0 else 0
        labels[i] = st.label[gi, 0]
        confs[i] = st.prob[gi, 0]
        if second:
            alt_labels[i] = st.label[gi, 1]
            alt_confs[i] = st.prob[gi, 1]
        else:
            alt_labels[i] = 0
            alt_confs[i] = 0.0


def ray_buffer(max_len_m: float, resolution_m: float) -> np.ndarray:
    """Key buffer long enough for any DDA walk of `max_len_m` (3 steps per voxel length)."""
    return np.empty((3 * int(np.ceil(max_len_m / resolution_m)) + 16, 3), np.int64)


class OccupancyBackend(MapBackend):
    """Occupancy + semantic voxel map; `integrate` returns the Delta of one cloud. Subclasses
    pick the fusion rule (`fusion`) and how many top classes a voxel keeps (`n_top`)."""

    values_kind = "log_odds"
    config_key = "octree"
    config_class = OctreeConfig
    uses_ray_length = True
    fusion: ClassVar[int]
    n_top: ClassVar[int]

    def __init__(self, config: OctreeConfig, **geometry):
        super().__init__(config, **geometry)
        self.n_classes = len(self.class_ids)
        self.semantic_lut = np.zeros(65536, bool)
        self.semantic_lut[self.class_ids] = True
        self._touched = np.empty(1 << 16, np.int64)
        self._keybuf = ray_buffer(self.max_range_m, self.resolution_m)
        ray = self.raycast_range_m
        self._consts = OccupancyConsts(
            self.resolution_m,
            1.0 / self.resolution_m,
            self.max_range_m,
            -1.0 if ray == 0 else float(ray),
            MAX_RULES[config.max_fusion],
            float(config.max_same_gain),
            float(config.max_disagree_factor),
            float(config.bayes_min_confidence),
            self.fusion,
            self.n_classes,
            *sensor_model(config),
        )

    def fields(self):
        return {
            "logodds": (np.float32, ()),
            "label": (np.uint16, (self.n_top,)),
            "prob": (np.float32, (self.n_top,)),
            "flags": (np.uint8, ()),
        }

    def _state(self) -> OccupancyState:
        c = self.grid.cols
        return OccupancyState(
            self.grid.state(),
            c["flags"],
            c["logodds"],
            c["label"],
            c["prob"],
            self._touched,
            self._keybuf,
            self.semantic_lut,
        )

    def _grow_touched(self) -> None:
        new = np.empty(self._touched.shape[0] * 2, np.int64)
        new[: self._touched.shape[0]] = self._touched
        self._touched = new

    def integrate(self, points, labels, confs, origin) -> Delta:
        i, n_touched = 0, 0
        while True:
            status, i, n_touched = _octree_collect(
                points, labels, confs, origin, self._state(), self._consts, i, n_touched
            )
            if status == DONE:
                break
            if status == GROW_TOUCHED:
                self._grow_touched()
            else:
                self.grid.handle(status)
        self.last_updates = n_touched  # voxel log-odds updates of this cloud
        changed = np.empty(n_touched, np.int64)
        nc, d_obs, d_occ = _octree_apply(self._state(), self._consts, n_touched, changed)
        self.n_observed += d_obs
        self.n_occupied += d_occ
        return self.rows(changed[:nc])

    def rows(self, g: np.ndarray) -> Delta:
        g = np.asarray(g, np.int64)
        d = Delta.empty(g.shape[0])
        _delta_rows(
            self._state(),
            self.resolution_m,
            g,
            d.columns(),
        )
        return d

    def fuse_labels(
        self, n: int, rows, labels, confs, sources=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The (top classes, their confidences) of `n` voxels that start with no label and fuse
        observation i (labels[i], confs[i]) into voxel rows[i] by this back-end's own rule (the
        cloud kernel's), a voxel's observations in a canonical order: by confidence, then by
        `sources` (default: the order given). Labels that are not semantic classes are skipped
        (they update occupancy only, as in a cloud)."""
        rows = np.ascontiguousarray(rows, np.int64)
        labels = np.ascontiguousarray(labels, np.uint16)
        confs = np.ascontiguousarray(np.clip(confs, 0.0, 1.0), np.float32)
        if sources is None:
            sources = np.arange(rows.shape[0])
        sources = np.ascontiguousarray(sources, np.int64)
        keep = self.semantic_lut[labels]
        if not keep.all():
            rows, labels, confs, sources = rows[keep], labels[keep], confs[keep], sources[keep]
        sem_l = np.zeros((n, self.n_top), np.uint16)
        sem_p = np.zeros((n, self.n_top), np.float32)
        _fuse_observations(sem_l, sem_p, rows, labels, confs, sources, self._consts)
        return sem_l, sem_p

    # -- queries ---------------------------------------------------------------------------

    def occupied_index(self) -> np.ndarray:
        used = self.grid.used
        return np.flatnonzero((used("flags") & OBSERVED).astype(bool) & (used("logodds") > 0))

    def top_classes(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.grid.cols["label"][g], self.grid.cols["prob"][g]
