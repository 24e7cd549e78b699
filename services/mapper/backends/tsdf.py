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
an update is O(1) instead of O(K). Every entry is then a whole number of log(p / q) steps, so a
voxel stores int16 step counts (2 bytes per class instead of 4, and exact where float32 sums
drifted); a count pushed below -32767 by the shifts saturates there, a probability of
exp(-32767 log(p / q)), zero in any float. The voxel label is the most probable class.

Surface (voxblox's mesh and Kimera's, without the triangles): a voxel is a surface voxel when its
weight is at least `min_weight` and one of its 6 face neighbours, also of weight >= `min_weight`,
has the opposite sign of distance, and the voxel is the one of that pair nearer the zero crossing
(|d| <= |d_neighbour|; on a tie the voxel in front, d >= 0, wins). That is one voxel per sign
change, so the surface is one voxel thick whatever the pose noise does to the band of small
distances. Since the status depends on the neighbours, the delta of a cloud carries the updated
voxels and those of their face neighbours whose status flipped, each with its new status.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np
from numba import njit

from smana.services.mapper.backends.base import MapBackend
from smana.services.mapper.backends.params import TsdfConfig
from smana.services.mapper.backends.tsdf_fusion import (
    STEPS_MIN,
    FusedRay,
    RowTables,
    TsdfConsts,
    fuse_ray,
    ray_band,
    row_labels,
    set_slot,
    start_key,
)
from smana.services.mapper.backends.tsdf_surface import SURFACE, extract_kernel, surface_kernel
from smana.services.mapper.block_grid import (
    DONE,
    GROW_TOUCHED,
    MARK_ANY,
    MARK_FREE,
    MARK_HIT,
    Grid,
    put_key_centre,
    voxblox_ray_keys,
    voxel_slot,
)
from smana.services.mapper.delta import Delta

_RENORM_AT = 30.0  # shift a log-probability vector once its top entry exceeds this (nats)
_CHUNK_RAYS = 1 << 15  # rays per pass of the parallel integration (bounds its buffers)
_PARALLEL_ROWS = 4096  # fewer Delta rows are built on one thread (waking the others costs more)


class TsdfState(NamedTuple):
    """The map as the kernel sees it: the block hash, the voxel columns and scratch buffers."""

    grid: Grid
    flags: np.ndarray  # u1 [voxels]: OBSERVED and this cloud's marks
    distance: np.ndarray  # f4 [voxels], metres
    weight: np.ndarray  # f4 [voxels]
    logp: np.ndarray  # i2 [voxels, K]: log-probability per semantic class, in log(p / q) steps
    touched: np.ndarray  # i8: voxels marked this cloud, in order
    keybuf: np.ndarray  # i8 [n, 3]: one ray's voxel keys
    gbuf: np.ndarray  # i8 [n]: their global indices
    counts: np.ndarray  # i8 [1]: newly observed voxels


@njit(cache=True, error_model="numpy")
def _tsdf_integrate(points, labels, origin, st, k, startset, i0, n_touched):
    """Integrate points i0.. ; resumable: every block is allocated before a ray updates anything.
    Returns (status, i, n_touched); `st.counts` accumulates the counters."""
    inv_res = k.inv_res
    min_range = k.min_range
    sub_inv = k.sub_inv
    grid = st.grid
    flags = st.flags
    touched = st.touched
    keybuf = st.keybuf
    gbuf = st.gbuf
    counts = st.counts
    ox = np.float64(origin[0])
    oy = np.float64(origin[1])
    oz = np.float64(origin[2])
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    for i in range(i0, points.shape[0]):
        dist, dx, dy, dz, clearing, ex, ey, ez, sx, sy, sz = ray_band(points, i, ox, oy, oz, k)
        if dist < min_range or dist == 0.0:
            continue
        skey = np.int64(-1)
        sslot = np.int64(-1)
        if sub_inv > 0:
            skey = start_key(points, i, sub_inv)
            sslot = set_slot(startset, skey)
            if startset[sslot] == skey:
                continue
        # cast from behind the surface towards the sensor, as voxblox does
        nk = voxblox_ray_keys(ex, ey, ez, sx, sy, sz, inv_res, keybuf)
        if n_touched + nk > touched.shape[0]:
            return GROW_TOUCHED, i, n_touched
        for j in range(nk):
            g, last_key, last_b = voxel_slot(
                grid, keybuf[j, 0], keybuf[j, 1], keybuf[j, 2], last_key, last_b
            )
            if g < 0:
                return -g, i, n_touched
            gbuf[j] = g
        if sub_inv > 0:
            startset[sslot] = skey
        ray = FusedRay(ox, oy, oz, dx, dy, dz, dist, -1 if clearing else k.sem_idx[labels[i]])
        for j in range(nk):
            g = gbuf[j]
            f = flags[g]
            if f & MARK_ANY:  # the fast integrator drops the rest of this ray
                break
            flags[g] = f | MARK_FREE
            touched[n_touched] = g
            n_touched += 1
            key = (keybuf[j, 0], keybuf[j, 1], keybuf[j, 2])
            counts[0] += fuse_ray(flags, st.distance, st.weight, st.logp, k, g, key, ray)
    return DONE, points.shape[0], n_touched


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


