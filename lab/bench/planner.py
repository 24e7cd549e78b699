"""`smana bench planner`: weighted A* side by side with two peers, each on a graph where both
compute the same cost.

Cluttered graphs (the planner's real work): N x N nodes at 0.2 m: terrain, patches of grass,
obstacles (hedges, topiary, trees as discs) with their safety zone, and smooth hills whose steep
flanks exceed the maximum step height. Queries run between far-apart free nodes (corner to corner
and side to side) through the planner's real query path (`Planner.plan`: window, enter costs, A*,
breakdown). The peer is scipy's Dijkstra (`scipy.sparse.csgraph.dijkstra`, C) on the same directed
graph with the same edge costs (paper eq. 1).

Flat graphs (the comparison with pyastar2d, C++): the same grass patches on flat, open ground.
pyastar2d's cost is the sum of the weights of the nodes entered, a diagonal step costing the same
as a side step; its weights are terrain 1.0 and grass 1.8 (per 0.2 m step: the paper's 0.2 m +
t_f 0.8 x T, T = 1 and 2). smana's kernel (`astar.search`) runs on the same graph with the same
cost: enter cost = pyastar2d's weight, no distance term (resolution 0), no height term (h_f 0),
octile heuristic (there min weight x Chebyshev steps, pyastar2d's own heuristic); both costs must
agree. smana under the paper's cost (distance + t_f T, a diagonal 0.283 m) on the same flat graph
is reported beside it, through `Planner.plan`, with pyastar2d's time as the yardstick.

Risk rows (`--risk`, column "risk": the mode and the doubt share): the cluttered graph with a
class distribution on a share of its free nodes (planner_workloads.make_risk says how).

`--map-doubt SEED ...` measures instead what share of a real map's free nodes is doubtful
(planner_workloads.map_doubt).

Every A* cost is checked against Dijkstra to 1e-6 relative (and pyastar2d's to 1e-5: it sums in
float32); a disagreement fails the benchmark. Every row prints the peer's and smana's wall and CPU
time (time.process_time), their ratio, and the load average.

Workload variants: graph sizes (`--sizes`), obstacle shares of the cluttered graphs
(`--obstacles`), query spans (`--lengths`, a share of the graph's size). The run ends with the
spread of each comparison: the ratio's median and range over every query of every variant, CPU
and wall, and the load average meanwhile.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time

import numpy as np
from scipy.sparse import csgraph

from smana.common.classes import ClassTable
from smana.common.cli import doc_summary
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.planner.astar import search
from smana.services.planner.planner import RISK_MODES, Planner
from smana.services.planner.reference import build_graph

from .planner_workloads import (
    GRASS,
    RES,
    ROBOT_RADIUS,
    anchor_points,
    far_free_pairs,
    grid_from_dense,
    make_flat_graph,
    make_graph,
    make_risk,
    print_map_doubt,
)

HINT = "pyastar2d not installed (pip install 'smana[bench]'): no pyastar2d comparison"


def timed(fn, runs: int, setup=None):
    """Median wall and CPU (time.process_time) milliseconds of `runs` calls, and the last
    result; `setup` (not timed) runs before each call."""
    walls, cpus, out = [], [], None
    for _ in range(runs):
        if setup is not None:
            setup()
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        cpus.append((time.process_time() - c) * 1e3)
        walls.append((time.perf_counter() - w) * 1e3)
    return statistics.median(walls), statistics.median(cpus), out


def _row(work, peer, p, s, expanded, cost, err, risk="-") -> dict:
    """One printed row: the peer's and smana's (wall, cpu) ms side by side."""
    return {
        "work": work,
        "risk": risk,
        "peer": peer,
        "peer_ms": p,
        "smana_ms": s,
        "expanded": expanded,
        "cost": cost,
        "rel_err": err,
        "load": os.getloadavg()[0],
    }


def _patch_one_tile(grid: NavGrid):
    """A graph patch as the planner receives them: one tile's nodes, rewritten here with their
    own values, so the graph changes version (the window's patched nodes and their enter costs
    are refreshed, `NavGrid.changes_since`) and the answer stays the same."""
    t = grid.tile_size
    x0, y0 = (s // 2 // t * t for s in grid.shape)
    cells = np.argwhere(np.ones((t, t), bool)) + (x0, y0)
    cells = cells[(cells[:, 0] < grid.shape[0]) & (cells[:, 1] < grid.shape[1])]

    def patch():
        grid.apply_patch(cells, *grid.read_cells(cells), risk=grid.read_risk(cells))

    return patch


# What each smana row times: building a Planner and its first query (nothing cached before),
# the first query on a Planner built just before (untimed: it builds its window ahead, as the
# service does on its tick after a graph change), the first query after a graph patch (the
# patched nodes of the window and enter costs refreshed), a repeat query on one graph version.
BUILD_FIRST, FIRST_NEW, FIRST_PATCHED, REPEAT = "build", "new", "patched", "repeat"


def _query(grid, classes, params, planner, a, b, heuristic, when=REPEAT):
    """(call, setup) for `timed`: a query on `planner`, or on a new Planner per call, built in
    the call (BUILD_FIRST) or in the untimed setup (FIRST_NEW). The Planner that answered is
    kept in `call.planner`."""
    fresh = {}

    def new_planner():
        fresh["p"] = Planner(grid, classes, params)

    def query():
        if when == BUILD_FIRST:
            new_planner()
        query.planner = fresh["p"] if when in (BUILD_FIRST, FIRST_NEW) else planner
        return query.planner.plan(a, b, heuristic=heuristic)

    return query, (new_planner if when == FIRST_NEW else None)


def _rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(b), 1e-300)


def run_size(
    n: int,
    runs: int,
    n_queries: int,
    classes,
    with_euclidean: bool,
    obstacle_share: float = 0.12,
    length: float = 1.0,
    with_risk: bool = False,
    doubt_shares: tuple[float, ...] = (0.5,),
) -> dict:
    """The cluttered graph: `Planner.plan` against scipy's Dijkstra on the same graph; with
    `with_risk` the same queries on the graph with risk layers, rows per mode and share of
    doubtful free nodes (`doubt_shares`)."""
    labels, heights, flags = make_graph(n, seed=n, classes=classes, obstacle_share=obstacle_share)
    grid = grid_from_dense(labels, heights, flags)
    # the paper's cost, as the peer computes it: smana's clearance cost (beside the safety
    # zone) off, so that both search the same graph
    params = PlannerConfig(h_f=0.1, t_f=0.8, max_step_m=0.3, heuristic="octile", clearance_cost=0)
    planner = Planner(grid, classes, params)
    patch = _patch_one_tile(grid)
    lut = classes.cost_lut
    enter = np.where((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0, np.inf, 0.8 * lut[labels])
    t = time.perf_counter()
    csr = build_graph(enter, heights, RES, params.h_f, params.max_step_m)
    build_ms = (time.perf_counter() - t) * 1e3
    pairs = far_free_pairs(flags, csr, n_queries, length)
    variant = f"{n} obst {obstacle_share:g} len {length:g}"
    out = {"n": n, "variant": variant, "edges": csr.nnz, "build_ms": build_ms, "queries": []}
    t = time.perf_counter()
    planner._dense(planner._window([pairs[0][0], pairs[0][1]], False))
    out["window_ms"] = (time.perf_counter() - t) * 1e3
    for s, g in pairs:
        sxy = grid.cell_centre(*s)
        gxy = grid.cell_centre(*g)
        dw, dc, dist = timed(
            lambda s=s: csgraph.dijkstra(csr, directed=True, indices=s[0] * n + s[1]),
            max(1, runs // 2),
        )
        want = float(dist[g[0] * n + g[1]])
        rows = []
        works = [
            ("new Planner + first", "octile", BUILD_FIRST),
            ("first, new Planner", "octile", FIRST_NEW),
            ("first after a patch", "octile", FIRST_PATCHED),
            ("repeat query", "octile", REPEAT),
        ]
        if with_euclidean:
            works.append(("repeat, Euclidean", "euclidean", REPEAT))
        for work, heur, when in works:
            fn, setup = _query(grid, classes, params, planner, sxy, gxy, heur, when)
            sw, sc, res = timed(fn, runs, patch if when == FIRST_PATCHED else setup)
            if not res.ok:
                raise RuntimeError(f"bench query failed: {res.error} {res.message}")
            err = _rel(res.cost_total, want)
            rows.append(
                _row(
                    work,
                    "scipy Dijkstra",
                    (dw, dc),
                    (sw, sc),
                    res.nodes_expanded,
                    res.cost_total,
                    err,
                )
            )
        out["queries"].append({"start": s, "goal": g, "rows": rows})
    out["grid_bytes"] = grid.nbytes
    if with_risk:
        _risk_rows(out, labels, heights, flags, classes, params, pairs, runs, doubt_shares)
    return out


CERTAIN = "certain"  # the risk column of the rows on risk layers whose nodes are all certain


def _risk_graphs(labels, heights, flags, doubt_shares):
    """(name, graph, mode) of the risk rows: "certain" (the layers there, every node certain:
    the costs and the search of the graph without them), then per doubt share each mode, named
    "mode share"; each share's graph is built when its rows come."""
    n = labels.shape[0]
    alt, p_label, p_alt = make_risk(labels, flags, n)
    yield (
        CERTAIN,
        grid_from_dense(labels, heights, flags, (alt, np.full_like(p_label, 255), p_alt)),
        "expected",
    )
    for share in doubt_shares:
        grid = grid_from_dense(labels, heights, flags, make_risk(labels, flags, n, share))
        for mode in RISK_MODES:
            yield f"{mode} {share:g}", grid, mode


