"""The figures of `smana bench replay`: one run's result (`RunResult`), the median over repeats
per configuration (`aggregate`) and the markdown tables of its report. replay.py runs the
stack and calls these."""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field

import numpy as np

from smana.services.mapper.backends import backend_class

# Paper, RELLIS-3D 00000, C++ on a Xeon W-2123 (8 cores): map + graph seconds per scan.
PAPER_S_PER_SCAN = {
    ("octree", 0.1): 0.56,
    ("tsdf", 0.1): 7.2,
    ("octree", 0.3): 0.10,
    ("tsdf", 0.3): 1.4,
}
PATH_QUERY_TARGET_MS = 100.0
OS1_POINTS = 131_072  # an Ouster OS1-64 scan: the paper's per-scan arithmetic
WARMUP_S = 1.0


@dataclass
class RunResult:
    backend: str
    map_res: float
    graph_res: float
    repeat: int
    scans: int = 0
    lost: int = 0
    points_per_scan: float = 0.0
    map_ms: list[float] = field(default_factory=list)  # per scan, the mapper's own timing
    graph_ms: list[float] = field(default_factory=list)  # per scan, the navgraph's own timing
    graph_e2e_ms: list[float] = field(default_factory=list)  # MapDelta -> GraphPatch arrivals
    map_us_per_point: list[float] = field(default_factory=list)
    graph_us_per_point: list[float] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)  # replay: publish -> MapDelta
    cpu_map: list[float] = field(default_factory=list)  # psutil samples, % of one core
    cpu_graph: list[float] = field(default_factory=list)
    rss_map_mb: float = 0.0
    rss_graph_mb: float = 0.0
    wall_s: float = 0.0


# -- reporting ------------------------------------------------------------------------------------


def _ms(values: list[float]) -> tuple[float, float]:
    return (float(np.mean(values)), float(np.std(values))) if values else (float("nan"),) * 2


def aggregate(runs: list[RunResult]) -> list[dict]:
    """Per configuration: the median over repeats of each figure."""
    groups: dict[tuple, list[RunResult]] = {}
    for r in runs:
        groups.setdefault((r.backend, r.map_res, r.graph_res), []).append(r)
    rows = []
    for (backend, mres, gres), rs in groups.items():

        def med(f, rs=rs):
            vals = [f(r) for r in rs]
            vals = [v for v in vals if v == v]
            return statistics.median(vals) if vals else float("nan")

        row = {
            "backend": backend,
            "map_res": mres,
            "graph_res": gres,
            "repeats": len(rs),
            "scans": rs[0].scans,
            "points_per_scan": med(lambda r: r.points_per_scan),
            "lost": max(r.lost for r in rs),
            "map_us_pt": med(lambda r: _ms(r.map_us_per_point)[0]),
            "map_us_pt_std": med(lambda r: _ms(r.map_us_per_point)[1]),
            "graph_us_pt": med(lambda r: _ms(r.graph_us_per_point)[0]),
            "graph_us_pt_std": med(lambda r: _ms(r.graph_us_per_point)[1]),
            "map_ms_scan": med(lambda r: _ms(r.map_ms)[0]),
            "graph_ms_scan": med(lambda r: _ms(r.graph_ms)[0]),
            "graph_e2e_ms": med(lambda r: _ms(r.graph_e2e_ms)[0]),
            "latency_ms": med(lambda r: _ms(r.latency_ms)[0]),
            "cpu_map": med(lambda r: _ms(r.cpu_map)[0]),
            "cpu_map_std": med(lambda r: _ms(r.cpu_map)[1]),
            "cpu_graph": med(lambda r: _ms(r.cpu_graph)[0]),
            "cpu_graph_std": med(lambda r: _ms(r.cpu_graph)[1]),
            "rss_map_mb": med(lambda r: r.rss_map_mb),
            "rss_graph_mb": med(lambda r: r.rss_graph_mb),
        }
        row["s_per_scan"] = (row["map_ms_scan"] + row["graph_ms_scan"]) / 1000.0
        # The paper's own arithmetic: time per point times a whole 131k-point scan.
        row["s_per_131k"] = (row["map_us_pt"] + row["graph_us_pt"]) * OS1_POINTS / 1e6
        # the paper reports an occupancy octree and a TSDF: compare each back-end to its kind
        distance = backend_class(backend).values_kind == "signed_distance"
        family = "tsdf" if distance else "octree"
        row["paper_s_per_scan"] = PAPER_S_PER_SCAN.get((family, round(mres, 2)))
        rows.append(row)
    return rows