@njit(cache=True, error_model="numpy")
def _tsdf_rows(grid, distance, logp, tables, g, out):
    """The Delta columns `out` (`DeltaColumns`, but `occupied`) of voxels g in one pass:
    coordinates, distance and `row_labels`."""
    keys, centres, labels, probs, _, values, alt_labels, alt_probs = out
    res, exp_steps, class_ids = tables
    for i in range(g.shape[0]):
        gi = g[i]
        put_key_centre(grid, gi, res, keys, centres, i)
        values[i] = distance[gi]
        row = row_labels(logp, gi, exp_steps, class_ids)
        labels[i], probs[i], alt_labels[i], alt_probs[i] = row


class Tsdf(MapBackend):
    """Semantic TSDF voxel map; `integrate` returns the Delta of one cloud."""

    name = "tsdf"
    values_kind = "signed_distance"
    config_key = "tsdf"
    config_class = TsdfConfig
    clip_to_extent = True  # the TSDF keys are only safe inside the extent

    def __init__(self, config: TsdfConfig, **geometry):
        if len(geometry["class_ids"]) < 2:
            raise ValueError("tsdf needs at least 2 semantic classes")
        super().__init__(config, **geometry)
        k = len(self.class_ids)
        self.sem_idx = np.full(65536, -1, np.int16)
        self.sem_idx[self.class_ids] = np.arange(k)
        p = config.label_probability
        self.log_ratio = float(np.log(p / ((1.0 - p) / (k - 1))))  # nats per step of `logp`
        self.trunc_m = config.truncation_voxels * self.resolution_m
        self.min_weight = float(config.min_weight)
        self._parallel_loaded = False  # the parallel kernels were called once (`_rows`)
        self._touched = np.empty(1 << 16, np.int64)
        band = 2 * self.trunc_m + self.resolution_m
        n_buf = 3 * int(np.ceil(band / self.resolution_m)) + 16
        self._keybuf = np.empty((n_buf, 3), np.int64)
        self._gbuf = np.empty(n_buf, np.int64)
        sub = config.start_voxel_subsampling
        self._consts = TsdfConsts(
            self.resolution_m,
            1.0 / self.resolution_m,
            self.max_range_m,
            self.trunc_m,
            float(config.max_weight),
            float(config.min_range_m),
            sub / self.resolution_m if sub > 0 else 0.0,
            bool(config.use_weight_dropoff),
            int(np.floor(_RENORM_AT / self.log_ratio)) + 1,
            self.sem_idx,
        )
        self.grid.loaders["logp"] = self._logp_from_nats
        # exp(-d log(p / q)) for d steps behind the top class, down to float64's underflow
        self._exp_steps = np.exp(-np.arange(int(750 / self.log_ratio) + 1) * self.log_ratio)
        self._row_tables = RowTables(self.resolution_m, self._exp_steps, self.class_ids)

    def fields(self):
        return {
            "distance": (np.float32, ()),
            "weight": (np.float32, ()),
            "logp": (np.int16, (len(self.class_ids),)),
            "flags": (np.uint8, ()),
        }

    def _state(self, counts: np.ndarray) -> TsdfState:
        c = self.grid.cols
        return TsdfState(
            self.grid.state(),
            c["flags"],
            c["distance"],
            c["weight"],
            c["logp"],
            self._touched,
            self._keybuf,
            self._gbuf,
            counts,
        )

    @property
    def threads(self) -> int:
        """Threads the integration runs on (`threads` of the config, capped at numba's)."""
        import numba

        n = numba.config.NUMBA_NUM_THREADS
        return n if self.config.threads == 0 else min(self.config.threads, n)

    def integrate(self, points, labels, confs, origin) -> Delta:
        del confs  # Kimera's fast integrator uses a fixed measurement probability
        grid = self.grid
        size = 1 << max(4, int(2 * points.shape[0]).bit_length())
        startset = np.full(size, -1, np.int64)
        counts = np.zeros(1, np.int64)
        threads = self.threads
        if threads > 1:
            n_touched = self._integrate_parallel(points, labels, origin, startset, counts, threads)
        else:
            n_touched = self._integrate_serial(points, labels, origin, startset, counts)
        changed = np.empty(n_touched, np.int64)
        nc = _tsdf_finish(self._touched, n_touched, grid.cols["flags"], changed)
        self.last_updates = nc  # voxels whose distance was fused this cloud
        self.n_observed += int(counts[0])
        # a voxel's status depends on its neighbours: re-extract around every updated voxel
        out_g = np.empty(7 * nc, np.int64)
        out_surf = np.empty(7 * nc, np.bool_)
        n, dcount = extract_kernel(
            changed[:nc],
            self._state(counts),
            self.min_weight,
            np.empty(7 * nc, np.int64),
            out_g,
            out_surf,
        )
        self.n_occupied += dcount
        return self._rows(out_g[:n], out_surf[:n])

    def _grow(self, status: int, n_touched: int) -> None:
        """Make room after a kernel returned `status` (resumed afterwards)."""
        if status == GROW_TOUCHED:
            new = np.empty(self._touched.shape[0] * 2, np.int64)
            new[:n_touched] = self._touched[:n_touched]
            self._touched = new
        else:
            self.grid.handle(status)

    def _integrate_serial(self, points, labels, origin, startset, counts) -> int:
        i, n_touched = 0, 0
        while True:
            status, i, n_touched = _tsdf_integrate(
                points, labels, origin, self._state(counts), self._consts, startset, i, n_touched
            )
            if status == DONE:
                return n_touched
            self._grow(status, n_touched)

    def _integrate_parallel(self, points, labels, origin, startset, counts, threads) -> int:
        """The same map on `threads` threads (tsdf_parallel.py), chunk by chunk of rays."""
        # OpenMP threads that spin between the short parallel passes burn a core the other
        # services need (CPU per scan doubled on a loaded 2-core machine): sleep instead, unless
        # the user chose. Read when numba first loads its OpenMP layer, so set before that.
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        import numba

        from smana.services.mapper.backends import tsdf_parallel as par

        numba.set_num_threads(threads)
        k = self._consts
        sel = np.empty(points.shape[0], np.int64)
        n_sel = par.select_rays(points, origin, k, startset, sel)
        chunk = min(n_sel, _CHUNK_RAYS)
        n_buf = self._keybuf.shape[0]
        walks = par.Walks(
            np.empty((chunk, n_buf), np.int64),
            np.empty(chunk, np.int64),
            np.empty(chunk, np.bool_),
            np.empty(chunk, np.int64),
        )
        keybufs = np.empty((4 * threads, n_buf, 3), np.int64)  # one per block of rays
        n_touched = 0
        for r0 in range(0, n_sel, chunk):
            rays = par.RayChunk(points, labels, origin, sel, r0, min(r0 + chunk, n_sel))
            par.cast_walks(
                rays, k, self.grid.state(), keybufs, walks.gbuf, walks.nks, walks.missing
            )
            r = r0
            while True:
                status, r, n_touched = par.claim_voxels(
                    rays, k, self._state(counts), walks, r, n_touched
                )
                if status == DONE:
                    break
                self._grow(status, n_touched)
            c = self.grid.cols
            counts[0] += par.fuse_claimed(
                rays, k, self.grid.state(), walks, c["flags"], c["distance"], c["weight"], c["logp"]
            )
        return n_touched

    # -- surface extraction ----------------------------------------------------------------

    def _check_index(self, g) -> np.ndarray:
        g = np.ascontiguousarray(g, np.int64)
        if g.ndim != 1:
            raise ValueError(f"voxel indices must be a 1-D array, got shape {g.shape}")
        n = self.grid.n_blocks * self.grid.voxels_per_block
        if g.shape[0] and (g.min() < 0 or g.max() >= n):
            raise ValueError(f"voxel indices must lie in [0, {n})")
        return g

    def surface(self, g) -> np.ndarray:
        """Bool per voxel index: is it a surface voxel (zero crossing, min weight)?"""
        g = self._check_index(g)
        out = np.empty(g.shape[0], np.bool_)
        c = self.grid.cols
        surface_kernel(g, self.grid.state(), c["distance"], c["weight"], self.min_weight, out)
        return out

    def _logp_from_nats(self, saved: np.ndarray) -> np.ndarray:
        """A map saved before the step counts holds float32 log-probabilities: whole steps."""
        if saved.dtype.kind == "f":
            saved = np.maximum(np.rint(saved / self.log_ratio), STEPS_MIN)
        return saved.astype(np.int16)

    def _store_surface(self, g: np.ndarray, surface: np.ndarray) -> int:
        """Set the SURFACE bits of g; returns the change in the number of surface voxels."""
        flags = self.grid.cols["flags"]
        f = flags[g]
        was = (f & SURFACE) != 0
        flags[g] = np.where(surface, f | SURFACE, f & ~SURFACE)
        return int(surface.sum()) - int(was.sum())

    def recount(self) -> None:
        # a loaded map (format 2 files have no SURFACE bits) gets its bits from the distances
        g = self.observed_index()
        self._store_surface(g, self.surface(g))
        super().recount()

    def labels_of(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(label, probability of that label) from the log-probability vectors."""
        d = self._rows(np.asarray(g, np.int64), np.zeros(len(g), np.bool_))
        return d.labels, d.confidences

    def _steps_behind_top(self, g: np.ndarray) -> np.ndarray:
        steps = self.grid.cols["logp"][g].astype(np.int64)
        return steps.max(axis=1, keepdims=True) - steps

    def probabilities(self, g: np.ndarray) -> np.ndarray:
        """Normalised class probabilities (rows follow `class_ids`)."""
        d = self._steps_behind_top(g)
        lut = self._exp_steps
        e = np.where(d < lut.shape[0], lut[np.minimum(d, lut.shape[0] - 1)], 0.0)
        return e / e.sum(axis=1, keepdims=True)

    def rows(self, g: np.ndarray) -> Delta:
        g = self._check_index(g)
        return self._rows(g, self.surface(g))

    def _rows(self, g: np.ndarray, surface: np.ndarray) -> Delta:
        d = Delta.empty(g.shape[0])
        d.occupied = surface.astype(np.uint8)
        c = self.grid.cols
        rows = _tsdf_rows
        if self.threads > 1 and (g.shape[0] >= _PARALLEL_ROWS or not self._parallel_loaded):
            # the first cloud takes every parallel kernel: a service's warm-up loads them all
            self._parallel_loaded = True
            import numba

            from smana.services.mapper.backends.tsdf_parallel import rows_parallel as rows

            numba.set_num_threads(self.threads)
        rows(self.grid.state(), c["distance"], c["logp"], self._row_tables, g, d.columns())
        return d

    # -- queries ---------------------------------------------------------------------------

    def occupied_index(self) -> np.ndarray:
        g = self.observed_index()
        return g[self.surface(g)]