def _risk_rows(out, labels, heights, flags, classes, params, pairs, runs, doubt_shares) -> None:
    """Per mode and doubt share, the queries on the graph with risk layers on a new Planner,
    built in the timed call (the window's risk enter pass counted) and built just before
    (untimed: it prepares that pass ahead, as the service does on its tick), against Dijkstra on
    the enter costs that mode gave (the window is the whole graph)."""
    n = labels.shape[0]
    plain = grid_from_dense(labels, heights, flags)
    out["pass_ms"] = {"-": _enter_pass(plain, classes, params, runs)}
    works = [("new Planner + first", BUILD_FIRST), ("first, new Planner", FIRST_NEW)]
    for name, grid, mode in _risk_graphs(labels, heights, flags, doubt_shares):
        p = dataclasses.replace(params, risk=mode)
        out["pass_ms"][name] = _enter_pass(grid, classes, p, runs)
        csr = None
        for q, (s, g) in zip(out["queries"], pairs, strict=True):
            sxy, gxy = grid.cell_centre(*s), grid.cell_centre(*g)
            for work, when in works:
                fn, setup = _query(grid, classes, p, None, sxy, gxy, "octile", when)
                sw, sc, res = timed(fn, runs, setup)
                if csr is None:
                    enter = fn.planner._enter_cache[0]
                    assert enter.shape == (n, n), "the risk rows' window is the whole graph"
                    csr = build_graph(enter, heights, RES, p.h_f, p.max_step_m)
                dw, dc, dist = timed(
                    lambda s=s, csr=csr: csgraph.dijkstra(
                        csr, directed=True, indices=s[0] * n + s[1]
                    ),
                    1,
                )
                want = float(dist[g[0] * n + g[1]])
                cost = res.cost_total if res.ok else np.inf
                err = 0.0 if cost == want == np.inf else _rel(cost, want)
                row = _row(work, "scipy Dijkstra", (dw, dc), (sw, sc), 0, cost, err, name)
                row.update(expanded=res.nodes_expanded)
                q["rows"].append(row)


