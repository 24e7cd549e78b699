"""The TSDF's integration on several cores, bit-identical to the serial kernel of tsdf.py.

The serial kernel is voxblox's fast integrator: rays in cloud order, each stopping at the first
voxel that an earlier ray of the same cloud reached. So a voxel takes at most one ray per cloud,
and which ray that is depends on the order. The work splits in three passes:

1. serial, `select_rays`: the rays the serial kernel casts (range limits, start-voxel subsampling:
   the first point of each cell, in cloud order), a cheap probe per point;
2. parallel over ray blocks, `cast_walks`: each ray's band, its voxblox walk and the block
   look-up of every voxel (read-only on the block hash; a voxel whose block is missing is left
   to pass 3);
3. serial, `claim_voxels`: in cloud order, blocks allocated as the serial kernel allocates them
   (same order, so the same block indices), and each ray marks the voxels of its walk up to the
   first one already marked: the ray that owns each voxel this cloud, a flag read per voxel;
4. parallel over rays, `fuse_claimed`: distance, weight and label step of every claimed voxel.
   Each voxel has one owner, so no two threads write the same voxel and every voxel sees the
   same arithmetic on the same inputs as in the serial kernel: identical bits.

This is the order-preserving half of voxblox's own answer: its fast integrator spreads the rays
over threads and takes a voxel's first ray *in time* (not reproducible), its merged integrator
groups the rays of a voxel (another result); nvblox projects voxels into a depth image (no
rays). The serial passes (1 and 3) bound the gain on two cores. The Delta rows, one per voxel,
run in parallel as well (`rows_parallel`). The surface extraction stays serial: in parallel,
a neighbour shared by several updated voxels is tested once by each (the serial pass marks it
seen), which cost more CPU than the second core saved in wall time (26 against 17 ms per 50 m
scan, docs/benchmarks.md).

The passes take their inputs as named tuples (`RayChunk`, `Walks`, tsdf_fusion.py's `TsdfConsts`,
the `Grid`), but a parallel pass takes the arrays it writes one by one: inside a numba parallel
loop, writes through an array taken from a tuple there are lost (numba 0.68.1, numba issues 7135 and
10338), and a parallel loop takes no tuple nested in another (numba issue 10139), so `TsdfState`,
which holds the `Grid`, stays with the serial passes. `rows_parallel`, with seven output columns,
takes them as one tuple and names each from it before its loop, a form whose writes land
(`tests/test_tsdf_parallel.py` checks the forms that lose writes and this one).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from smana.services.mapper.backends.tsdf_fusion import (
    FusedRay,
    fuse_ray,
    ray_band,
    row_labels,
    set_slot,
    start_key,
)
from smana.services.mapper.block_grid import (
    DONE,
    GROW_TOUCHED,
    MARK_ANY,
    MARK_FREE,
    put_key_centre,
    table_find,
    unpack_block,
    voxblox_ray_keys,
    voxel_index,
    voxel_slot,
)


class RayChunk(NamedTuple):
    """The rays sel[r0:r1] of a cloud, the part of it a pass works on."""

    points: np.ndarray  # f4 [N, 3]: the cloud
    labels: np.ndarray  # u2 [N]
    origin: np.ndarray  # [3]: the sensor's position
    sel: np.ndarray  # i8: the rays the serial kernel casts, in cloud order (`select_rays`)
    r0: int
    r1: int


class Walks(NamedTuple):
    """The walks of a chunk's rays, row r - r0 for ray sel[r]."""

    gbuf: np.ndarray  # i8 [chunk, n]: global index of each voxel of the walk, -1: no block yet
    nks: np.ndarray  # i8 [chunk]: voxels in the walk
    missing: np.ndarray  # bool [chunk]: a voxel's block did not exist when the walk was cast
    claimed: np.ndarray  # i8 [chunk]: voxels the ray owns this cloud (the first ones)


@njit(cache=True, error_model="numpy")
def select_rays(points, origin, k, startset, sel):
    """Indices of the rays the serial kernel casts, in cloud order; returns their number."""
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    n = 0
    for i in range(points.shape[0]):
        dx = np.float64(points[i, 0]) - ox
        dy = np.float64(points[i, 1]) - oy
        dz = np.float64(points[i, 2]) - oz
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        if dist < k.min_range or dist == 0.0:
            continue
        if k.sub_inv > 0:
            skey = start_key(points, i, k.sub_inv)
            s = set_slot(startset, skey)
            if startset[s] == skey:
                continue
            startset[s] = skey
        sel[n] = i
        n += 1
    return n


