"""`smana bench explorer`: what one exploration plan costs, next to slow references.

Grid: a 12 x 12 m garden-like box at 0.2 m (60 x 60 nodes, padded by the view range), hedges and
trees, the western half known. Times (median of `--repeats` runs):
- `view_gains` (numba kernel) for every frontier candidate, 16 headings, occlusion on, against
  a vectorised numpy version of the same rule and the pure-Python per-cell reference the tests
  use (`services/explorer/reference.py`, timed on a few candidates and scaled);
- one whole `Explorer.plan` with a free path-cost function (what the explorer adds on top of the
  planner's own query time).
"""

from __future__ import annotations

import json
import statistics
import time

import numpy as np

from smana.common.cli import doc_summary
from smana.common.config.explorer import ExplorerConfig, ViewConfig
from smana.services.explorer import frontier as fr
from smana.services.explorer.exploration import Explorer, GridBox
from smana.services.explorer.reference import view_gains_reference

TRAV = np.zeros(9, bool)
TRAV[[1, 2]] = True


def garden_grid(seed: int = 0, size_m: float = 12.0, res: float = 0.2, pad_m: float = 4.0):
    rng = np.random.default_rng(seed)
    n = int(round(size_m / res))
    p = int(round(pad_m / res))
    labels = np.zeros((n + 2 * p, n + 2 * p), np.uint16)
    inner = np.where(rng.random((n // 5, n // 5)) < 0.5, 1, 2).repeat(5, 0).repeat(5, 1)
    labels[p : p + n, p : p + n] = inner
    lab = labels[p : p + n, p : p + n]
    lab[[0, -1], :] = 4
    lab[:, [0, -1]] = 4
    for k in range(4):
        row = rng.integers(8, n - 8)
        lo = rng.integers(0, n // 2)
        lab[row, lo : lo + n // 2] = 4 + k % 2
    for _ in range(12):
        i, j = rng.integers(3, n - 3, 2)
        lab[i - 1 : i + 2, j - 1 : j + 2] = 8
    flags = np.zeros(labels.shape, np.uint8)
    known = np.zeros(labels.shape, bool)
    known[p : p + n // 2, p : p + n] = True
    flags[known] = fr.KNOWN
    flags[known & (labels >= 4)] |= fr.OBSTACLE
    labels[~known] = 0
    return GridBox(np.array([-size_m / 2 - pad_m] * 2), res, labels, flags)


def gains_numpy(unknown, opaque, cand, fov: fr.FovModel, spc: int = 2) -> np.ndarray:
    """The same rule as the kernel, vectorised over offsets with numpy (one candidate at a time)."""
    nx, ny = unknown.shape
    off = fov.offsets
    length = np.hypot(off[:, 0], off[:, 1])
    n = np.ceil(length * spc).astype(int)
    s_max = int(n.max())
    out = np.zeros((len(cand), len(fov.yaws)))
    s = np.arange(1, s_max)[None, :]
    t = s / n[:, None]
    valid_s = s < n[:, None]
    for c, (cx, cy) in enumerate(cand):
        tx, ty = cx + off[:, 0], cy + off[:, 1]
        inside = (tx >= 0) & (ty >= 0) & (tx < nx) & (ty < ny)
        target = np.zeros(len(off), bool)
        target[inside] = unknown[tx[inside], ty[inside]]
        sx = np.floor(cx + t * off[:, 0:1] + 0.5).astype(int)
        sy = np.floor(cy + t * off[:, 1:2] + 0.5).astype(int)
        ok = valid_s & (sx >= 0) & (sy >= 0) & (sx < nx) & (sy < ny)
        hit = np.zeros(sx.shape, bool)
        hit[ok] = opaque[sx[ok], sy[ok]]
        hit &= ~((sx == tx[:, None]) & (sy == ty[:, None]))
        vis = target & ~hit.any(axis=1)
        out[c] = fov.in_sector.astype(float) @ vis * fov.resolution_m**2
    return out


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run(repeats: int = 5, view_range_m: float = 4.0) -> dict:
    g = garden_grid()
    free = fr.traversable_mask(g.labels, g.flags, TRAV)
    unknown = fr.unknown_mask(g.flags)
    opaque = (g.flags & fr.OBSTACLE) != 0
    start = tuple(int(v) for v in np.argwhere(free)[len(np.argwhere(free)) // 2])
    reach = fr.reachable_mask(free, start)
    cells = fr.sample_candidates(fr.frontier_cells(reach, unknown), 3)
    view = ViewConfig(fov_deg=57.0, max_range_m=view_range_m, min_range_m=0.3, n_yaw=16)
    fov = fr.FovModel.build(g.resolution_m, view)
    fr.view_gains(unknown, opaque, cells[:1], fov)  # JIT outside the timing
    ours = fr.view_gains(unknown, opaque, cells, fov)[0]
    ref_np = gains_numpy(unknown, opaque, cells, fov)
    few = cells[:3]
    ref_py = view_gains_reference(unknown, opaque, few, g.resolution_m, view)
    agree = bool(np.allclose(ours, ref_np) and np.allclose(ours[:3], ref_py))
    t_numba = _median_ms(lambda: fr.view_gains(unknown, opaque, cells, fov), repeats)
    t_numpy = _median_ms(lambda: gains_numpy(unknown, opaque, cells, fov), max(1, repeats // 2))
    t_py = _median_ms(lambda: view_gains_reference(unknown, opaque, few, g.resolution_m, view), 1)
    t_py *= len(cells) / len(few)

    ex = Explorer(ExplorerConfig(view=view), TRAV, 9)
    ex.update_grid(g)
    xy = g.centres(np.array(start))
    ex.update_pose(float(xy[0]), float(xy[1]), 0.0, 0.0)

    def cost(a, b):
        return float(np.hypot(*(np.asarray(b) - a))) * 5.0, np.array([a, b])

    def plan():
        ex.goal = None
        ex.plan(cost)

    plan()
    t_plan = _median_ms(plan, repeats)
    return {
        "grid_nodes": int(g.labels.size),
        "frontier_nodes": int(ex.frontier_size),
        "candidates": int(len(cells)),
        "offsets_per_view": int(len(fov.offsets)),
        "agree_with_references": agree,
        "view_gains_numba_ms": t_numba,
        "view_gains_numpy_ms": t_numpy,
        "view_gains_python_ms_scaled": t_py,
        "plan_ms": t_plan,
        "queries_per_plan": int(ex.last_outcome.chosen.n_queries) if ex.last_outcome.chosen else 0,
    }


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, positive_float, positive_int

    p = ArgumentParser(
        prog="smana bench explorer",
        description=doc_summary(__doc__),
        epilog="Duration measured once on a 2-core machine: about 5 s.",
    )
    p.add_argument("--repeats", type=positive_int, default=5)
    p.add_argument("--view-range", type=positive_float, default=4.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    r = run(args.repeats, args.view_range)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"grid {r['grid_nodes']} nodes, {r['frontier_nodes']} frontier nodes, "
        f"{r['candidates']} candidates x 16 headings x {r['offsets_per_view']} cells; "
        f"results agree with both references: {r['agree_with_references']}"
    )
    print(f"{'view gains, occlusion on':<34} {'median ms':>10}")
    print(f"{'  smana (numba kernel)':<34} {r['view_gains_numba_ms']:>10.2f}")
    print(f"{'  numpy vectorised reference':<34} {r['view_gains_numpy_ms']:>10.2f}")
    print(f"{'  pure Python reference (scaled)':<34} {r['view_gains_python_ms_scaled']:>10.0f}")
    print(
        f"{'whole Explorer.plan (free paths)':<34} {r['plan_ms']:>10.2f}"
        f"   ({r['queries_per_plan']} path queries)"
    )
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    raise SystemExit(run_command("bench explorer", cli))