def run_flat(n: int, runs: int, n_queries: int, classes, pyastar, length: float = 1.0) -> dict:
    """The flat graph: smana's kernel against pyastar2d under pyastar2d's cost, and smana's
    `Planner.plan` under the paper's cost (pyastar2d's time beside it)."""
    labels, heights, flags = make_flat_graph(n, seed=n)
    grass = labels == GRASS
    weights = np.where(grass, 1.8, 1.0).astype(np.float32)
    enter = weights.astype(np.float64)  # the very same numbers as pyastar2d's
    zeros = np.zeros((n, n))
    grid = grid_from_dense(labels, heights, flags)
    # the paper's cost, as the peer computes it: smana's clearance cost (beside the safety
    # zone) off, so that both search the same graph
    params = PlannerConfig(h_f=0.1, t_f=0.8, max_step_m=0.3, heuristic="octile", clearance_cost=0)
    planner = Planner(grid, classes, params)
    patch = _patch_one_tile(grid)
    # Exactness checks only (not timed here): Dijkstra under both costs.
    csr_eq = build_graph(enter, zeros, 0.0, 0.0)
    csr_paper = build_graph(0.8 * classes.cost_lut[labels], zeros, RES, 0.1, 0.3)
    out = {"n": n, "variant": f"{n} flat len {length:g}", "queries": [], "peer_err": 0.0}
    for s, g in anchor_points(n, length)[:n_queries]:
        sxy, gxy = grid.cell_centre(*s), grid.cell_centre(*g)
        src, dst = s[0] * n + s[1], g[0] * n + g[1]
        want_eq = float(csgraph.dijkstra(csr_eq, directed=True, indices=src)[dst])
        want_paper = float(csgraph.dijkstra(csr_paper, directed=True, indices=src)[dst])
        peer, rows = None, []
        if pyastar is not None:
            pw, pc, path = timed(lambda s=s, g=g: pyastar.astar_path(weights, s, g, True), runs)
            peer = (pw, pc)
            # pyastar2d returns the path only: its cost is the sum of the weights entered.
            p_cost = float(enter[path[1:, 0], path[1:, 1]].sum())
            # pyastar2d sums float32 weights: its path may differ from the optimum by rounding.
            out["peer_err"] = max(out["peer_err"], _rel(p_cost, want_eq))
        # smana's kernel with pyastar2d's cost; like pyastar2d's wrapper it finds the minimum
        # weight on every call (pyastar2d checks it, smana's octile heuristic uses it).
        sw, sc, res = timed(
            lambda s=s, g=g: search(
                enter, zeros, s, g, 0.0, 0.0, np.inf, "octile", float(enter.min())
            ),
            runs,
        )
        rows.append(
            _row(
                "A*, pyastar2d's cost",
                "pyastar2d",
                peer,
                (sw, sc),
                res.nodes_expanded,
                res.cost,
                _rel(res.cost, want_eq),
            )
        )
        for work, when in (
            ("first, new Planner, paper", FIRST_NEW),
            ("after a patch, paper", FIRST_PATCHED),
            ("repeat query, paper", REPEAT),
        ):
            fn, setup = _query(grid, classes, params, planner, sxy, gxy, "octile", when)
            sw, sc, res = timed(fn, runs, patch if when == FIRST_PATCHED else setup)
            if not res.ok:
                raise RuntimeError(f"bench query failed: {res.error} {res.message}")
            rows.append(
                _row(
                    work,
                    "pyastar2d",
                    peer,
                    (sw, sc),
                    res.nodes_expanded,
                    res.cost_total,
                    _rel(res.cost_total, want_paper),
                )
            )
        out["queries"].append({"start": s, "goal": g, "rows": rows})
    return out


