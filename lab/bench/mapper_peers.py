"""The peers of `smana bench mapper`, each run on the same scans as smana's back-ends: OctoMap's
C++ octree (pyoctomap) and Open3D's VoxelBlockGrid TSDF (fed depth images rendered from the
scans); and what every measurement shares (its timings, the process's memory)."""

from __future__ import annotations

import os
import resource
import time

import numpy as np

MAX_RANGE_M = 10.0
# pinhole cameras for Open3D: 4 x 90 degrees around the sensor
O3D_W, O3D_H, O3D_F = 512, 224, 256.0


def load_average() -> float:
    """The machine's 1-minute load average (a measurement under load says so)."""
    return os.getloadavg()[0]


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def timings(cfg: dict, scans, run_medians, cpu_medians, times, rss0: float) -> dict:
    """The figures every row shares: medians (of the runs' medians: robust to a busy run), p95,
    time per point, memory growth."""
    med = float(np.median(run_medians))
    n_pts = float(np.mean([s[0].shape[0] for s in scans]))
    return {
        **cfg,
        "scans": len(scans),
        "points_per_scan": n_pts,
        "median_ms": med * 1e3,
        "cpu_median_ms": float(np.median(cpu_medians) * 1e3),
        "run_medians_ms": [float(x * 1e3) for x in run_medians],
        "p95_ms": float(np.percentile(times, 95) * 1e3),
        "us_per_point": med * 1e6 / n_pts,
        "peak_rss_mb": rss_mb(),
        "rss_growth_mb": rss_mb() - rss0,
    }


def run_octomap(cfg: dict, scans) -> dict:
    import pyoctomap

    clouds = [(p.astype(np.float64), o.astype(np.float64)) for p, _, _, o in scans]
    # pyoctomap copies the numpy cloud into an octomap::Pointcloud point by point in Cython;
    # timing a max range of ~0 (every ray empty) measures that wrapper cost, subtracted below.
    probe = pyoctomap.OcTree(cfg["res"])
    over, over_cpu = [], []
    for p, o in clouds:
        t0, c0 = time.perf_counter(), time.process_time()
        probe.insertPointCloud(p, o, 1e-6, True)
        over.append(time.perf_counter() - t0)
        over_cpu.append(time.process_time() - c0)
    del probe
    rss0, load0 = rss_mb(), load_average()
    run_medians, cpu_medians, times = [], [], []
    for _ in range(cfg.get("repeats", 1)):
        tree = pyoctomap.OcTree(cfg["res"])
        run, cpu = [], []
        for p, o in clouds:
            t0, c0 = time.perf_counter(), time.process_time()
            tree.insertPointCloud(p, o, MAX_RANGE_M, True)  # lazy_eval: OctoMap's fastest path
            run.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        run_medians.append(np.median(run))
        cpu_medians.append(np.median(cpu))
        times += run
    t, ov = np.array(times), np.array(over)
    med = float(np.median(run_medians))
    leaves = tree.getNumLeafNodes()
    return {
        **cfg,
        "scans": len(scans),
        "median_ms": med * 1e3,
        "run_medians_ms": [float(x * 1e3) for x in run_medians],
        "p95_ms": float(np.percentile(t, 95) * 1e3),
        "wrapper_ms": float(np.median(ov) * 1e3),
        "cpp_median_ms": (med - float(np.median(ov))) * 1e3,
        "cpu_median_ms": float(np.median(cpu_medians) * 1e3),
        "cpp_cpu_median_ms": float((np.median(cpu_medians) - np.median(over_cpu)) * 1e3),
        "us_per_point": med * 1e6 / clouds[0][0].shape[0],
        "peak_rss_mb": rss_mb(),
        "rss_growth_mb": rss_mb() - rss0,
        "map_mb": tree.memoryUsage() / 2**20,
        "bytes_per_allocated_voxel": tree.memoryUsage() / max(leaves, 1),
        "voxels_observed": leaves,
        "load": [load0, load_average()],
    }


