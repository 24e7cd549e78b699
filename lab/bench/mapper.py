"""`smana bench mapper`: time the three back-ends on OS1-64-like scans, side by side with OctoMap
and Open3D.

For each scene, back-end, resolution (0.1, 0.3 m) and ray-casting mode (1 m, full ray; the TSDF
has only its truncation band), with 10 m maximum range, it prints the median and p95 time per scan
(wall and CPU), the microseconds per point, voxel updates per second, peak RAM and bytes per
allocated voxel. Two scenes: `garden` (every beam returns, most of them beyond the 10 m range, so
rays are long carving rays) and `short` (the same scans with the returns beyond 10 m dropped: all
rays end on a surface, mean range about 5 m, the case where the fixed cost per point shows);
`--scenes` also offers `near` (returns within 5 m only: the shortest rays).

Peers, on the same scans and range, each optional (a one-line hint when missing):
- OctoMap's C++ `insertPointCloud` (`pyoctomap`), beside `octree-max` with full rays; in the same
  run the voxels on which the two disagree (occupied vs free vs unknown) are counted, and a
  disagreement above 1 % fails the run (exit status 1);
- Open3D's `VoxelBlockGrid` TSDF (`open3d`, no labels), beside `tsdf`: it integrates depth
  images, so each scan is projected beforehand (untimed) into 4 pinhole depth images of 90
  degrees, 512 x 224 pixels.

The comparison table prints, per pair, both sides' wall and CPU medians, the ratios and the load
average around each side's run. Every configuration runs in a fresh child process so that its
peak RSS is its own; `--quick` runs a tiny version in-process (for the test suite). The scans come
from `scans.GardenWorld` (deterministic), 64 x 2048 = 131,072 points each before the range cut.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.cli import doc_summary
from smana.lab.bench.mapper_peers import (
    MAX_RANGE_M,
    load_average,
    rss_mb,
    run_octomap,
    run_open3d,
    timings,
)
from smana.lab.bench.mapper_report import (
    TARGETS,
    carves,
    pair_table,
    paired_results,
    ray_label,
    results_table,
    spread,
    spread_lines,
    summary,
)

SCENES = ("garden", "short")  # the default ones
NEAR_M = 5.0  # the `near` scene keeps the returns within this range


def _load_scans(path: Path):
    with np.load(path) as z:
        pts, lab, conf, org, off = (
            z[k] for k in ("points", "labels", "confidences", "origins", "offsets")
        )
    return [
        (pts[a:b], lab[a:b], conf[a:b], org[i])
        for i, (a, b) in enumerate(zip(off[:-1], off[1:], strict=True))
    ]


def save_scans(path: Path, scans: list) -> list[int]:
    """Write `(points, labels, confidences, origin)` scans in the bench's scans file format (one
    array each, `offsets` splitting them; `_load_scans` reads it back); the point counts."""
    sizes = [len(s[0]) for s in scans]
    np.savez(
        path,
        points=np.concatenate([s[0] for s in scans]),
        labels=np.concatenate([s[1] for s in scans]),
        confidences=np.concatenate([s[2] for s in scans]),
        origins=np.stack([s[3] for s in scans]),
        offsets=np.concatenate([[0], np.cumsum(sizes)]),
    )
    return sizes


def _make_scans(n_scans: int, n_beams: int, n_cols: int, scene: str, path: Path) -> dict:
    """Write the scans of `scene` to `path`; returns its point count and mean range."""
    from smana.lab.data.scans import GardenWorld

    world = GardenWorld(n_beams=n_beams, n_cols=n_cols)
    scans, ranges = [], []
    for k in range(n_scans):
        s = world.scan(k)
        r = np.linalg.norm(s.points.astype(np.float64) - s.origin, axis=1)
        cut = {"short": MAX_RANGE_M, "near": NEAR_M}.get(scene, np.inf)
        keep = r <= cut
        scans.append((s.points[keep], s.labels[keep], s.confidences[keep], s.origin))
        ranges.append(r[keep])
    sizes = save_scans(path, scans)
    r = np.concatenate(ranges)
    return {
        "points_per_scan": float(np.mean(sizes)),
        "mean_range_m": float(r.mean()),
        "beyond_range": float(np.mean(r > MAX_RANGE_M)),
    }


# -- one measurement each (run in a child process) ---------------------------------------------


def run_ours(cfg: dict, scans) -> dict:
    from smana.services.mapper.backends.params import TsdfConfig
    from smana.services.mapper.semantic_map import SemanticMap

    ray = cfg["ray_m"]
    max_range = cfg.get("max_range_m", MAX_RANGE_M)
    # the TSDF's integration threads (`smana bench tsdf`); left out, the default: every core
    tsdf_conf = TsdfConfig(threads=cfg["threads"]) if "threads" in cfg else None

    def new_map():
        m = SemanticMap(cfg["backend"], cfg["res"], max_range, ray or 0.0, config=tsdf_conf)
        if cfg.get("reserve_blocks"):
            # room for as many blocks as Open3D's grid is built with (`smana bench tsdf`),
            # before the timing as Open3D's, pages touched: on a host where a page fault costs
            # microseconds, growing the columns otherwise dominates the long ranges' scans.
            grid = m._core.grid
            grid.grow_blocks(cfg["reserve_blocks"])
            for col in grid.cols.values():
                col.fill(0)
            while grid.h_keys.shape[0] < 4 * cfg["reserve_blocks"]:
                grid.grow_table()
        return m

    # Load or compile the kernels outside the timed loop.
    warm = new_map()  # ray None: 0, the full ray
    p, lab, conf, org = scans[0]
    warm.integrate(p[:2000], lab[:2000], conf[:2000], org)
    del warm
    rss0, load0 = rss_mb(), load_average()
    run_medians, cpu_medians, times, updates, deltas = [], [], [], [], []
    for _ in range(cfg.get("repeats", 1)):  # a fresh map each run, the same scans
        m = new_map()
        run, cpu = [], []
        for p, lab, conf, org in scans:
            t0, c0 = time.perf_counter(), time.process_time()
            d = m.integrate(p, lab, conf, org)
            run.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            updates.append(m._core.last_updates)
            deltas.append(len(d))
        run_medians.append(np.median(run))
        cpu_medians.append(np.median(cpu))
        times += run
    st = m.stats()
    return {
        **timings(cfg, scans, run_medians, cpu_medians, times, rss0),
        "voxel_updates_per_s": float(np.sum(updates) / np.sum(times)),
        "delta_median": float(np.median(deltas)),
        "map_mb": st["bytes_used"] / 2**20,
        "bytes_per_allocated_voxel": st["bytes_per_allocated_voxel"],
        "bytes_reserved_per_allocated_voxel": st["bytes_reserved_per_allocated_voxel"],
        "bytes_per_observed_voxel": st["bytes_per_observed_voxel"],
        "voxels_observed": st["voxels_observed"],
        "load": [load0, load_average()],
    }


def run_agreement(cfg: dict, scans) -> dict:
    """Occupancy of our octree-max (full rays) against OctoMap on the same clouds."""
    import pyoctomap

    from smana.services.mapper.semantic_map import SemanticMap

    res = cfg["res"]
    m = SemanticMap("octree-max", res, MAX_RANGE_M, 0.0)
    tree = pyoctomap.OcTree(res)
    for p, lab, conf, org in scans:
        m.integrate(p, lab, conf, org)
        tree.insertPointCloud(
            p.astype(np.float64), org.astype(np.float32).astype(np.float64), MAX_RANGE_M, True
        )
    ours = m._core.rows(m._core.observed_index())
    mine = dict(zip(map(tuple, ours.keys.tolist()), ours.values.tolist(), strict=True))
    theirs = {}
    for leaf in tree.begin_leafs():
        # lazy_eval never prunes, so every leaf is one voxel
        k = tuple(int(np.floor(c / res)) for c in leaf.getCoordinate())
        theirs[k] = np.float32(leaf.current_node.getLogOdds())
    union = mine.keys() | theirs.keys()
    only_ours = len(mine.keys() - theirs.keys())
    only_theirs = len(theirs.keys() - mine.keys())
    both = mine.keys() & theirs.keys()
    state_diff = sum((mine[k] > 0) != (theirs[k] >= 0) for k in both)
    exact = sum(np.float32(mine[k]) == theirs[k] for k in both)
    disagree = only_ours + only_theirs + state_diff
    return {
        **cfg,
        "scans": len(scans),
        "voxels_union": len(union),
        "only_ours": only_ours,
        "only_octomap": only_theirs,
        "state_differs": int(state_diff),
        "logodds_equal": int(exact),
        "agreement": 1.0 - disagree / max(len(union), 1),
    }


def run_sequence(cfg: dict, scans) -> dict:
    """A scan sequence through the map and its navigation graph, as the mapper and navgraph
    services chain them: per scan, the map's integration, then the graph's integration of the
    map's delta (graph at `graph_res`), each timed (wall and CPU). Every repeat starts from an
    empty map and graph; each scan's figure is its median over the repeats. Memory: the map's
    and the graph's own bytes after the sequence, and the process's peak RSS (this process
    alone when run as a child)."""
    from smana.common.classes import ClassTable
    from smana.common.config.navgraph import NavgraphConfig
    from smana.services.mapper.semantic_map import SemanticMap
    from smana.services.navgraph.graph import NavGraph

    classes = ClassTable.load(cfg.get("classes", "garden3drms"))
    res, ray = cfg["res"], cfg["ray_m"]
    origins = np.array([s[3] for s in scans])
    lo = origins[:, :2].min(axis=0) - MAX_RANGE_M - 2 * cfg["graph_res"]
    hi = origins[:, :2].max(axis=0) + MAX_RANGE_M + 2 * cfg["graph_res"]
    graph_cfg = NavgraphConfig(
        resolution_m=cfg["graph_res"], bounds_min_xy=lo.tolist(), bounds_max_xy=hi.tolist()
    )

    def fresh():
        return SemanticMap(cfg["backend"], res, MAX_RANGE_M, ray or 0.0, classes), NavGraph(
            classes, graph_cfg
        )

    # load or compile the kernels outside the timed loop
    m, g = fresh()
    p, lab, conf, org = scans[0]
    d = m.integrate(p[:2000], lab[:2000], conf[:2000], org)
    g.integrate(d.centres, d.labels, d.occupied, map_resolution_m=res)
    del m, g
    rss0 = rss_mb()
    n, reps = len(scans), cfg.get("repeats", 1)
    t = np.zeros((4, reps, n))  # map wall, map CPU, graph wall, graph CPU (s)
    for r in range(reps):
        m, g = fresh()
        for k, (p, lab, conf, org) in enumerate(scans):
            t0, c0 = time.perf_counter(), time.process_time()
            d = m.integrate(p, lab, conf, org)
            t1, c1 = time.perf_counter(), time.process_time()
            g.integrate(d.centres, d.labels, d.occupied, map_resolution_m=res)
            t[:, r, k] = (t1 - t0, c1 - c0, time.perf_counter() - t1, time.process_time() - c1)
    med = np.median(t, axis=1) * 1e3  # per scan, over the repeats
    return {
        **cfg,
        "scans": n,
        "points": [int(s[0].shape[0]) for s in scans],
        "map_ms": med[0].tolist(),
        "map_cpu_ms": med[1].tolist(),
        "graph_ms": med[2].tolist(),
        "graph_cpu_ms": med[3].tolist(),
        # a repeat's mean CPU time a scan, map + graph: the spread the machine adds
        "repeat_scan_cpu_ms": ((t[1] + t[3]).mean(axis=1) * 1e3).tolist(),
        "peak_rss_mb": rss_mb(),
        "rss_growth_mb": rss_mb() - rss0,
        "map_mb": m.stats()["bytes_used"] / 2**20,
        "graph_mb": g.nbytes / 2**20,
        "voxels_observed": m.stats()["voxels_observed"],
        "load": load_average(),
    }


RUNNERS = {
    "ours": run_ours,
    "sequence": run_sequence,
    "octomap": run_octomap,
    "open3d": run_open3d,
    "agreement": run_agreement,
}
PEERS = {"octomap": "pyoctomap", "open3d": "open3d"}  # kind -> module to import


def run_config(cfg: dict, scans_path: Path, in_process: bool) -> dict:
    """One measurement of `cfg` on the scans file, in this process or in a child of its own."""
    if in_process:
        scans = _load_scans(scans_path)[: cfg.get("n_scans")]
        return RUNNERS[cfg["kind"]](cfg, scans)
    cmd = [
        sys.executable,
        "-m",
        "smana.lab.bench.mapper",
        "--child",
        json.dumps(cfg),
        "--scans-file",
        str(scans_path),
    ]
    env = None
    if "threads" in cfg:  # Open3D's OpenMP threads (smana's come from its config)
        env = {**os.environ, "OMP_NUM_THREADS": str(cfg["threads"])}
    out = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        return {**cfg, "error": out.stderr.strip().splitlines()[-1:] or ["failed"]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def have_module(module: str) -> bool:
    """Whether an optional package is installed (a one-line hint on stderr when not)."""
    try:
        __import__(module)
    except ImportError:
        print(
            f"{module} not installed (pip install 'smana[bench]'): its rows are skipped",
            file=sys.stderr,
        )
        return False
    return True


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, output_file, positive_float, positive_int
    from smana.services.mapper.backends import BACKENDS

    backends = list(BACKENDS)
    p = ArgumentParser(
        prog="smana bench mapper",
        description=doc_summary(__doc__),
        epilog=(
            "Duration measured once on a 2-core machine: about 10 minutes by default (20 scans x "
            "3 repeats "
            "per configuration, both scenes, OctoMap and Open3D included); --quick about 10 s. "
            "Exit status 1 when a configuration failed or octree-max disagrees with OctoMap on "
            "more than 1 % of the voxels. A progress bar with an ETA shows on a terminal "
            "(SMANA_PROGRESS=1 forces it, 0 hides it)."
        ),
    )
    p.add_argument("--quick", action="store_true", help="tiny scans, 0.3 m only, in-process")
    p.add_argument(
        "--scans", type=positive_int, default=20, help="scans per configuration (default 20)"
    )
    p.add_argument(
        "--repeats", type=positive_int, default=3, help="runs per configuration (default 3)"
    )
    p.add_argument("--agreement-scans", type=positive_int, default=5)
    p.add_argument("--resolutions", type=positive_float, nargs="+", default=[0.1, 0.3])
    p.add_argument("--backends", nargs="+", choices=backends, default=backends)
    p.add_argument(
        "--scenes",
        nargs="+",
        choices=(*SCENES, "near"),
        default=list(SCENES),
        help=f"garden: every return, most beyond range; short: returns within range only; "
        f"near: returns within {NEAR_M:g} m only",
    )
    p.add_argument("--no-octomap", action="store_true", help="skip the pyoctomap comparison")
    p.add_argument("--no-open3d", action="store_true", help="skip the Open3D comparison")
    p.add_argument("--in-process", action="store_true", help="no child processes (RSS shared)")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument("--out", type=Path, help="also write the JSON results to this file")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--scans-file", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.out:
        output_file(args.out)

    if args.child:
        cfg = json.loads(args.child)
        scans = _load_scans(args.scans_file)[: cfg.get("n_scans")]
        print(json.dumps(RUNNERS[cfg["kind"]](cfg, scans)))
        return 0

    beams, cols, n = (64, 2048, args.scans)
    if args.quick:
        beams, cols, n = 16, 256, 3
        args.resolutions, args.in_process, args.agreement_scans = [0.3], True, 2
        args.repeats = 1
    peers = {
        kind: not getattr(args, f"no_{kind}") and have_module(module)
        for kind, module in PEERS.items()
    }
    configs = []
    for scene in args.scenes:
        for res in args.resolutions:
            common = {"scene": scene, "res": res, "repeats": args.repeats}
            for backend in args.backends:
                # a back-end without ray carving (the TSDF's band) runs once
                for ray in [1.0, None] if carves(backend) else [None]:
                    configs.append({"kind": "ours", "backend": backend, "ray_m": ray, **common})
            if peers["octomap"] and "octree-max" in args.backends:
                configs.append({"kind": "octomap", "backend": "octomap", "ray_m": None, **common})
                configs.append(
                    {
                        "kind": "agreement",
                        "backend": "octree-max",
                        "scene": scene,
                        "res": res,
                        "ray_m": None,
                        "n_scans": args.agreement_scans,
                    }
                )
            if peers["open3d"] and "tsdf" in args.backends:
                configs.append({"kind": "open3d", "backend": "open3d", "ray_m": None, **common})
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="smana-bench-") as tmp:
        paths, scenes = {}, {}
        for scene in args.scenes:
            paths[scene] = Path(tmp) / f"{scene}.npz"
            scenes[scene] = _make_scans(n, beams, cols, scene, paths[scene])
        results = []
        with progress.bar(len(configs), "bench mapper", unit="config") as bar:
            for cfg in configs:
                if not args.json:
                    progress.say(
                        f"running {cfg['kind']} {cfg['backend']} {cfg['scene']} {cfg['res']:g} m "
                        f"{ray_label(cfg)} ...",
                        file=sys.stderr,
                    )
                results.append(run_config(cfg, paths[cfg["scene"]], args.in_process))
                bar.update()
    pairs = paired_results(results)
    lines, checks = summary(results, pairs)
    failed = any("error" in r for r in results) or checks.get("octomap_agreement", 1.0) < 0.99
    report = {
        "scans": n,
        "points_per_scan": beams * cols,
        "scenes": scenes,
        "max_range_m": MAX_RANGE_M,
        "machine": {"cpus": os.cpu_count(), "load_avg_1m": load_average()},
        "wall_s": time.perf_counter() - t_start,
        "results": results,
        "pairs": pairs,
        "spread": spread(pairs),
        "checks": checks,
        "targets": TARGETS,
        "failed": failed,
    }
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print(
            f"{n} scans of {beams} x {cols} beams, max range {MAX_RANGE_M:g} m, "
            f"load average {load_average():.2f} on {os.cpu_count()} cpus"
        )
        for scene, st in scenes.items():
            print(
                f"scene {scene}: {st['points_per_scan']:.0f} points per scan, mean range "
                f"{st['mean_range_m']:.1f} m, {st['beyond_range']:.0%} beyond {MAX_RANGE_M:g} m"
            )
        print(results_table(results))
        print()
        print(pair_table(pairs))
        print("(wall x, cpu x: smana / peer; load: 1-minute load average around both runs)")
        print("\n".join(spread_lines(report["spread"])))
        print("\n".join(lines))
        print(f"wall time {report['wall_s']:.0f} s")
    if failed:
        print("bench mapper: a configuration failed or OctoMap agreement < 99 %", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench mapper", cli))