HEADER = (
    f"{'graph':>24} {'query':>16} {'work':<26} {'risk':<14} {'peer':<14} {'peer ms':>8} "
    f"{'peer cpu':>8} "
    f"{'smana ms':>8} {'smana cpu':>9} {'ratio':>5} {'cpu r.':>6} {'expanded':>8} {'cost':>10} "
    f"{'rel err':>7} {'load':>5}"
)


def _print_row(variant: str, q: dict, r: dict) -> None:
    label = f"{q['start'][0]},{q['start'][1]}->{q['goal'][0]},{q['goal'][1]}"
    if r["peer_ms"] is None:
        peer = f"{'-':>8} {'-':>8}"
        ratio = f"{'-':>5} {'-':>6}"
    else:
        (pw, pc), (sw, sc) = r["peer_ms"], r["smana_ms"]
        peer = f"{pw:8.1f} {pc:8.1f}"
        ratio = f"{sw / pw:5.2f} {sc / max(pc, 1e-9):6.2f}"
    sw, sc = r["smana_ms"]
    print(
        f"{variant:>24} {label:>16} {r['work']:<26} {r['risk']:<14} {r['peer']:<14} {peer} "
        f"{sw:8.1f} {sc:9.1f} "
        f"{ratio} {r['expanded']:8d} {r['cost']:10.3f} {r['rel_err']:7.0e} {r['load']:5.2f}"
    )


