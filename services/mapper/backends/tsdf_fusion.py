"""One ray's fusion into the TSDF, as the serial integrator (tsdf.py) and the parallel one
(tsdf_parallel.py) both run it: the kernels' per-map constants (`TsdfConsts`, `RowTables`), a
ray's band (`ray_band`), its fusion into one voxel (`fuse_ray`: voxblox's projective distance and
weight, Kimera's label step), the start-voxel subsampling set (`start_key`, `set_slot`) and a
voxel's label columns (`row_labels`). Written once, inlined into both integrators' kernels, so
the two make the same map to the bit (tests/test_tsdf_parallel.py). The model is tsdf.py's
docstring.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from smana.services.mapper.block_grid import MARK_FREE, MARK_HIT, OBSERVED, hash_slot, pack_block

STEPS_MIN = -32767  # saturation of the int16 step counts


class TsdfConsts(NamedTuple):
    """Per-map constants of the kernels."""

    res: float
    inv_res: float
    max_range: float
    trunc: float  # metres
    max_weight: float
    min_range: float
    sub_inv: float  # 1 / start-voxel subsampling cell, 0: off
    dropoff: bool
    renorm_steps: int  # shift the vector once its top entry reaches this many steps
    sem_idx: np.ndarray  # i2 [65536]: label -> class column, -1 for none


class FusedRay(NamedTuple):
    """A ray as `fuse_ray` takes it: the sensor's position, the point's offset from it and that
    offset's length, and the class column of the point's label (-1: none, a clearing ray)."""

    ox: float
    oy: float
    oz: float
    dx: float
    dy: float
    dz: float
    dist: float
    label_idx: int


class RowTables(NamedTuple):
    """Per-map constants of the Delta rows (`_tsdf_rows`)."""

    res: float
    exp_steps: np.ndarray  # f8: exp(-d log(p / q)) for d steps behind the top class
    class_ids: np.ndarray  # u2: the class id of each column of `logp`


@njit(cache=True, error_model="numpy", inline="always")
def set_slot(keys, key):
    """Slot of `key` in an open-addressing set, or the free slot where it would go: one probe
    sequence serves the membership test and the insertion (`keys[slot] = key`), valid until
    the next insertion."""
    mask = keys.shape[0] - 1
    s = hash_slot(key, 40) & mask  # the block table's Fibonacci hash
    while True:
        k = keys[s]
        if k == key or k == -1:
            return s
        s = (s + 1) & mask


@njit(cache=True, error_model="numpy", inline="always")
def ray_band(points, i, ox, oy, oz, k):
    """Ray i's geometry: (dist, dx, dy, dz, clearing, ex, ey, ez, sx, sy, sz), the point's
    offset from the origin and its length, and the band from e (behind the surface) to s."""
    dx = np.float64(points[i, 0]) - ox
    dy = np.float64(points[i, 1]) - oy
    dz = np.float64(points[i, 2]) - oz
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    ux = dx / dist
    uy = dy / dist
    uz = dz / dist
    trunc = k.trunc
    clearing = dist > k.max_range
    if clearing:
        ex = ox + ux * k.max_range
        ey = oy + uy * k.max_range
        ez = oz + uz * k.max_range
        sx = ex - ux * trunc
        sy = ey - uy * trunc
        sz = ez - uz * trunc
    else:
        px = np.float64(points[i, 0])
        py = np.float64(points[i, 1])
        pz = np.float64(points[i, 2])
        ex = px + ux * trunc
        ey = py + uy * trunc
        ez = pz + uz * trunc
        sx = px - ux * trunc
        sy = py - uy * trunc
        sz = pz - uz * trunc
    return dist, dx, dy, dz, clearing, ex, ey, ez, sx, sy, sz


@njit(cache=True, error_model="numpy", inline="always")
def fuse_ray(flags, distance, weight, logp, k, g, key, ray):
    """Fuse a `FusedRay` into voxel g (key: its (kx, ky, kz)), already marked MARK_FREE by that
    ray: the projective distance with its weight, and the label step. Returns 1 when the voxel is
    newly observed. A voxel takes at most one ray per cloud, so voxels are independent here. The
    columns come one by one: inside a numba parallel loop, writes through an array taken from a
    tuple there are lost (numba 0.68.1, numba issues 7135 and 10338; tests/test_tsdf_parallel.py
    checks this still holds), and this function is inlined into one
    (`tsdf_parallel.fuse_claimed`)."""
    res = k.res
    trunc = k.trunc
    ox, oy, oz, dx, dy, dz, dist, label_idx = ray
    cx = (np.float64(key[0]) + 0.5) * res
    cy = (np.float64(key[1]) + 0.5) * res
    cz = (np.float64(key[2]) + 0.5) * res
    sdf = dist - ((cx - ox) * dx + (cy - oy) * dy + (cz - oz) * dz) / dist
    w = 1.0
    if k.dropoff and sdf < -res:
        w = max((trunc + sdf) / (trunc - res), 0.0)
    w_old = np.float64(weight[g])
    w_new = w_old + w
    if w_new < 1e-6:
        return 0
    d_new = (sdf * w + np.float64(distance[g]) * w_old) / w_new
    f = flags[g]
    distance[g] = min(trunc, d_new) if d_new > 0 else max(-trunc, d_new)
    weight[g] = min(k.max_weight, w_new)
    flags[g] = f | MARK_FREE | MARK_HIT | OBSERVED
    if label_idx >= 0:
        v = np.int64(logp[g, label_idx]) + 1
        if v >= k.renorm_steps:
            for c in range(logp.shape[1]):
                logp[g, c] = max(np.int64(logp[g, c]) - v, STEPS_MIN)
            logp[g, label_idx] = 0
        else:
            logp[g, label_idx] = v
    return 1 if f & OBSERVED == 0 else 0


@njit(cache=True, error_model="numpy", inline="always")
def start_key(points, i, sub_inv):
    """Key of point i's start-voxel subsampling cell."""
    return pack_block(
        np.int64(np.floor(np.float64(points[i, 0]) * sub_inv)),
        np.int64(np.floor(np.float64(points[i, 1]) * sub_inv)),
        np.int64(np.floor(np.float64(points[i, 2]) * sub_inv)),
    )


@njit(cache=True, error_model="numpy", inline="always")
def row_labels(logp, g, exp_steps, class_ids):
    """Voxel g's label columns: (label, probability, second class, probability). The label is
    the first most probable class (0 for a uniform vector), its probability 1 / sum over the
    classes of exp(-(steps behind the top) * log(p / q)) (`RowTables.exp_steps`, 0 past its end);
    the second class is the first most probable of the others (0 when the vector is uniform or
    its probability is 0)."""
    n_exp = exp_steps.shape[0]
    top = 0
    alt = -1
    uniform = True
    for c in range(1, logp.shape[1]):
        if logp[g, c] > logp[g, top]:
            alt = top
            top = c
        elif alt < 0 or logp[g, c] > logp[g, alt]:
            alt = c
        if logp[g, c] != logp[g, 0]:
            uniform = False
    z = 0.0
    for c in range(logp.shape[1]):
        d = np.int64(logp[g, top]) - np.int64(logp[g, c])
        if d < n_exp:
            z += exp_steps[d]
    label = 0 if uniform else class_ids[top]
    d_alt = np.int64(logp[g, top]) - np.int64(logp[g, alt]) if alt >= 0 else n_exp
    if uniform or d_alt >= n_exp:
        return label, 1.0 / z, 0, 0.0
    return label, 1.0 / z, class_ids[alt], exp_steps[d_alt] / z