@njit(cache=True, error_model="numpy", parallel=True)
def cast_walks(rays, k, grid, keybuf, gbuf, nks, missing):
    """The rays of a `RayChunk`, in `keybuf.shape[0]` blocks: each ray's voxel count and global
    indices (`Walks`' nks and gbuf), -1 where the block does not exist yet (`missing` set)."""
    points, _, origin, sel, r0, r1 = rays
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    n_blocks = keybuf.shape[0]
    n = r1 - r0
    vb = 3 * grid.bits
    for b in prange(n_blocks):
        keys = keybuf[b]
        last_key = np.int64(-1)
        last_b = np.int64(-1)
        for r in range(r0 + b * n // n_blocks, r0 + (b + 1) * n // n_blocks):
            _, _, _, _, _, ex, ey, ez, sx, sy, sz = ray_band(points, sel[r], ox, oy, oz, k)
            nk = voxblox_ray_keys(ex, ey, ez, sx, sy, sz, k.inv_res, keys)
            row = r - r0
            nks[row] = nk
            miss = False
            for j in range(nk):
                bkey, local = voxel_index(keys[j, 0], keys[j, 1], keys[j, 2], grid.bits)
                if bkey != last_key:
                    last_b = table_find(grid, bkey)
                    last_key = bkey
                if last_b < 0:
                    gbuf[row, j] = -1
                    miss = True
                else:
                    gbuf[row, j] = (last_b << vb) | local
            missing[row] = miss


@njit(cache=True, error_model="numpy")
def claim_voxels(rays, k, st, walks, r, n_touched):
    """Rays sel[r:r1] of a `RayChunk`, in order: allocate the blocks their walks need, then mark
    each walk up to the first voxel already marked (`walks.claimed`: how many voxels ray r owns).
    Resumable like the serial kernel: (status, next ray, n_touched)."""
    points, _, origin, sel, r0, r1 = rays
    gbuf, nks, missing, claimed = walks
    grid = st.grid
    flags = st.flags
    touched = st.touched
    keybuf = st.keybuf
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    while r < r1:
        row = r - r0
        nk = nks[row]
        if n_touched + nk > touched.shape[0]:
            return GROW_TOUCHED, r, n_touched
        if missing[row]:  # walk again with allocation, in the serial kernel's order
            _, _, _, _, _, ex, ey, ez, sx, sy, sz = ray_band(points, sel[r], ox, oy, oz, k)
            voxblox_ray_keys(ex, ey, ez, sx, sy, sz, k.inv_res, keybuf)
            for j in range(nk):
                g, last_key, last_b = voxel_slot(
                    grid, keybuf[j, 0], keybuf[j, 1], keybuf[j, 2], last_key, last_b
                )
                if g < 0:
                    return -g, r, n_touched
                gbuf[row, j] = g
            missing[row] = False
        c = 0
        for j in range(nk):
            g = gbuf[row, j]
            f = flags[g]
            if f & MARK_ANY:  # the fast integrator drops the rest of this ray
                break
            flags[g] = f | MARK_FREE
            touched[n_touched] = g
            n_touched += 1
            c += 1
        claimed[row] = c
        r += 1
    return DONE, r1, n_touched


@njit(cache=True, error_model="numpy", parallel=True)
def fuse_claimed(rays, k, grid, walks, flags, distance, weight, logp):
    """Fuse the rays of a `RayChunk` into the voxels they own (`walks`); returns the newly
    observed count. The columns written come one by one (module docstring)."""
    points, labels, origin, sel, r0, r1 = rays
    gbuf = walks.gbuf
    claimed = walks.claimed
    block_keys = grid.block_keys
    bits = grid.bits
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    vb = 3 * bits
    bm = (1 << bits) - 1
    new = 0
    for r in prange(r0, r1):
        row = r - r0
        c = claimed[row]
        if c == 0:
            continue
        i = sel[r]
        dist, dx, dy, dz, clearing, _, _, _, _, _, _ = ray_band(points, i, ox, oy, oz, k)
        ray = FusedRay(ox, oy, oz, dx, dy, dz, dist, -1 if clearing else k.sem_idx[labels[i]])
        for j in range(c):
            g = gbuf[row, j]
            bx, by, bz = unpack_block(block_keys[g >> vb])
            local = g & ((1 << vb) - 1)
            key = (
                (bx << bits) | (local & bm),
                (by << bits) | ((local >> bits) & bm),
                (bz << bits) | ((local >> (2 * bits)) & bm),
            )
            new += fuse_ray(flags, distance, weight, logp, k, g, key, ray)
    return new


@njit(cache=True, error_model="numpy", parallel=True)
def rows_parallel(grid, distance, logp, tables, g, out):
    """tsdf.py's `_tsdf_rows` over the threads: each row is its own. Its seven output columns
    would not fit as arguments: each is taken from `out` by its name before the loop, a form
    whose writes land (`a, b = out` there, or `out.keys` inside the loop, would lose them;
    tests/test_tsdf_parallel.py checks the three forms)."""
    keys = out.keys
    centres = out.centres
    labels = out.labels
    probs = out.confidences
    values = out.values
    alt_labels = out.alt_labels
    alt_probs = out.alt_confidences
    res, exp_steps, class_ids = tables  # read only: unpacking is safe, and no tuple per row
    for i in prange(g.shape[0]):
        gi = g[i]
        put_key_centre(grid, gi, res, keys, centres, i)
        values[i] = distance[gi]
        row = row_labels(logp, gi, exp_steps, class_ids)
        labels[i], probs[i], alt_labels[i], alt_probs[i] = row