def spread(results: list[dict]) -> list[dict]:
    """Per (peer, work, risk): the smana / peer ratio's median and range (wall and CPU) over
    every query of every workload variant in `results`, and the load average's range meanwhile."""
    groups: dict[tuple[str, str, str], list[tuple[str, dict]]] = {}
    for r in results:
        for q in r["queries"]:
            for row in q["rows"]:
                if row["peer_ms"] is not None:
                    key = (row["peer"], row["work"], row.get("risk", "-"))
                    groups.setdefault(key, []).append((r["variant"], row))
    out = []
    for (peer, work, risk), rows in groups.items():
        wall = [row["smana_ms"][0] / row["peer_ms"][0] for _, row in rows]
        cpu = [row["smana_ms"][1] / max(row["peer_ms"][1], 1e-9) for _, row in rows]
        loads = [row["load"] for _, row in rows]
        out.append(
            {
                "peer": peer,
                "work": work,
                "risk": risk,
                "variants": len({v for v, _ in rows}),
                "queries": len(rows),
                "cpu": (statistics.median(cpu), min(cpu), max(cpu)),
                "wall": (statistics.median(wall), min(wall), max(wall)),
                "load": (min(loads), max(loads)),
            }
        )
    return out


def _print_spread(results: list[dict]) -> None:
    print(
        "spread over the workload variants: smana / peer ratio, median [min, max] over every "
        "query, CPU and wall"
    )
    for g in spread(results):
        c, w, ld = g["cpu"], g["wall"], g["load"]
        print(
            f"  {g['peer']:<14} {g['work']:<26} {g['risk']:<14} {g['variants']} variants, "
            f"{g['queries']:2d} queries: CPU {c[0]:.2f} [{c[1]:.2f}, {c[2]:.2f}], wall {w[0]:.2f} "
            f"[{w[1]:.2f}, {w[2]:.2f}], load {ld[0]:.1f}-{ld[1]:.1f}"
        )


def _enter_pass(grid, classes, params, runs) -> float:
    """Median CPU ms of building a new Planner: it prepares the window gather and enter-cost
    pass of the known area (no search): where risk adds work; the A* after it is the same
    kernel."""
    return timed(lambda: Planner(grid, classes, params), runs)[1]


def _risk_ratios(r: dict, work: str) -> str:
    """Per mode (and doubt share), the CPU time of its `work` row over the same query's without
    risk: the median over the queries."""
    out = []
    for mode in (name for name in r["pass_ms"] if name != "-"):
        ratios = []
        for q in r["queries"]:
            cpu = {row["risk"]: row["smana_ms"][1] for row in q["rows"] if row["work"] == work}
            ratios.append(cpu[mode] / max(cpu["-"], 1e-9))
        out.append(f"{mode} x{statistics.median(ratios):.2f}")
    return ", ".join(out)


