"""`smana bench scale`: a robot's day at outdoor scale, a long drive through mapper, navgraph and
planner.

The drive is `lab/data/longdrive.py`'s: OS1-64-like scans (131,072 rays, 10 Hz) along a
lawnmower over a procedural 1 km^2 world at 1.5 m/s, `--km` long. The cores run in this process,
in lockstep, each scan through all three: the mapper integrates it (octree-max at 0.1 m by
default), the navgraph integrates the voxels it changed (0.2 m nodes over the 1 km^2 bounds) and
the planner answers a path from the robot back to where it was `--plan-back-m` earlier along the
drive, unknown space allowed (the replanning a robot does as its map grows). Scan generation is
not timed.

Measured, per scan: map, graph, plan and their sum (p50 / p95 / p99 / max); drops, i.e. scans a
10 Hz latest-wins receiver (a zenoh `RingChannel(1)`, as the mapper's) would have skipped given
the measured times: a scan is dropped when the previous ones keep the chain busy past the next
scan's arrival (the bench itself integrates every scan, so its maps are the lockstep ones); the
process's RSS every `--rss-every-s` seconds of drive with each core's own bytes; at the end the
map's save and load times and file size. Progress with an ETA on stderr (`common/progress`).

Output: a table on stdout and in `<out>/scale_bench.md`, the figures in `scale_bench.json`.
Exit status 1 when a goal is missed (RSS over 2 GB, a drop, save or load over 5 s) unless
`--no-goals`; --quick (a short drive of small scans, for the test suite) never checks them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.cli import doc_summary

RATE_HZ = 10.0
GOAL_RSS_MB = 2048.0
GOAL_SAVE_LOAD_S = 5.0
QUICK = {"km": 0.015, "beams": 16, "columns": 256, "plan_back_m": 5.0, "window_m": 12.0}


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def dropped(service_s: list[float], period_s: float = 1.0 / RATE_HZ) -> list[int]:
    """Scans a latest-wins receiver of depth one skips: scan k arrives at k * period_s; a scan
    that arrives while the chain is busy waits, and is replaced (dropped) when the next one
    arrives before the chain is free. `service_s[k]` is the time scan k takes once started."""
    out = []
    free_at = 0.0
    n = len(service_s)
    for k in range(n):
        arrival = k * period_s
        start = max(arrival, free_at)
        if k + 1 < n and start > (k + 1) * period_s:
            out.append(k)  # the next scan came in while this one waited: this one is dropped
            continue
        free_at = start + service_s[k]
    return out


def _pct(values) -> dict:
    if len(values) == 0:
        return {"p50": 0.0, "p95": 0.0, "p99": 0.0, "max": 0.0}
    a = np.asarray(values, float)
    return {
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def run(args: argparse.Namespace, out: Path) -> dict:
    from smana.common.classes import ClassTable
    from smana.common.config import MapperConfig, NavgraphConfig
    from smana.lab.data.longdrive import Drive, DriveWorld
    from smana.services.mapper.semantic_map import SemanticMap
    from smana.services.navgraph.graph import NavGraph
    from smana.services.planner.planner import Planner
    from smana.services.planner.planner import warm_up as planner_warm_up

    world = DriveWorld(seed=args.seed, side_m=args.side_m)
    drive = Drive(world, speed_mps=args.speed, beams=args.beams, columns=args.columns)
    n = drive.n_scans(args.km)
    classes = ClassTable.load("rellis3d")
    half = 0.5 * args.side_m + 20.0  # the lawnmower's square and the sensor's reach past it
    mapper = SemanticMap.from_config(
        MapperConfig(backend=args.backend, resolution_m=args.map_res), class_table=classes
    )
    graph = NavGraph(
        classes,
        NavgraphConfig(
            resolution_m=args.graph_res, bounds_min_xy=[-half, -half], bounds_max_xy=[half, half]
        ),
    )
    planner = Planner(graph.grid, classes)
    # the planner's kernels compile (or load) now: its first query comes 20 m into the drive,
    # past the first scan that the figures leave out (a fresh cache once cost it 670 ms)
    planner_warm_up(classes)
    store = None
    if args.window_m > 0:
        from smana.services.mapper.blockstore import BlockStore

        shutil.rmtree(out / "blockstore", ignore_errors=True)  # a previous run's regions
        store = BlockStore(mapper, out / "blockstore", keep_radius_m=args.window_m)
    rss_every = max(1, int(round(args.rss_every_s * RATE_HZ)))
    rec: dict = {
        "scans": n,
        "km": args.km,
        "speed_mps": args.speed,
        "points_in_scan": args.beams * args.columns,
        "points": [],
        "map_ms": [],
        "graph_ms": [],
        "plan_ms": [],
        "plan_ok": 0,
        "plan_failed": [],
        "rss": [],  # (scan, drive s, rss MB, map MB, graph MB, planner window MB)
    }
    rss0 = _rss_mb()
    t_start = time.perf_counter()
    stop = threading.Event()
    # SIGINT ends the drive early: the map is still saved and loaded and the figures reported
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    with progress.bar(n, "driving", unit="scan") as bar:
        for k in range(n):
            if stop.is_set():
                progress.say(f"stopped by SIGINT after {k} of {n} scans")
                break
            pts, lab, origin = drive.scan(k)
            t0 = time.perf_counter()
            if store is not None:
                store.before(origin)
            delta = mapper.integrate(pts, lab, origin=origin)
            if store is not None:
                store.after(origin)
            t1 = time.perf_counter()
            graph.integrate(
                delta.centres, delta.labels, delta.occupied, map_resolution_m=mapper.resolution_m
            )
            t2 = time.perf_counter()
            back = drive.distance_m(k) - args.plan_back_m
            if back >= 0:
                x, y, _ = world.position(back)
                res = planner.plan(origin[:2], (x, y), allow_unknown=True)
                if res.ok:
                    rec["plan_ok"] += 1
                else:
                    rec["plan_failed"].append((k, res.message))
            t3 = time.perf_counter()
            rec["points"].append(len(pts))
            rec["map_ms"].append((t1 - t0) * 1e3)
            rec["graph_ms"].append((t2 - t1) * 1e3)
            rec["plan_ms"].append((t3 - t2) * 1e3 if back >= 0 else 0.0)
            if k % rss_every == 0 or k == n - 1:
                window = planner._cache
                rec["rss"].append(
                    (
                        k,
                        k / RATE_HZ,
                        _rss_mb(),
                        mapper.stats()["bytes_reserved"] / 2**20,
                        graph.nbytes / 2**20,
                        0.0 if window is None else sum(a.nbytes for a in window) / 2**20,
                    )
                )
                # a run stopped early still leaves its figures so far
                partial = {"summary": summarise(rec), "rss": rec["rss"], "scans_done": k + 1}
                (out / "scale_bench.partial.json").write_text(json.dumps(partial, default=float))
                progress.say(
                    f"  {drive.distance_m(k) / 1000:.3f} km, scan {k}/{n}: RSS "
                    f"{rec['rss'][-1][2]:.0f} MB, last {sum(_last(rec)):.1f} ms"
                )
            bar.update()
    signal.signal(signal.SIGINT, previous)
    rec["scans_done"] = len(rec["map_ms"])
    rec["km_done"] = drive.distance_m(rec["scans_done"]) / 1000.0
    rec["wall_s"] = time.perf_counter() - t_start
    rec["rss_start_mb"] = rss0
    rec["peak_rss_mb"] = _peak_rss_mb()
    rec["map_stats"] = mapper.stats()
    rec["store"] = None if store is None else store.stats()
    rec["graph_stats"] = graph.stats()
    # Save and load the map as the mapper service does (SemanticMap.save / load).
    path = out / "scale_map.npz"
    t0 = time.perf_counter()
    mapper.save(path)
    t1 = time.perf_counter()
    loaded = SemanticMap.load(path, class_table=classes)
    t2 = time.perf_counter()
    rec["save_s"], rec["load_s"] = t1 - t0, t2 - t1
    rec["map_file_mb"] = path.stat().st_size / 2**20
    rec["load_same"] = loaded.stats()["voxels_observed"] == mapper.stats()["voxels_observed"]
    if not args.keep_map:
        path.unlink()
        shutil.rmtree(out / "blockstore", ignore_errors=True)
    return rec


def _last(rec: dict) -> tuple[float, float, float]:
    return rec["map_ms"][-1], rec["graph_ms"][-1], rec["plan_ms"][-1]


def summarise(rec: dict) -> dict:
    total = [a + b + c for a, b, c in zip(rec["map_ms"], rec["graph_ms"], rec["plan_ms"])]
    # the first scan loads every kernel (numba caches): as the other benches, not counted
    steady = slice(1, None)
    drops = dropped([t / 1e3 for t in total[steady]])
    rss = [r[2] for r in rec["rss"]]
    return {
        "map_ms": _pct(rec["map_ms"][steady]),
        "graph_ms": _pct(rec["graph_ms"][steady]),
        "plan_ms": _pct([t for t in rec["plan_ms"][steady] if t > 0]),
        "total_ms": _pct(total[steady]),
        "drops": len(drops),
        "first_drops": [k + 1 for k in drops[:10]],
        "rss_max_mb": max(rss) if rss else 0.0,
        "points_mean": float(np.mean(rec["points"])) if rec["points"] else 0.0,
    }


def report(rec: dict, s: dict, load: tuple, load_end: float) -> str:
    ms = rec["map_stats"]
    lines = [
        f"smana bench scale: {rec['km_done']:.3f} of {rec['km']:g} km at {rec['speed_mps']:g} m/s, "
        f"{rec['scans_done']} of {rec['scans']} scans "
        f"of {rec['points_in_scan']:,} rays ({s['points_mean']:,.0f} returns on average), "
        f"{rec['wall_s']:.0f} s; load average {load[0]:.2f} -> {load_end:.2f}",
        "",
        "| per scan (ms) | p50 | p95 | p99 | max |",
        "|---|---|---|---|---|",
    ]
    for name in ("map", "graph", "plan", "total"):
        p = s[f"{name}_ms"]
        lines.append(
            f"| {name} | {p['p50']:.1f} | {p['p95']:.1f} | {p['p99']:.1f} | {p['max']:.1f} |"
        )
    lines += [
        "",
        f"drops at 10 Hz (latest wins): {s['drops']} of {rec['scans_done'] - 1}"
        + (f" (first: {s['first_drops']})" if s["drops"] else ""),
        f"plans: {rec['plan_ok']} found, {len(rec['plan_failed'])} failed",
        f"RSS: start {rec['rss_start_mb']:.0f} MB, max sampled {s['rss_max_mb']:.0f} MB, peak "
        f"{rec['peak_rss_mb']:.0f} MB",
        f"map: {ms['blocks']:,} blocks, {ms['voxels_observed']:,} voxels observed, "
        f"{ms['bytes_reserved'] / 2**20:.0f} MB; graph "
        f"{rec['graph_stats']['bytes'] / 2**20:.0f} MB "
        f"({rec['graph_stats']['tiles']:,} tiles)",
        (
            "block store: off (--window-m 0): the whole map is resident"
            if rec["store"] is None
            else f"block store: {rec['store']['resident_blocks']:,} blocks resident, "
            f"{rec['store']['stored_blocks']:,} on disk in {rec['store']['stored_regions']:,} "
            f"regions ({rec['store']['stored_bytes'] / 2**20:.0f} MB); regions written "
            f"{rec['store']['regions_written']:,}, read back {rec['store']['regions_read']:,}"
        ),
        f"map file (resident part) {rec['map_file_mb']:.0f} MB: save {rec['save_s']:.2f} s, load "
        f"{rec['load_s']:.2f} s (same voxels after load: {rec['load_same']})",
        "",
        "| drive s | RSS MB | map MB | graph MB | planner window MB |",
        "|---|---|---|---|---|",
    ]
    step = max(1, len(rec["rss"]) // 12)
    for r in rec["rss"][::step] + ([rec["rss"][-1]] if (len(rec["rss"]) - 1) % step else []):
        lines.append(f"| {r[1]:.0f} | {r[2]:.0f} | {r[3]:.0f} | {r[4]:.0f} | {r[5]:.0f} |")
    return "\n".join(lines)


def goals(rec: dict, s: dict) -> list[str]:
    missed = []
    if rec["peak_rss_mb"] > GOAL_RSS_MB:
        missed.append(f"peak RSS {rec['peak_rss_mb']:.0f} MB > {GOAL_RSS_MB:.0f} MB")
    if s["drops"]:
        missed.append(f"{s['drops']} scans dropped")
    for what in ("save_s", "load_s"):
        if rec[what] > GOAL_SAVE_LOAD_S:
            missed.append(f"map {what[:-2]} {rec[what]:.2f} s > {GOAL_SAVE_LOAD_S:g} s")
    if not rec["load_same"]:
        missed.append("the loaded map differs")
    return missed


# what planner_over_box holds per node of its box at its peak (cell indices in int64 twice and
# int32, the patch's columns, the graph's and the planner's window), a bound for refusing a box
BOX_BYTES_PER_NODE = 64


def planner_over_box(w_m: float, h_m: float, graph_res: float, side_m: float) -> dict:
    """The planner on a graph whose known part is one w_m x h_m box (what a lawnmower has
    seen after w_m * h_m / lane spacing metres): a 20 m query, its repeat, and a query after a
    patch that grows the known box (the planner's window is the known box, `Planner._window`).
    Times in ms, the window's cached arrays in MB, the process's peak RSS."""
    from smana.common.classes import ClassTable
    from smana.common.navgrid import FLAG_KNOWN, NavGrid
    from smana.services.planner.planner import Planner

    half = 0.5 * side_m + 20.0
    g = NavGrid.from_bounds((-half, -half), (half, half), graph_res)
    nx, ny = int(w_m / graph_res), int(h_m / graph_res)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    cells = np.stack([ix.ravel(), iy.ravel()], 1).astype(np.int32)
    k = len(cells)
    grass = np.full(k, 3, np.uint16)
    g.apply_patch(cells, grass, np.zeros(k, np.float32), np.full(k, FLAG_KNOWN, np.uint8))
    planner = Planner(g, ClassTable.load("rellis3d"))
    a, b = g.cell_centre(10, 5), g.cell_centre(10 + int(20.0 / graph_res), 5)
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        planner.plan(a, b, allow_unknown=True)
        times.append((time.perf_counter() - t0) * 1e3)
    one = np.array([[0, min(ny + 1, g.shape[1] - 1)]], np.int32)
    g.apply_patch(one, grass[:1], np.zeros(1, np.float32), np.full(1, FLAG_KNOWN, np.uint8))
    t0 = time.perf_counter()
    planner.plan(a, b, allow_unknown=True)
    grown = (time.perf_counter() - t0) * 1e3
    return {
        "box_m": [w_m, h_m],
        "nodes": nx * ny,
        "first_ms": times[0],
        "repeat_ms": times[1],
        "after_growth_ms": grown,
        "window_mb": sum(x.nbytes for x in planner._cache) / 2**20,
        "graph_mb": g.nbytes / 2**20,
        "peak_rss_mb": _peak_rss_mb(),
    }


def main(args: argparse.Namespace) -> int:
    if args.planner_box_m:
        from smana.common.cli import UsageError

        w, h = args.planner_box_m
        nodes = int(w / args.graph_res) * int(h / args.graph_res)
        need = nodes * BOX_BYTES_PER_NODE
        have = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        if need > have:  # refused before numpy tries (and the kernel's OOM killer answers)
            raise UsageError(
                f"--planner-box-m {w:g}x{h:g}: {nodes:.3g} nodes at {args.graph_res:g} m need "
                f"about {need / 2**30:.3g} GiB, this machine has {have / 2**30:.3g} GiB"
            )
        try:
            r = planner_over_box(w, h, args.graph_res, args.side_m)
        except MemoryError:
            raise UsageError(
                f"--planner-box-m {w:g}x{h:g}: {nodes:.3g} nodes do not fit in memory"
            ) from None
        print(
            f"planner over a known box of {w:g} x {h:g} m ({r['nodes'] / 1e6:.1f} M nodes at "
            f"{args.graph_res:g} m): a 20 m query {r['first_ms']:.0f} ms first (kernels "
            f"loaded, window built), {r['repeat_ms']:.1f} ms repeat, {r['after_growth_ms']:.1f} "
            f"ms after the known box grew; window {r['window_mb']:.0f} MB, graph "
            f"{r['graph_mb']:.0f} MB, peak RSS {r['peak_rss_mb']:.0f} MB"
        )
        return 0
    if args.quick:
        args.km, args.beams, args.columns = QUICK["km"], QUICK["beams"], QUICK["columns"]
        args.plan_back_m, args.window_m = QUICK["plan_back_m"], QUICK["window_m"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    rec = run(args, out)
    s = summarise(rec)
    text = report(rec, s, load, os.getloadavg()[0])
    print(text)
    (out / "scale_bench.md").write_text(text + "\n")
    raw = {k: v for k, v in rec.items()} | {"summary": s, "load_start": load[0]}
    (out / "scale_bench.json").write_text(json.dumps(raw, indent=1, default=float))
    missed = [] if (args.quick or args.no_goals) else goals(rec, s)
    if missed:
        print("goals missed: " + "; ".join(missed), file=sys.stderr)
        return 1
    return 0


def _box(text: str) -> tuple[float, float]:
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        w = h = -1.0
    if not (np.isfinite(w) and np.isfinite(h) and w >= 30 and h >= 1):
        raise argparse.ArgumentTypeError(
            f"expected WxH in metres (W >= 30), e.g. 1000x400; got {text}"
        )
    return w, h


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, output_dir
    from smana.lab.bench.replay import BACKENDS

    def positive(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = float("nan")
        if not (np.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}")
        return v

    p = ArgumentParser(
        prog="smana bench scale",
        description=doc_summary(__doc__),
        epilog=(
            "Duration measured once on a shared 2-core machine (load average 8 to 11): about 60 s "
            "per 100 scans of 131,072 rays, scan generation included (1 km is 6,667 scans); "
            "--quick (the test suite's: 15 m of 4,096-ray scans) about 20 s. SIGINT ends the "
            "drive early and still saves, loads and reports. Output: the tables on stdout and in "
            "<out>/scale_bench.md, the figures in <out>/scale_bench.json."
        ),
    )
    p.add_argument("--km", type=positive, default=1.0, help="drive length in km (default 1)")
    p.add_argument("--speed", type=positive, default=1.5, help="m/s (default 1.5)")
    p.add_argument("--side-m", type=positive, default=1000.0, help="world square side, m")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", choices=BACKENDS, default="octree-max")
    p.add_argument("--map-res", type=positive, default=0.1, help="map resolution, m")
    p.add_argument("--graph-res", type=positive, default=0.2, help="graph resolution, m")
    p.add_argument(
        "--plan-back-m", type=positive, default=20.0, help="plan back to this far along the drive"
    )
    p.add_argument("--rss-every-s", type=positive, default=10.0, help="RSS sample period, drive s")
    p.add_argument(
        "--window-m",
        type=float,
        default=40.0,
        help="keep the map's blocks within this of the robot in memory, the rest on disk in "
        "<out>/blockstore (services/mapper/blockstore.py); 0 keeps the whole map (default 40)",
    )
    p.add_argument(
        "--planner-box-m",
        type=_box,
        default=None,
        metavar="WxH",
        help="instead of the drive: time the planner over a graph known on a W x H m box",
    )
    p.add_argument(
        "--keep-map", action="store_true", help="keep <out>/scale_map.npz and <out>/blockstore"
    )
    p.add_argument("--no-goals", action="store_true", help="exit 0 even when a goal is missed")
    p.add_argument("--quick", action="store_true", help="15 m of 4,096-ray scans (for tests)")
    p.add_argument("--out", default="runs/bench-scale", help="default: runs/bench-scale")
    args = p.parse_args(argv)
    args.beams, args.columns = 64, 2048
    from smana.common.config import MapperConfig

    reach = MapperConfig().max_range_m + 8 * args.map_res  # the block store's load radius
    if not (np.isfinite(args.window_m) and (args.window_m == 0 or args.window_m > reach)):
        p.error(f"--window-m: expected 0 or a number > {reach:g} m, got {args.window_m}")
    output_dir(args.out, "output directory", "--out")
    return main(args)


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench scale", cli))
