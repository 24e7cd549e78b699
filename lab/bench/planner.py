"""`smana bench planner`: weighted A* on deterministic cluttered graphs, side by side with scipy's
Dijkstra (`scipy.sparse.csgraph.dijkstra`) on the same graph with the same edge costs.

Each graph is a square of N x N nodes at 0.2 m: terrain, patches of grass, obstacles (hedges,
topiary, trees as discs) with their safety zone, and smooth hills whose steep flanks exceed the
maximum step height. Queries run between far-apart free nodes (corner to corner and side to side)
through the planner's real query path (`Planner.plan`: window, enter costs, A*, breakdown). Every
A* cost is checked against Dijkstra to 1e-6 relative; a disagreement fails the benchmark.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

from smana.common.classes import ClassTable
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.planner import Planner
from smana.services.planner.reference import build_graph

RES = 0.2
ROBOT_RADIUS = 0.4
GRASS, TERRAIN = 1, 2
OBSTACLES = (4, 5, 6, 8)  # hedge, topiary, rose, tree


def make_graph(n: int, seed: int = 0, classes: ClassTable | None = None):
    """A deterministic cluttered N x N garden: labels, heights, flags (dense arrays)."""
    classes = classes or ClassTable.load("garden3drms")
    rng = np.random.default_rng(seed)
    # Grass where smooth noise is high: patches of a few metres, about 40 % of the ground.
    noise = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=12, mode="wrap")
    labels = np.where(noise > np.quantile(noise, 0.6), GRASS, TERRAIN).astype(np.uint16)
    # Obstacles: discs of 0.3 to 1.5 m radius covering ~12 % of the area.
    obstacle = np.zeros((n, n), bool)
    yy, xx = np.mgrid[0:n, 0:n]
    n_discs = int(0.12 * n * n / (np.pi * (0.8 / RES) ** 2))
    centres = rng.integers(0, n, size=(n_discs, 2))
    radii = rng.uniform(0.3, 1.5, n_discs) / RES
    kinds = rng.choice(OBSTACLES, n_discs)
    for (cx, cy), r, k in zip(centres, radii, kinds, strict=True):
        ri = int(np.ceil(r))
        x0, x1, y0, y1 = max(0, cx - ri), min(n, cx + ri + 1), max(0, cy - ri), min(n, cy + ri + 1)
        disc = (xx[x0:x1, y0:y1] - cx) ** 2 + (yy[x0:x1, y0:y1] - cy) ** 2 <= r * r
        labels[x0:x1, y0:y1][disc] = k
        obstacle[x0:x1, y0:y1] |= disc
    # Hills: a few metres high over tens of metres, steep flanks in places.
    hills = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=40, mode="wrap")
    heights = (hills / np.abs(hills).max() * 0.03 * n).astype(np.float32)
    dist = ndimage.distance_transform_edt(~obstacle) * RES
    safety = (dist <= ROBOT_RADIUS + 1e-9) & ~obstacle
    flags = (FLAG_KNOWN | obstacle * FLAG_OBSTACLE | safety * FLAG_SAFETY_ZONE).astype(np.uint8)
    assert not (classes.obstacle_lut[labels] != obstacle).any()
    return labels, heights, flags


def grid_from_dense(labels, heights, flags) -> NavGrid:
    n = labels.shape[0]
    grid = NavGrid((0.0, 0.0), labels.shape, RES, tile_size=32)
    cells = np.argwhere(np.ones((n, n), bool))
    grid.apply_patch(cells, labels.ravel(), heights.ravel(), flags.ravel())
    return grid


def far_free_pairs(flags, graph_csr, n_queries: int):
    """Start/goal pairs near opposite corners and sides, both free and connected."""
    n = flags.shape[0]
    free = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    m = n // 50 + 1
    anchors = [
        ((m, m), (n - 1 - m, n - 1 - m)),
        ((n - 1 - m, m), (m, n - 1 - m)),
        ((m, n // 2), (n - 1 - m, n // 2)),
        ((n // 2, m), (n // 2, n - 1 - m)),
    ]
    # The largest connected component of the graph, so that every query has an answer.
    _, comp = csgraph.connected_components(graph_csr, directed=True, connection="strong")
    big = np.bincount(comp).argmax()
    ok = free.ravel() & (comp == big)
    idx = np.flatnonzero(ok)
    px, py = idx // n, idx % n
    pairs = []
    for a, b in anchors[:n_queries]:
        ends = []
        for x, y in (a, b):
            j = np.argmin((px - x) ** 2 + (py - y) ** 2)
            ends.append((int(px[j]), int(py[j])))
        pairs.append(tuple(ends))
    return pairs


def run_size(n: int, runs: int, n_queries: int, classes, with_euclidean: bool) -> dict:
    labels, heights, flags = make_graph(n, seed=n, classes=classes)
    grid = grid_from_dense(labels, heights, flags)
    params = PlannerConfig(h_f=0.1, t_f=0.8, max_step_m=0.3, heuristic="octile")
    planner = Planner(grid, classes, params)
    lut = classes.cost_lut
    enter = np.where((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0, np.inf, 0.8 * lut[labels])
    t = time.perf_counter()
    csr = build_graph(enter, heights, RES, params.h_f, params.max_step_m)
    build_ms = (time.perf_counter() - t) * 1e3
    pairs = far_free_pairs(flags, csr, n_queries)
    out = {"n": n, "edges": csr.nnz, "build_ms": build_ms, "queries": []}
    t = time.perf_counter()
    planner._dense(planner._window([pairs[0][0], pairs[0][1]], False))
    out["window_ms"] = (time.perf_counter() - t) * 1e3
    for s, g in pairs:
        sxy = grid.cell_centre(*s)
        gxy = grid.cell_centre(*g)
        row = {"start": s, "goal": g}
        for heur in ("octile", "euclidean") if with_euclidean else ("octile",):
            times, res = [], None
            if heur == "octile":
                # The first query after a graph change also builds the window and enter costs.
                row["cold_ms"] = statistics.median(
                    Planner(grid, classes, params).plan(sxy, gxy, heuristic=heur).time_ms
                    for _ in range(runs)
                )
            for _ in range(runs):
                res = planner.plan(sxy, gxy, heuristic=heur)
                times.append(res.time_ms)
            if not res.ok:
                raise RuntimeError(f"bench query failed: {res.error} {res.message}")
            row[heur] = {
                "ms": statistics.median(times),
                "expanded": res.nodes_expanded,
                "cost": res.cost_total,
                "length_m": res.cost_distance,
            }
        dj_times = []
        for _ in range(max(1, runs // 2)):
            t = time.perf_counter()
            dist = csgraph.dijkstra(csr, directed=True, indices=s[0] * n + s[1])
            dj_times.append((time.perf_counter() - t) * 1e3)
        row["dijkstra"] = {"ms": statistics.median(dj_times), "cost": float(dist[g[0] * n + g[1]])}
        for heur in ("octile", "euclidean"):
            if heur in row:
                rel = abs(row[heur]["cost"] - row["dijkstra"]["cost"]) / row["dijkstra"]["cost"]
                row[heur]["rel_err"] = rel
        out["queries"].append(row)
    out["grid_bytes"] = grid.nbytes
    return out


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, int_in, positive_int

    p = ArgumentParser(
        prog="smana bench planner",
        description=__doc__.split("\n")[0],
        epilog="Duration on a 2-core machine: about 35 s by default; --quick about 1 s.",
    )
    p.add_argument("--quick", action="store_true", help="test-sized run (small graphs, few runs)")
    # below 4 x 4 nodes there are no two free nodes far enough apart to query
    p.add_argument("--sizes", type=int_in(4), nargs="+", help="graph sizes N (N x N nodes)")
    p.add_argument("--runs", type=positive_int, help="runs per query (median reported)")
    p.add_argument("--queries", type=int_in(1, 4), default=2, help="queries per graph (1..4)")
    p.add_argument("--no-euclidean", action="store_true", help="skip the paper's heuristic")
    args = p.parse_args(argv)
    sizes = args.sizes or ([60, 120] if args.quick else [250, 500, 1000])
    runs = args.runs or (3 if args.quick else 7)
    classes = ClassTable.load("garden3drms")
    # Compile the kernels before timing anything.
    warm = Planner(grid_from_dense(*make_graph(40, 1, classes)), classes)
    warm.plan((1.0, 1.0), (6.0, 6.0))
    warm.plan((1.0, 1.0), (6.0, 6.0), heuristic="euclidean")

    print(f"planner benchmark: {runs} runs per query, median; h_f 0.1, t_f 0.8, max step 0.3 m,")
    print(f"resolution {RES} m, robot radius {ROBOT_RADIUS} m; Dijkstra = scipy.sparse.csgraph;")
    print("first = the first query after a graph change (window and enter costs built, octile)")
    hdr = (
        f"{'graph':>11} {'query':>16} {'first ms':>8} {'A* octile ms':>12} {'expanded':>9} "
        f"{'A* eucl ms':>10} {'expanded':>9} {'Dijkstra ms':>11} {'cost':>10} {'rel err':>8}"
    )
    print(hdr)
    failed = False
    for n in sizes:
        r = run_size(n, runs, args.queries, classes, not args.no_euclidean)
        for q in r["queries"]:
            o, e, d = q["octile"], q.get("euclidean"), q["dijkstra"]
            err = max(o["rel_err"], e["rel_err"] if e else 0.0)
            failed |= err > 1e-6
            label = f"{q['start'][0]},{q['start'][1]}->{q['goal'][0]},{q['goal'][1]}"
            e_ms = f"{e['ms']:10.1f} {e['expanded']:9d}" if e else f"{'-':>10} {'-':>9}"
            print(
                f"{n:>5}x{n:<5} {label:>16} {q['cold_ms']:8.1f} {o['ms']:12.1f} "
                f"{o['expanded']:9d} {e_ms} "
                f"{d['ms']:11.1f} {d['cost']:10.3f} {err:8.1e}"
            )
        print(
            f"{'':>11} window {r['window_ms']:.1f} ms (once per graph version), "
            f"grid {r['grid_bytes'] / 2**20:.1f} MiB, {r['edges']} edges, "
            f"scipy graph build {r['build_ms']:.0f} ms"
        )
    if failed:
        print("FAIL: an A* cost differs from Dijkstra by more than 1e-6 relative")
        return 1
    print("all A* costs equal the Dijkstra optimum to 1e-6 relative")
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench planner", cli))
