"""`smana bench navgraph`: integrating one 131k-point LiDAR scan's map delta into the graph.

A deterministic synthetic scan stands in for a RELLIS-3D Ouster OS1-64 sweep (64 beams x 2048
azimuths = 131,072 rays, 45 degrees vertical field of view, 10 m max range, as in the paper) over
a garden: rolling terrain and grass, trees (cylinders) and hedges (boxes). From it the benchmark
builds the delta an octree mapper would publish at 0.1 m (every hit voxel occupied, the voxels of
the last 1 m of each ray free: ray casting limited to 1 m as in the paper) and a TSDF-style delta
(voxels within 2 voxels of each hit, with signed distances), each voxel with a label
distribution as a mapper's deltas carry one since issue 29 (`distribution`), and times
`NavGraph.integrate` at 0.2 m:

- first scan: an empty graph (tile allocation included);
- next scan: the scan taken 0.5 m further on, integrated into the warm graph;
- tsdf: the TSDF delta into an empty graph;
- walled: the first scan inside a circular hedge 9 m away, so that every one of the 131,072 rays
  returns within range (the open garden returns about 45 % of them).

The named reference is the same highest-voxel projection done in one shot with vectorised numpy
(lexsort; no column state, so it cannot clear): it times the part of the work both do, and the
graph must agree with it node for node. Memory: the graph's bytes for 100 m and 2 km bounds hold
the same data, against what a dense array over the 2 km bounds would need.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np

from smana.common.classes import ClassTable
from smana.common.cli import doc_summary
from smana.common.config.navgraph import NavgraphConfig
from smana.services.navgraph.graph import NavGraph

MAP_RES = 0.1
GRAPH_RES = 0.2
MAX_RANGE = 10.0
RAYCAST = 1.0
GRASS, TERRAIN, HEDGE, TOPIARY, TREE = 1, 2, 4, 5, 8


class Garden:
    """An analytic garden scene that rays can be cast into."""

    def __init__(self, seed: int = 0, extent: float = 40.0, wall_radius: float | None = None):
        rng = np.random.default_rng(seed)
        # A circular hedge wall round the origin (a walled courtyard): every ray returns.
        self.wall_radius = wall_radius
        n_trees = int(extent * extent / 40)
        self.trees = np.column_stack(
            [
                rng.uniform(-extent / 2, extent / 2, (n_trees, 2)),
                rng.uniform(0.15, 0.5, n_trees),  # radius
                rng.uniform(2.0, 6.0, n_trees),  # height
            ]
        )
        n_hedges = int(extent * extent / 100)
        lo = rng.uniform(-extent / 2, extent / 2, (n_hedges, 2))
        size = np.where(rng.random((n_hedges, 1)) < 0.5, [[4.0, 0.6]], [[0.6, 4.0]])
        size = size * rng.uniform(0.5, 1.5, (n_hedges, 1))
        self.hedges = np.column_stack([lo, lo + size, rng.uniform(0.6, 1.8, n_hedges)])
        self.hedge_label = rng.choice([HEDGE, TOPIARY], n_hedges)
        # Keep the sensor's own spot clear.
        near = np.hypot(self.trees[:, 0], self.trees[:, 1]) < 2.0
        self.trees = self.trees[~near]
        mid = (self.hedges[:, :2] + self.hedges[:, 2:4]) / 2
        keep = np.hypot(mid[:, 0], mid[:, 1]) > 4.0
        self.hedges, self.hedge_label = self.hedges[keep], self.hedge_label[keep]

    @staticmethod
    def ground(x, y):
        return 0.25 * np.sin(0.35 * x) * np.cos(0.27 * y) + 0.03 * x

    @staticmethod
    def ground_label(x, y):
        return np.where(np.sin(0.6 * x + 0.3) + np.cos(0.45 * y) > 0.4, GRASS, TERRAIN)

    def scan(self, origin, n_beams=64, n_azimuths=2048, fov_deg=45.0):
        """Points (N, 3) and labels of one sweep from `origin` (rays beyond max range dropped)."""
        elev = np.deg2rad(np.linspace(-fov_deg / 2, fov_deg / 2, n_beams))
        azim = np.linspace(0, 2 * np.pi, n_azimuths, endpoint=False)
        e, a = np.meshgrid(elev, azim, indexing="ij")
        d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
        o = np.asarray(origin, np.float64)
        t_hit = np.full(len(d), np.inf)
        label = np.zeros(len(d), np.uint16)
        # Ground: march, then bisect the first crossing.
        prev = np.zeros(len(d))
        for t in np.arange(0.05, MAX_RANGE + 0.05, 0.05):
            p = o + d * t
            below = (p[:, 2] < self.ground(p[:, 0], p[:, 1])) & np.isinf(t_hit)
            if below.any():
                lo, hi = prev[below], np.full(below.sum(), t)
                for _ in range(8):
                    mid = (lo + hi) / 2
                    q = o + d[below] * mid[:, None]
                    under = q[:, 2] < self.ground(q[:, 0], q[:, 1])
                    hi = np.where(under, mid, hi)
                    lo = np.where(under, lo, mid)
                t_hit[below] = hi
                q = o + d[below] * hi[:, None]
                label[below] = self.ground_label(q[:, 0], q[:, 1])
            prev[:] = t
        # Trees: vertical cylinders.
        for cx, cy, r, h in self.trees:
            ox, oy = o[0] - cx, o[1] - cy
            qa = d[:, 0] ** 2 + d[:, 1] ** 2
            qb = 2 * (ox * d[:, 0] + oy * d[:, 1])
            qc = ox * ox + oy * oy - r * r
            disc = qb * qb - 4 * qa * qc
            ok = (disc > 0) & (qa > 1e-12)
            t = np.where(ok, (-qb - np.sqrt(np.where(ok, disc, 0))) / (2 * np.where(ok, qa, 1)), -1)
            z = o[2] + d[:, 2] * t
            base = self.ground(cx, cy)
            hit = ok & (t > 0) & (t < t_hit) & (z < base + h)
            t_hit[hit] = t[hit]
            label[hit] = TREE
        # Hedges: boxes from the ground to their height (slab method).
        for (x0, y0, x1, y1, h), lab in zip(self.hedges, self.hedge_label, strict=True):
            base = self.ground((x0 + x1) / 2, (y0 + y1) / 2) - 0.2
            lo = np.array([x0, y0, base])
            hi = np.array([x1, y1, base + 0.2 + h])
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (lo - o) / d
                t2 = (hi - o) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= tmin) & (tmin > 0) & (tmin < t_hit)
            t_hit[hit] = tmin[hit]
            label[hit] = lab
        if self.wall_radius is not None:
            qa = d[:, 0] ** 2 + d[:, 1] ** 2
            qb = 2 * (o[0] * d[:, 0] + o[1] * d[:, 1])
            qc = o[0] ** 2 + o[1] ** 2 - self.wall_radius**2  # < 0: the sensor is inside
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
            hit = (qa > 1e-12) & (t > 0) & (t < t_hit)
            t_hit[hit] = t[hit]
            label[hit] = HEDGE
        keep = t_hit <= MAX_RANGE
        return o + d[keep] * t_hit[keep, None], label[keep], d[keep], t_hit[keep]


def octree_delta(origin, points, labels, dirs, t_hit):
    """Occupied hit voxels (last label wins) and the free voxels of the last metre of each ray."""
    keys = np.floor(points / MAP_RES).astype(np.int64)
    occ_keys, idx = np.unique(keys, axis=0, return_index=True)
    occ_labels = labels[idx]
    steps = np.arange(MAP_RES / 2, RAYCAST, MAP_RES / 2)
    t = t_hit[:, None] - steps[None, :]
    t = np.where(t > 0, t, np.nan)
    free_pts = origin + dirs[:, None, :] * t[:, :, None]
    free_pts = free_pts[np.isfinite(free_pts).all(axis=2)]
    free_keys = np.unique(np.floor(free_pts / MAP_RES).astype(np.int64), axis=0)
    # A voxel that is hit stays occupied.
    packed = _pack(free_keys)
    free_keys = free_keys[~np.isin(packed, _pack(occ_keys))]
    centres = (np.concatenate([occ_keys, free_keys]) + 0.5) * MAP_RES
    lab = np.concatenate([occ_labels, np.zeros(len(free_keys), np.uint16)])
    occupied = np.r_[np.ones(len(occ_keys), np.uint8), np.zeros(len(free_keys), np.uint8)]
    values = np.where(occupied == 1, 2.0, -0.4).astype(np.float32)
    return centres.astype(np.float32), lab.astype(np.uint16), occupied, values


def tsdf_delta(origin, points, labels, dirs, t_hit):
    """Voxels within 2 voxel sizes before and after each hit, with the signed distance along the
    ray (the TSDF truncation band), one entry per voxel."""
    offsets = np.arange(-2 * MAP_RES, 2 * MAP_RES + 1e-9, MAP_RES / 2)
    t = t_hit[:, None] - offsets[None, :]
    pts = origin + dirs[:, None, :] * t[:, :, None]
    sd = np.broadcast_to(offsets[None, :], t.shape)
    keys = np.floor(pts.reshape(-1, 3) / MAP_RES).astype(np.int64)
    uk, idx = np.unique(keys, axis=0, return_index=True)
    centres = ((uk + 0.5) * MAP_RES).astype(np.float32)
    values = sd.reshape(-1)[idx].astype(np.float32)
    lab = np.repeat(labels, len(offsets))[idx]
    occupied = (np.abs(values) < MAP_RES).astype(np.uint8)
    return centres, lab.astype(np.uint16), occupied, values


def distribution(delta, seed: int = 0) -> dict:
    """A label distribution for a delta's voxels, as MapDelta v2 carries one (octree-bayes-like:
    a confidence in [0.33, 1], a second class for about half the voxels): what `integrate` gets
    from a mapper since issue 29, so the bench times that path."""
    rng = np.random.default_rng(seed)
    m = len(delta[0])
    conf = rng.uniform(0.33, 1.0, m).astype(np.float32)
    alt = np.where(rng.uniform(size=m) < 0.5, rng.choice([1, 2], m), 0).astype(np.uint16)
    alt_conf = np.where(alt > 0, (1 - conf) * rng.uniform(0.3, 1.0, m), 0).astype(np.float32)
    return {"confidences": conf, "alt_labels": alt, "alt_confidences": alt_conf}


def _pack(keys):
    k = keys + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def numpy_highest(centres, labels, occupied, classes, bounds_min, res):
    """The reference: each node's highest occupied voxel in one vectorised pass (no clearing)."""
    c = centres[occupied != 0].astype(np.float64)
    lab = labels[occupied != 0]
    ix = np.floor((c[:, 0] - bounds_min[0]) / res).astype(np.int64)
    iy = np.floor((c[:, 1] - bounds_min[1]) / res).astype(np.int64)
    gz = np.floor(c[:, 2] / MAP_RES).astype(np.int64)
    gx = np.floor((c[:, 0] - bounds_min[0]) / MAP_RES).astype(np.int64)
    gy = np.floor((c[:, 1] - bounds_min[1]) / MAP_RES).astype(np.int64)
    sub = ((gx & 255) << 8) | (gy & 255)
    node = ix * 1_000_000 + iy
    order = np.lexsort((sub, classes.obstacle_lut[lab], gz, node))
    last = np.r_[node[order][1:] != node[order][:-1], True]
    top = order[last]
    return ix[top], iy[top], lab[top], c[top, 2].astype(np.float32)


