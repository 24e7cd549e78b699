"""`smana experiment resources`: the paper's section 5 (Figures 11 and 12) on real LiDAR scans:
time per point, CPU, memory and map size of octree-max, octree-bayes and the TSDF at 0.1 / 0.3 /
0.6 m, each with its navigation graph at twice the map's resolution, and whether each keeps up
with a 10 Hz sensor.

    smana experiment resources [--quick] [--repeats 5] [--out DIR]

The data: the first five scans of KITTI odometry sequence 00 (Velodyne HDL-64E, 10 Hz, about
124,000 points each; tests/data/kitti, with its licence and provenance) placed in the world by
KITTI's ground-truth poses, the car driving about 0.86 m a scan. They carry no labels: the
geometric labeller (common/geometric.py) gives each point ground, obstacle or unknown before the
timing (untimed), and the maps use the `geometric` class table (3 classes). The TSDF's voxel
holds one int16 per class, so it runs a second time with RELLIS-3D's table (20 classes, the
paper's labels; the same labels renamed, WIDE_LABELS): the voxel real labels would give. As in
the paper: 10 m maximum range, octree ray casting limited to the last 1 m before a hit, graph
resolution twice the map's.

Each (back-end, resolution) runs in a child process of its own, so that its peak RSS is its own
(`ru_maxrss`, the resident set's high-water mark: the interpreter, numba and the scans included;
`rss growth` is what the timed part added after the kernels were compiled). The kernels are
compiled (or loaded from numba's cache) before timing. The sequence runs `--repeats` times from
an empty map and graph; a scan's time is its median over the repeats. Times are CPU times
(`process_time`), the wall time beside them: the machine this runs on is shared (loads of 10
to 40 on its 2 cores were seen), which stretches the wall clock by whatever else runs, while the
kernels are single-threaded, so a scan's CPU time is its wall time on a core of its own. Through
`lab/bench/mapper.py`'s `run_sequence` (`smana bench mapper`'s harness).

Verdict rules, fixed before the runs (lab/stats.py; the unit is a scan of the sequence, n = 5):
- "octree-max runs in real time at r" (r = 0.1 and 0.3 m, graph 2r): a scan's map + graph CPU
  time against the sensor's period, 100 ms. Reproduced when the 95 % t interval over the scans of
  (100 ms - time) lies above 0 (`decide_above`: the mean time a scan is below the period),
  not reproduced when it lies below 0.
- "the TSDF does not run in real time at r": the same on (time - 100 ms).
- "the TSDF is slower than octree-max at r": the per-scan paired difference TSDF - octree-max,
  above 0 (`decide_above`).
All on the 3-class (`geometric`) runs; the 20-class TSDF is reported beside them, not decided.
Their p-values join the verdict table of docs/experiments.md, Holm-corrected with every other
claim (`smana experiment report`). The quick form's verdicts test the tooling, not the paper.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.lab import stats

KITTI_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "kitti"
DATA_FILES = ("000000.bin", "seq00_000001-000004.npz")
BACKENDS = ("octree-max", "octree-bayes", "tsdf")
RESOLUTIONS = (0.1, 0.3, 0.6)
CLAIM_RESOLUTIONS = (0.1, 0.3)  # the paper's two settings (map / graph 0.1 / 0.2, 0.3 / 0.6 m)
PERIOD_MS = 100.0  # a 10 Hz LiDAR
RAY_M = 1.0  # the paper's octree ray casting distance
CLASSES = "geometric"  # the labeller's table: 3 classes
# The TSDF's voxel holds one int16 per class: run it a second time with RELLIS-3D's 20 classes
# (the paper's labels), the geometric labels renamed to ids of that table (ground -> asphalt,
# obstacle -> building): they carry nothing more, but the voxel is the size real labels give.
WIDE_CLASSES = "rellis3d"
WIDE_LABELS = np.array([0, 2, 10], np.uint16)  # geometric id -> rellis3d id
WIDE_BACKENDS = ("tsdf",)
# Paper, RELLIS-3D 00000, map + graph a scan (ms), Xeon W-2123 8 cores, C++ (its table of times)
PAPER_SCAN_MS = {("octree-max", 0.1): 560.0, ("tsdf", 0.1): 7200.0}
PAPER_SCAN_MS |= {("octree-max", 0.3): 100.0, ("tsdf", 0.3): 1400.0}


def kitti_sequence(n_scans: int = 5, every: int = 1):
    """[(points N x 3 float32 in the world, origin)] of KITTI 00's first `n_scans` scans (at most
    5), every `every`-th point. The world is scan 0's LiDAR frame; KITTI's poses are the left
    camera's, so a scan's LiDAR pose is Tr^-1 P_k Tr (Tr: LiDAR to camera)."""
    if not 1 <= n_scans <= 5:
        raise ValueError(f"n_scans must be 1 to 5, got {n_scans}")
    with np.load(KITTI_DIR / DATA_FILES[1]) as z:
        xyz, off = z["xyz_cm"], z["offsets"]
        cam, tr3 = z["kitti_poses"], z["kitti_tr"]
    tr = np.eye(4)
    tr[:3] = tr3
    first = np.fromfile(KITTI_DIR / DATA_FILES[0], np.float32).reshape(-1, 4)[:, :3]
    raw = [first] + [xyz[a:b].astype(np.float32) / 100 for a, b in zip(off[:-1], off[1:])]
    out = []
    for k in range(n_scans):
        p = np.eye(4)
        p[:3] = cam[k]
        pose = np.linalg.inv(tr) @ p @ tr
        pts = raw[k][::every].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        out.append((pts.astype(np.float32), pose[:3, 3].copy()))
    return out


def write_scans(path: Path, n_scans: int, every: int, relabel=None) -> list[int]:
    """The labelled sequence in `smana bench mapper`'s scans file format (labels through the
    `relabel` lookup table when given); the point counts."""
    from smana.common.geometric import label_geometric

    scans = []
    for pts, org in kitti_sequence(n_scans, every):
        lab = label_geometric(pts, org)
        if relabel is not None:
            lab = relabel[lab]
        scans.append((pts, lab, np.ones(len(pts), np.float32), org))
    from smana.lab.bench.mapper import save_scans

    return save_scans(path, scans)


def run(backends, resolutions, repeats: int, n_scans: int, every: int, in_process: bool):
    """One result of `run_sequence` per (back-end, resolution, class table): every back-end
    with the geometric table, those of WIDE_BACKENDS with RELLIS-3D's as well."""
    from smana.lab.bench import mapper as bench

    configs = [
        {
            "kind": "sequence",
            "backend": b,
            "res": r,
            "graph_res": 2 * r,
            "ray_m": RAY_M,
            "repeats": repeats,
            "classes": classes,
        }
        for r in resolutions
        for classes, names in ((CLASSES, backends), (WIDE_CLASSES, WIDE_BACKENDS))
        for b in names
        if b in backends
    ]
    results = []
    with tempfile.TemporaryDirectory(prefix="smana-resources-") as tmp:
        paths = {CLASSES: Path(tmp) / "scans.npz", WIDE_CLASSES: Path(tmp) / "wide.npz"}
        write_scans(paths[CLASSES], n_scans, every)
        write_scans(paths[WIDE_CLASSES], n_scans, every, WIDE_LABELS)
        with progress.bar(len(configs), "resources", unit="config") as bar:
            for cfg in configs:
                results.append(bench.run_config(cfg, paths[cfg["classes"]], in_process))
                bar.update()
    return results


