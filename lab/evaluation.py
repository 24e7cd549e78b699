"""`smana eval map`: a run's map scored against ground truth, and the lab's own measures.

The measures themselves (reconstruction error, classification ratio, precision, completeness,
F-score; coverage, travelled labels, clearance) are the product's, in
`smana.deploy.report.ground_truth` (a run's report computes them as it ends); they are re-exported
here for the experiments. This module adds what only the lab needs: the reachable area from a
world's spawn point, a grid graph for shortest paths, and the `smana eval` command.

    smana eval map RUN_DIR [--map FILE] [--gt FILE]

finds the run's final map and the ground truth (the `gt.ply` in the run directory, or the
simulated world rebuilt from the run's config and exported there), prints the table and writes
`eval_map.json` into the run directory.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from smana.deploy.report.ground_truth import (  # noqa: F401 - measured as a run report does
    MAP_CANDIDATES,
    clearance_along,
    collision_raster,
    count_events,
    evaluate_map,
    exploration_coverage,
    find_map,
    footprint_contacts,
    gt_cloud_for_run,
    label_shares,
    load_labelled_cloud,
    load_run_config,
    nearest_gt,
    reachable_traversable,
    robot_footprint,
    robot_height_m,
    sample_grid,
    surface_completeness,
    terrain_share,
    travelled_nodes,
    world_from_config,
)


def reachable_from_spawn(world, clearance_m: float):
    """(traversability `Raster` with `clearance_m`, mask of its cells 8-connected to the world's
    spawn point, that point's cell): the free space a robot of that radius could reach from
    where it starts."""
    trav = world.traversability(clearance_m)
    x0, y0, _ = world.spawn_pose(clearance_m)
    start = tuple(int(v) for v in trav.index_of(x0, y0))
    return trav, reachable_traversable(trav.data, start), start


def grid_graph(mask: np.ndarray, offsets, step_cost):
    """A sparse graph over the True cells of `mask`: one edge from each cell a to a + offset for
    every offset in `offsets` whose end is in `mask`, weighted `step_cost(b_cells, step_cells)`
    (b_cells (E, 2) the ends, step_cells the offset's length in cells). Returns (csr matrix,
    cells (N, 2), the node index of each cell). For scipy.sparse.csgraph's shortest paths."""
    from scipy.sparse import coo_matrix

    cells = np.argwhere(mask)
    idx = -np.ones(mask.shape, np.int64)
    idx[mask] = np.arange(len(cells))
    rows, cols, wts = [], [], []
    for di, dj in offsets:
        b = cells + (di, dj)
        ok = np.all((b >= 0) & (b < mask.shape), axis=1)
        a, b = cells[ok], b[ok]
        ok = mask[b[:, 0], b[:, 1]]
        a, b = a[ok], b[ok]
        rows.append(idx[a[:, 0], a[:, 1]])
        cols.append(idx[b[:, 0], b[:, 1]])
        wts.append(np.broadcast_to(step_cost(b, math.hypot(di, dj)), len(b)))
    n = len(cells)
    graph = coo_matrix(
        (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    return graph, cells, idx


def format_map_table(scores: dict) -> str:
    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    lines = [
        f"map points: {scores['n_points']}",
        f"reconstruction error: mean {f(scores['reconstruction_error_mean_m'], '.4f')} m, "
        f"std {f(scores['reconstruction_error_std_m'], '.4f')} m, "
        f"median {f(scores['reconstruction_error_median_m'], '.4f')} m",
        f"classification ratio: {f(scores['classification_ratio'], '.3f')}",
        f"within {scores['threshold_m'] * 100:g} cm: precision {f(scores['precision'], '.3f')}, "
        f"completeness {f(scores['completeness'], '.3f')}, F-score {f(scores['f_score'], '.3f')}",
        "",
        f"{'class (map label)':<20} {'points':>8} {'err mean m':>11} {'err std m':>10} "
        f"{'class. ratio':>12}",
    ]
    for name, s in scores["per_class"].items():
        lines.append(
            f"{name:<20} {s['n_points']:>8} {f(s['error_mean_m'], '.4f'):>11} "
            f"{f(s['error_std_m'], '.4f'):>10} {f(s['classification_ratio'], '.3f'):>12}"
        )
    lines += ["", f"{'class (true label)':<20} {'points':>8} {'class. ratio':>12}"]
    for name, s in scores["per_true_class"].items():
        lines.append(f"{name:<20} {s['n_points']:>8} {f(s['classification_ratio'], '.3f'):>12}")
    return "\n".join(lines)


def eval_map_run(
    run_dir: Path,
    map_path: Path | None = None,
    gt_path: Path | None = None,
    spacing_m: float = 0.03,
    threshold_m: float = 0.05,
) -> dict:
    """Evaluate a run directory's map; writes `eval_map.json` there and returns the scores."""
    from smana.common.classes import ClassTable

    run_dir = Path(run_dir)
    config = load_run_config(run_dir)
    classes = ClassTable.load(config.general.class_table)
    names = {i: c.name for i, c in classes.classes.items()}
    map_path = Path(map_path) if map_path else find_map(run_dir)
    mp, ml = load_labelled_cloud(map_path)
    if gt_path:
        gp, gl = load_labelled_cloud(Path(gt_path))
    else:
        gp, gl = gt_cloud_for_run(run_dir, config, spacing_m)
    scores = evaluate_map(mp, ml, gp, gl, names, threshold_m=threshold_m)
    scores["map"] = str(map_path)
    scores["gt"] = str(gt_path or run_dir / "gt.ply")
    (run_dir / "eval_map.json").write_text(json.dumps(scores, indent=2))
    return scores


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, doc_summary, positive_float

    p = ArgumentParser(prog="smana eval", description=doc_summary(__doc__))
    sub = p.add_subparsers(dest="what", required=True)
    m = sub.add_parser(
        "map",
        help="reconstruction error, classification ratio, precision, completeness and F-score "
        "of a run's map",
    )
    m.add_argument("run_dir", type=Path)
    m.add_argument("--map", type=Path, help="map file (PLY or .npz); default: found in RUN_DIR")
    m.add_argument(
        "--gt",
        type=Path,
        help="ground-truth labelled PLY; default: RUN_DIR/gt.ply "
        "or exported from the run's simulated world",
    )
    m.add_argument(
        "--spacing", type=positive_float, default=0.03, help="GT sample spacing when exported"
    )
    m.add_argument(
        "--threshold",
        type=positive_float,
        default=0.05,
        help="distance (m) within which a map point and a true surface point count as matched "
        "(precision, completeness, F-score; default 0.05)",
    )
    m.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = p.parse_args(argv)
    if not args.run_dir.is_dir():
        print(f"smana eval: {args.run_dir} is not a directory", file=sys.stderr)
        return 2
    try:
        scores = eval_map_run(args.run_dir, args.map, args.gt, args.spacing, args.threshold)
    except (FileNotFoundError, ValueError) as exc:
        print(f"smana eval: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(scores, indent=2) if args.json else format_map_table(scores))
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("eval", cli))