def _print_risk(r: dict) -> None:
    passes = ", ".join(f"{k} {v:.1f} ms" for k, v in r["pass_ms"].items())
    for work in ("new Planner + first", "first, new Planner"):
        print(f"{'':>24} risk / no risk, CPU of '{work}': " + _risk_ratios(r, work))
    print(
        f"{'':>24} risk: window and enter costs alone (a new Planner): {passes} (- = without risk)"
    )


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, int_in, positive_int

    def share(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = math.nan
        if not 0.0 < v <= 1.0:  # NaN fails too
            raise argparse.ArgumentTypeError(f"expected a number > 0 and <= 1, got {text!r}")
        return v

    p = ArgumentParser(
        prog="smana bench planner",
        description=doc_summary(__doc__),
        epilog="Duration measured once on a 2-core machine: about 60 s by default; --quick a few "
        "seconds.",
    )
    p.add_argument("--quick", action="store_true", help="test-sized run (small graphs, few runs)")
    # below 4 x 4 nodes there are no two free nodes far enough apart to query
    p.add_argument("--sizes", type=int_in(4), nargs="+", help="graph sizes N (N x N nodes)")
    p.add_argument("--runs", type=positive_int, help="runs per query (median reported)")
    p.add_argument("--queries", type=int_in(1, 4), default=2, help="queries per graph (1..4)")
    p.add_argument(
        "--obstacles",
        type=share,
        nargs="+",
        default=[0.12],
        help="cluttered graphs: obstacle shares of the area, one graph each (default 0.12)",
    )
    p.add_argument(
        "--lengths",
        type=share,
        nargs="+",
        default=[1.0],
        help="query spans as a share of the graph's size (default 1: corner to corner)",
    )
    p.add_argument("--no-euclidean", action="store_true", help="skip the paper's heuristic")
    p.add_argument("--no-flat", action="store_true", help="skip the flat graphs (pyastar2d)")
    p.add_argument(
        "--risk",
        action="store_true",
        help="add the risk rows (planner.risk) to the cluttered graphs",
    )
    p.add_argument(
        "--doubt",
        type=share,
        nargs="+",
        default=[0.5],
        help="risk rows: shares of the free nodes whose label is doubtful, drawn at random, one "
        "set of rows each (default 0.5)",
    )
    p.add_argument(
        "--map-doubt",
        type=int,
        nargs="+",
        metavar="SEED",
        help="instead: the share of a real map's known free nodes whose label is doubtful, per "
        "wet-garden seed (TSDF under label noise p = 0.7; see the module's help)",
    )
    args = p.parse_args(argv)
    if args.map_doubt:
        print_map_doubt(args.map_doubt, args.quick)
        return 0
    sizes = args.sizes or ([60, 120] if args.quick else [250, 500, 1000])
    runs = args.runs or (3 if args.quick else 7)
    classes = ClassTable.load("garden3drms")
    try:
        import pyastar2d
    except ImportError:
        pyastar2d = None
    # Compile the kernels before timing anything.
    warm = Planner(grid_from_dense(*make_graph(40, 1, classes)), classes)
    warm.plan((1.0, 1.0), (6.0, 6.0))
    warm.plan((1.0, 1.0), (6.0, 6.0), heuristic="euclidean")
    small = make_graph(40, 1, classes)
    risky = Planner(grid_from_dense(*small, make_risk(small[0], small[2], 1)), classes)
    for mode in RISK_MODES:
        risky.plan((1.0, 1.0), (6.0, 6.0), risk=mode)
    search(np.ones((4, 4)), np.zeros((4, 4)), (0, 0), (3, 3), 0.0, 0.0, np.inf, "octile", 1.0)

    print(f"planner benchmark: {runs} runs per query, median wall and CPU (process_time) ms;")
    cores = os.cpu_count()
    print(f"ratio = smana / peer (< 1: smana faster); load = 1-min load average, {cores} cores")
    print(f"paper's cost: h_f 0.1, t_f 0.8, max step 0.3 m, resolution {RES} m, robot radius")
    print(f"{ROBOT_RADIUS} m, octile heuristic unless said; first = the first query after a graph")
    print("patch (one tile: its nodes refreshed in the cached window), or on a new Planner")
    print("(nothing cached);")
    print("rel err = |cost - Dijkstra| / Dijkstra; risk = planner.risk on the graph with risk")
    print("layers and the share of its free nodes doubtful ('certain': every node certain), '-' =")
    print("the graph without them")
    print("flat graphs: pyastar2d's cost = sum of the weights entered (terrain 1.0, grass 1.8; a")
    print(
        "diagonal as a side step); smana's kernel on the same weights, no distance or height term"
    )
    print(HEADER)
    failed = False
    results = []
    if not args.no_flat and pyastar2d is None:
        print(HINT)  # the flat rows exist to compare with pyastar2d: skipped without it
    elif not args.no_flat:
        for n in sizes:
            for length in args.lengths:
                r = run_flat(n, runs, args.queries, classes, pyastar2d, length)
                results.append(r)
                for q in r["queries"]:
                    for row in q["rows"]:
                        failed |= not row["rel_err"] <= 1e-6
                        _print_row(r["variant"], q, row)
                failed |= not r["peer_err"] <= 1e-5
                print(
                    f"{'':>24} flat: pyastar2d's path costs {r['peer_err']:.0e} relative off "
                    "the optimum (it sums in float32)"
                )
    for n in sizes:
        for obstacle_share in args.obstacles:
            for length in args.lengths:
                r = run_size(
                    n,
                    runs,
                    args.queries,
                    classes,
                    not args.no_euclidean,
                    obstacle_share,
                    length,
                    args.risk,
                    tuple(args.doubt),
                )
                results.append(r)
                for q in r["queries"]:
                    for row in q["rows"]:
                        failed |= not row["rel_err"] <= 1e-6
                        _print_row(r["variant"], q, row)
                print(
                    f"{'':>24} cluttered: window {r['window_ms']:.1f} ms on a new Planner, "
                    f"grid {r['grid_bytes'] / 2**20:.1f} MiB, {r['edges']} edges, "
                    f"scipy graph build {r['build_ms']:.0f} ms (not counted)"
                )
                if args.risk:
                    _print_risk(r)
    _print_spread(results)
    if failed:
        print("FAIL: an A* cost differs from Dijkstra (or pyastar2d's) beyond the tolerance")
        return 1
    print("all A* costs equal the Dijkstra optimum to 1e-6 relative (pyastar2d's to 1e-5)")
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench planner", cli))