def table_markdown(rows: list[dict]) -> str:
    head = (
        "| back-end | map / graph res | pts/scan | map µs/pt (±sd) | graph µs/pt (±sd) | "
        "map+graph s/scan | µs/pt x 131k | paper s/scan | CPU map % (±sd) | "
        "CPU graph % (±sd) | RAM map MB | RAM graph MB | lost |"
    )
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        paper = f"{r['paper_s_per_scan']:.2f}" if r["paper_s_per_scan"] else "-"
        lines.append(
            f"| {r['backend']} | {r['map_res']:g} / {r['graph_res']:g} m | "
            f"{r['points_per_scan']:.0f} | {r['map_us_pt']:.3f} ± {r['map_us_pt_std']:.3f} | "
            f"{r['graph_us_pt']:.3f} ± {r['graph_us_pt_std']:.3f} | {r['s_per_scan']:.3f} | "
            f"{r['s_per_131k']:.3f} | {paper} | {r['cpu_map']:.0f} ± {r['cpu_map_std']:.0f} | "
            f"{r['cpu_graph']:.0f} ± {r['cpu_graph_std']:.0f} | {r['rss_map_mb']:.0f} | "
            f"{r['rss_graph_mb']:.0f} | {r['lost']} |"
        )
    return "\n".join(lines)


def realtime_markdown(summary: dict, backend: str, mres: float, gres: float) -> str:
    lat = summary["latency"]
    pq = summary.get("path_queries", [])
    # The first second pays for loading compiled kernels in every process: shown apart.
    period_ms = 1000.0 / (summary["recorded_rate_hz"] * summary["rate_factor"])
    rows = summary["per_scan"]
    t0 = rows[0][3] if rows else 0.0
    steady = [r for r in rows if r[3] >= t0 + WARMUP_S]
    steady_lost = sum(r[5] is None for r in steady)
    steady_late = sum(r[5] is not None and r[5] > period_ms for r in steady)
    lines = [
        f"Realtime replay, {backend} {mres:g} / {gres:g} m, {summary['scans']} scans at "
        f"{summary['recorded_rate_hz']:.1f} Hz x{summary['rate_factor']:g}: "
        f"{summary['published']} published, {summary['acknowledged']} integrated, "
        f"{summary['lost']} dropped by the mapper, {summary['late_published']} published late, "
        f"{summary['late_integrated']} integrated more than one period late; "
        f"publish -> MapDelta mean {lat['mean_ms']:.0f} ms, p95 {lat['p95_ms']:.0f} ms, "
        f"max {lat['max_ms']:.0f} ms. After the first {WARMUP_S:g} s (kernels loading): "
        f"{steady_lost} dropped and {steady_late} late of {len(steady)} scans.",
    ]
    if pq:
        wall = np.array([q["wall_ms"] for q in pq])
        plan = np.array([q["planner_ms"] for q in pq if q["planner_ms"] is not None])
        ok = sum(q["ok"] for q in pq)
        errors = sorted({q["error"] for q in pq if not q["ok"]})
        within = int((wall <= PATH_QUERY_TARGET_MS).sum())
        rest = f", {wall[1:].max():.1f} ms after the first" if wall.size > 1 else ""
        lines.append(
            f"Path queries during the replay (first pose -> current pose, every 0.5 s): "
            f"{len(pq)} asked, {ok} paths found; round trip median {np.median(wall):.1f} ms, "
            f"max {wall.max():.1f} ms{rest}, {within}/{len(pq)} within "
            f"{PATH_QUERY_TARGET_MS:.0f} ms"
            + (
                f"; planner's own time median {np.median(plan):.1f} ms, max {plan.max():.1f} ms"
                if plan.size
                else ""
            )
            + (f"; errors: {', '.join(errors)}" if errors else "")
            + "."
        )
    return "\n".join(lines)