def rows_of(results: list[dict]) -> list[dict]:
    """The compact raw rows: one per scan of each configuration, and one per configuration."""
    rows = []
    for r in results:
        if "error" in r:
            rows.append({"kind": "error", "backend": r["backend"], "res_m": r["res"]})
            continue
        key = {
            "backend": r["backend"],
            "classes": r["classes"],
            "res_m": r["res"],
            "graph_res_m": r["graph_res"],
        }
        for k in range(r["scans"]):
            rows.append(
                {
                    "kind": "scan",
                    **key,
                    "scan": k,
                    "points": r["points"][k],
                    **{f: r[f][k] for f in ("map_ms", "map_cpu_ms", "graph_ms", "graph_cpu_ms")},
                }
            )
        rep = r["repeat_scan_cpu_ms"]
        rows.append(
            {
                "kind": "config",
                **key,
                "repeats": r["repeats"],
                "repeat_scan_cpu_ms_min": min(rep),
                "repeat_scan_cpu_ms_max": max(rep),
                **{f: r[f] for f in ("peak_rss_mb", "rss_growth_mb", "map_mb", "graph_mb")},
                "voxels_observed": r["voxels_observed"],
                "load": r["load"],
            }
        )
    return rows


def _scans(rows, backend: str, res: float, classes: str = CLASSES) -> dict[int, dict]:
    return {
        r["scan"]: r
        for r in rows
        if r["kind"] == "scan"
        and r["backend"] == backend
        and r["res_m"] == res
        and r.get("classes", CLASSES) == classes
    }