def depth_images(points: np.ndarray, origin: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(depth image, world-to-camera extrinsic) of 4 pinhole cameras at the sensor, looking
    along +x, +y, -x, -y; each pixel keeps its nearest point (depth along the optical axis)."""
    rel = points.astype(np.float64) - origin
    out = []
    for k in range(4):
        a = k * np.pi / 2
        fwd = np.array([np.cos(a), np.sin(a), 0.0])
        right = np.array([np.sin(a), -np.cos(a), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        rot = np.stack([right, down, fwd])  # world -> camera rows
        cam = rel @ rot.T
        z = cam[:, 2]
        front = z > 1e-3
        u = np.floor(O3D_F * cam[front, 0] / z[front] + O3D_W / 2).astype(np.int64)
        v = np.floor(O3D_F * cam[front, 1] / z[front] + O3D_H / 2).astype(np.int64)
        inside = (u >= 0) & (u < O3D_W) & (v >= 0) & (v < O3D_H)
        depth = np.full(O3D_H * O3D_W, np.inf)
        np.minimum.at(depth, v[inside] * O3D_W + u[inside], z[front][inside])
        depth[np.isinf(depth)] = 0.0  # Open3D: 0 is no return
        ext = np.eye(4)
        ext[:3, :3] = rot
        ext[:3, 3] = -rot @ origin
        out.append((depth.reshape(O3D_H, O3D_W).astype(np.float32), ext))
    return out


def run_open3d(cfg: dict, scans) -> dict:
    """Open3D's VoxelBlockGrid TSDF (tsdf and weight, no labels) on the scans' depth images."""
    import open3d as o3d
    import open3d.core as o3c

    from smana.services.mapper.backends.tsdf import TsdfConfig

    trunc = TsdfConfig().truncation_voxels
    max_range = cfg.get("max_range_m", MAX_RANGE_M)
    cpu = o3c.Device("CPU:0")
    intr = o3c.Tensor(
        np.array([[O3D_F, 0, O3D_W / 2], [0, O3D_F, O3D_H / 2], [0, 0, 1]]), o3c.float64
    )
    frames = [
        [
            (o3d.t.geometry.Image(o3c.Tensor(d)), o3c.Tensor(e, o3c.float64))
            for d, e in depth_images(p, o)
        ]
        for p, _, _, o in scans
    ]

    def grid():
        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)),
            voxel_size=cfg["res"],
            block_resolution=8,
            block_count=20000,
            device=cpu,
        )

    def integrate(vbg, frame):
        for depth, ext in frame:
            blocks = vbg.compute_unique_block_coordinates(
                depth, intr, ext, 1.0, max_range, trunc_voxel_multiplier=trunc
            )
            vbg.integrate(blocks, depth, intr, ext, 1.0, max_range, trunc_voxel_multiplier=trunc)

    integrate(grid(), frames[0])  # warm-up (first-call costs) outside the timed loop
    rss0, load0 = rss_mb(), load_average()
    run_medians, cpu_medians, times = [], [], []
    for _ in range(cfg.get("repeats", 1)):
        vbg = grid()
        run, cpu_t = [], []
        for frame in frames:
            t0, c0 = time.perf_counter(), time.process_time()
            integrate(vbg, frame)
            run.append(time.perf_counter() - t0)
            cpu_t.append(time.process_time() - c0)
        run_medians.append(np.median(run))
        cpu_medians.append(np.median(cpu_t))
        times += run
    n_blocks = int(vbg.hashmap().size())
    return {
        **timings(cfg, scans, run_medians, cpu_medians, times, rss0),
        "map_mb": n_blocks * 512 * 8 / 2**20,
        "bytes_per_allocated_voxel": 8.0,  # two float32 attributes (hash map not counted)
        "voxels_observed": n_blocks * 512,  # allocated: Open3D does not tell observed ones
        "load": [load0, load_average()],
    }