def timed(fn, runs):
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times), out


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, positive_int

    p = ArgumentParser(
        prog="smana bench navgraph",
        description=doc_summary(__doc__),
        epilog="Duration measured once on a 2-core machine: about 20 s by default; --quick about "
        "2 s.",
    )
    p.add_argument("--quick", action="store_true", help="test-sized run (16 x 512 rays, 3 runs)")
    p.add_argument("--runs", type=positive_int, help="runs per case (median reported)")
    args = p.parse_args(argv)
    runs = args.runs or (3 if args.quick else 9)
    beams, azimuths = (16, 512) if args.quick else (64, 2048)
    classes = ClassTable.load("garden3drms")
    garden = Garden(seed=1)
    origins = [np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.1, 0.0])]
    for o in origins:
        o[2] = Garden.ground(o[0], o[1]) + 0.8  # sensor 0.8 m above the ground
    t = time.perf_counter()
    scans = [garden.scan(o, beams, azimuths) for o in origins]
    deltas = [octree_delta(o, *s) for o, s in zip(origins, scans, strict=True)]
    tsdf = tsdf_delta(origins[0], *scans[0])
    walled_scan = Garden(seed=1, wall_radius=9.0).scan(origins[0], beams, azimuths)
    walled = octree_delta(origins[0], *walled_scan)
    gen_s = time.perf_counter() - t
    dist = {id(d): distribution(d, k) for k, d in enumerate([*deltas, tsdf, walled])}

    def integrate(g, d):
        return g.integrate(*d[:3], map_resolution_m=MAP_RES, **dist[id(d)])

    bounds = ((-50.0, -50.0), (50.0, 50.0))

    def fresh(b=bounds):
        config = NavgraphConfig(
            bounds_min_xy=list(b[0]),
            bounds_max_xy=list(b[1]),
            resolution_m=GRAPH_RES,
            robot_radius_m=0.4,
        )
        return NavGraph(classes, config)

    warm_up = fresh()
    integrate(warm_up, deltas[0])

    def first_timed():
        g = fresh()  # construction is not part of an update
        t0 = time.perf_counter()
        up = integrate(g, deltas[0])
        return (time.perf_counter() - t0) * 1e3, g, up

    def next_timed():
        g = fresh()
        integrate(g, deltas[0])
        t0 = time.perf_counter()
        up = integrate(g, deltas[1])
        return (time.perf_counter() - t0) * 1e3, g, up

    def tsdf_timed():
        g = fresh()
        t0 = time.perf_counter()
        up = integrate(g, tsdf)
        return (time.perf_counter() - t0) * 1e3, g, up

    def walled_timed():
        g = fresh()
        t0 = time.perf_counter()
        up = integrate(g, walled)
        return (time.perf_counter() - t0) * 1e3, g, up

    def median_of(fn):
        outs = [fn() for _ in range(runs)]
        return statistics.median(o[0] for o in outs), outs[-1][1], outs[-1][2]

    first_ms, g1, up1 = median_of(first_timed)
    next_ms, _, up2 = median_of(next_timed)
    tsdf_ms, _, up3 = median_of(tsdf_timed)
    walled_ms, _, up4 = median_of(walled_timed)
    ref_ms, ref = timed(
        lambda: numpy_highest(
            deltas[0][0], deltas[0][1], deltas[0][2], classes, bounds[0], GRAPH_RES
        ),
        runs,
    )
    # Node-for-node agreement with the reference on the first scan.
    rix, riy, rlab, rz = ref
    glab, gh, gflags = g1.grid.read_cells(np.stack([rix, riy], 1))
    agree = bool((glab == rlab).all() and np.allclose(gh, rz) and (gflags & 1).all())
    n_known = g1.grid.n_known()
    agree &= n_known == len(rix)

    big_bounds = ((-1000.0, -1000.0), (1000.0, 1000.0))
    g_big = fresh(big_bounds)
    integrate(g_big, deltas[0])
    dense_nodes = g_big.grid.shape[0] * g_big.grid.shape[1]
    # labels, heights, flags, the five int32 bookkeeping layers and the distribution (u2, u1, u1)
    per_node = sum(np.dtype(d).itemsize for d in ("u2", "f4", "u1", "u2", "u1", "u1")) + 5 * 4

    n_pts = len(scans[0][0])
    print(
        f"navgraph benchmark: {beams * azimuths} rays, {n_pts} returns within {MAX_RANGE:g} m; "
        f"map {MAP_RES} m, graph {GRAPH_RES} m, robot radius 0.4 m; median of {runs} runs"
    )
    print(f"(synthetic scene and deltas generated in {gen_s:.1f} s)")
    print(f"{'case':<34} {'voxels':>8} {'surface':>8} {'changed':>8} {'ms':>8}")
    for name, d, up, ms in (
        ("first scan, octree delta", deltas[0], up1, first_ms),
        ("next scan (+0.5 m), warm graph", deltas[1], up2, next_ms),
        ("first scan, tsdf delta", tsdf, up3, tsdf_ms),
        (f"walled: all {len(walled_scan[0])} rays return", walled, up4, walled_ms),
    ):
        print(f"{name:<34} {len(d[0]):>8} {up.n_surface:>8} {len(up.cells):>8} {ms:>8.2f}")
    print(
        f"{'reference: numpy one-shot highest':<34} {len(deltas[0][0]):>8} "
        f"{int(deltas[0][2].sum()):>8} {len(rix):>8} {ref_ms:>8.2f}"
    )
    print(f"graph agrees with the reference node for node: {'yes' if agree else 'NO'}")
    print(
        f"memory after the first scan: {g1.nbytes / 2**20:.2f} MiB with 100 m bounds, "
        f"{g_big.nbytes / 2**20:.2f} MiB with 2 km bounds ({g_big.grid.n_tiles} tiles, "
        f"{n_known} known nodes); a dense graph over 2 km would need "
        f"{dense_nodes * per_node / 2**30:.1f} GiB"
    )
    return 0 if agree else 1


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench navgraph", cli))