def _total(r: dict) -> float:
    """A scan's map + graph CPU time (ms): what the verdicts and the table's times are made of."""
    return r["map_cpu_ms"] + r["graph_cpu_ms"]


def _wall(r: dict) -> float:
    return r["map_ms"] + r["graph_ms"]


def claims(rows: list[dict]) -> list[dict]:
    """The paper's section 5 claims, decided by the rules of the module docstring (p-values
    uncorrected: the report corrects the whole table together)."""
    out = []

    def add(claim, paper, ci, d: stats.Decision, rule):
        out.append(
            {
                "claim": claim,
                "paper": paper,
                "smana": ci.format(1.0, ".1f", " ms"),
                **d.fields(),
                "rule": rule,
                "unit": " ms",
            }
        )

    for res in CLAIM_RESOLUTIONS:  # each claim where its runs are (a failed one has none)
        octree, tsdf = _scans(rows, "octree-max", res), _scans(rows, "tsdf", res)
        g = f"{res:g} m (graph {2 * res:g} m)"
        if octree:
            add(
                f"octree-max runs in real time at {g}: map + graph a scan under {PERIOD_MS:g} ms",
                f'{PAPER_SCAN_MS["octree-max", res]:g} ms a scan, "real time"',
                stats.mean_ci([_total(r) for r in octree.values()]),
                stats.decide_above(
                    stats.mean_ci([PERIOD_MS - _total(r) for r in octree.values()]),
                    yes=f"under {PERIOD_MS:g} ms",
                    no=f"over {PERIOD_MS:g} ms",
                ),
                f"below {PERIOD_MS:g} ms",
            )
        if tsdf:
            add(
                f"the TSDF does not run in real time at {g}: map + graph a scan over "
                f"{PERIOD_MS:g} ms",
                f"{PAPER_SCAN_MS['tsdf', res]:g} ms a scan",
                stats.mean_ci([_total(r) for r in tsdf.values()]),
                stats.decide_above(
                    stats.mean_ci([_total(r) - PERIOD_MS for r in tsdf.values()]),
                    yes=f"over {PERIOD_MS:g} ms",
                    no=f"under {PERIOD_MS:g} ms",
                ),
                f"above {PERIOD_MS:g} ms",
            )
        both = sorted(set(octree) & set(tsdf))
        if both:
            diff = stats.mean_ci([_total(tsdf[k]) - _total(octree[k]) for k in both])
            add(
                f"the TSDF is slower than octree-max at {g}: TSDF minus octree-max, paired per "
                "scan",
                f"{PAPER_SCAN_MS['tsdf', res] - PAPER_SCAN_MS['octree-max', res]:g} ms",
                diff,
                stats.decide_above(diff, yes="TSDF slower", no="TSDF faster"),
                "above 0",
            )
    return out


def table(rows: list[dict]) -> list[str]:
    """The markdown table of docs/experiments.md's section 5, one line per configuration: CPU
    times (mean [95 % CI] over the scans of each scan's median over the repeats) and per point,
    the wall time and the share of it on a CPU, the share of one core the map and graph would
    take at 10 Hz (the paper's Figure 11 "CPU"), and the spread over the repeats (the lowest
    and highest of the repeats' mean CPU time a scan)."""
    lines = [
        "| back-end | map / graph res | map, CPU ms a scan | graph, CPU ms a scan | "
        "map + graph, CPU ms | us a point, CPU (map, graph) | map + graph, wall ms | CPU / wall | "
        "real time at 10 Hz (CPU) | a core at 10 Hz | repeats' spread, CPU ms a scan | map MB | "
        "graph MB | peak RSS MB (growth) | paper, map + graph |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    configs = [r for r in rows if r["kind"] == "config"]

    def order(c):
        return c["res_m"], c.get("classes", CLASSES) != CLASSES, BACKENDS.index(c["backend"])

    for c in sorted(configs, key=order):
        classes = c.get("classes", CLASSES)
        sc = list(_scans(rows, c["backend"], c["res_m"], classes).values())
        name = c["backend"] if classes == CLASSES else f"{c['backend']}, {classes} classes"
        pts = np.array([r["points"] for r in sc], float)

        def ci(values):
            return stats.mean_ci(values).format(1.0, ".1f")

        tot = stats.mean_ci([_total(r) for r in sc])
        us_map = float(np.mean(np.array([r["map_cpu_ms"] for r in sc]) / pts) * 1e3)
        us_graph = float(np.mean(np.array([r["graph_cpu_ms"] for r in sc]) / pts) * 1e3)
        cpu = sum(_total(r) for r in sc) / sum(_wall(r) for r in sc)
        rt = "yes" if tot.defined and tot.hi < PERIOD_MS else "no" if tot.lo > PERIOD_MS else "?"
        paper = PAPER_SCAN_MS.get((c["backend"], c["res_m"])) if classes == CLASSES else None
        lines.append(
            f"| {name} | {c['res_m']:g} / {c['graph_res_m']:g} m | "
            f"{ci([r['map_cpu_ms'] for r in sc])} | {ci([r['graph_cpu_ms'] for r in sc])} | "
            f"{tot.format(1.0, '.1f')} | {us_map:.2f}, {us_graph:.3f} | "
            f"{ci([_wall(r) for r in sc])} | {cpu:.0%} | {rt} | {tot.mean / PERIOD_MS:.0%} | "
            f"{c['repeat_scan_cpu_ms_min']:.1f}-{c['repeat_scan_cpu_ms_max']:.1f} | "
            f"{c['map_mb']:.1f} | "
            f"{c['graph_mb']:.2f} | {c['peak_rss_mb']:.0f} ({c['rss_growth_mb']:.0f}) | "
            f"{'-' if paper is None else f'{paper:g} ms'} |"
        )
    return lines


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    from smana.common.cli import doc_summary, positive_int

    r = sub.add_parser(
        "resources",
        help="section 5: time per point, CPU and memory of the back-ends on real KITTI scans",
        description=doc_summary(__doc__),
        epilog="Duration measured once on a 2-core machine (load 13 to 44): about 150 s with the "
        "default 5 repeats (12 configurations of 5 scans, a child process each); --quick (2 "
        "scans, every 8th point, 0.3 m, in-process) a few seconds. Exit status 1 when a "
        "configuration failed.",
    )
    r.add_argument(
        "--out", type=Path, help="output directory (default runs/experiment-resources-<time>)"
    )
    r.add_argument(
        "--quick", action="store_true", help="2 scans, every 8th point, 0.3 m, in-process"
    )
    r.add_argument(
        "--repeats", type=positive_int, default=5, help="runs of the sequence (default 5)"
    )


def check_args(args, parser=None) -> None:
    """Refuse to start without the scans, before the output directory exists (one line)."""
    from smana.common.cli import UsageError

    missing = [n for n in DATA_FILES if not (KITTI_DIR / n).is_file()]
    if missing:  # an installed wheel has no tests/: the scans ship with the source tree only
        raise UsageError(
            f"the KITTI scans are not here ({KITTI_DIR}: {', '.join(missing)} missing); "
            "run smana experiment resources from a source checkout"
        )


def main(args, parser, out: Path) -> int:
    t0 = time.perf_counter()
    # the quick form: 2 scans, every 8th point, 0.3 m, once, in-process (the test suite's)
    res, repeats, n_scans, every = (
        ((0.3,), 1, 2, 8) if args.quick else (RESOLUTIONS, args.repeats, 5, 1)
    )
    results = run(BACKENDS, res, repeats, n_scans, every, in_process=args.quick)
    rows = rows_of(results)
    out.mkdir(parents=True, exist_ok=True)
    from .report import write_data

    command = "smana experiment resources" + (
        " --quick" if args.quick else f" --repeats {args.repeats}"
    )
    meta = {
        "command": command,
        "quick": bool(args.quick),
        "data": f"KITTI odometry 00, scans 0-{n_scans - 1}, "
        + ("every point" if every == 1 else f"every {every}th point")
        + ", geometric labels",
        "cpus": os.cpu_count(),
        "duration_s": round(time.perf_counter() - t0, 1),
    }
    write_data(out, "resources", rows, meta)
    (out / "resources_results.json").write_text(json.dumps(results, indent=1))
    lines = [
        f"# Section 5 on real scans: resources of the back-ends ({meta['data']})",
        "",
        *(["_Quick run: its verdicts test the tooling, not the paper._", ""] if args.quick else []),
        *table(rows),
        "",
        "| claim | paper | smana, mean [95 % CI] (n) | rule | p | verdict |",
        "|---|---|---|---|---|---|",
        *(
            f"| {c['claim']} | {c['paper']} | {c['smana']} | {c['rule']} | "
            f"{stats.format_p(c['p'], c['p_tests'])} | "
            f"{c['verdict']} |"
            for c in claims(rows)
        ),
    ]
    (out / "resources_summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    failed = [r for r in results if "error" in r]
    for r in failed:
        print(f"resources: {r['backend']} {r['res']:g} m failed: {r['error']}", file=sys.stderr)
    print(f"wall time {meta['duration_s']:.0f} s")
    return 1 if failed else 0
