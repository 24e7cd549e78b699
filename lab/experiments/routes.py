"""`smana experiment routes`: the terrain share of the cheapest routes between random places of
the garden, without exploring. It separates what the world's layout decides from what the
explorer decides: a robot that only drove between random reachable places by the planner's
cheapest route would travel this share of terrain at each grass cost factor; the exploration
experiment's travelled share is then read against it (docs/experiments.md).

Routes are computed on the ground-truth raster (0.1 m): cells the robot may stand on (a
traversable class with `navgraph.robot_radius_m` of clearance), reachable from the spawn,
8-connected, each step costing what the planner's equation 1 charges (distance plus t_f x the
class cost of the cell entered, scaled to the graph resolution: a 0.1 m step pays half a 0.2 m
node's class cost; heights left out, the garden is gentle). Seconds per seed, in-process.

    smana experiment routes [--seeds 5] [--factors 1,2,4] [--layout wheel] [--out DIR]

Another garden layout (`--layout`, a `sim.garden.layout` value) writes data/routes_<layout>.json
instead of data/routes.json: docs/experiments.md has a generated table for each.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import dijkstra

from smana.common import progress
from smana.lab import evaluation as ev
from smana.lab import stats

GRASS, TERRAIN = 1, 2
OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, -1), (-1, 0), (-1, -1), (-1, 1))


def _graph(reach: np.ndarray, step_class_cost: np.ndarray, res: float, t_f: float, graph_res):
    """Directed 8-connected graph over the True cells of `reach`: (csr, cell index of each node).
    The planner charges t_f x T(l) per graph node entered; a raster step pays its share."""

    def cost(b, step):
        return step * res + t_f * step_class_cost[b[:, 0], b[:, 1]] * (res / graph_res)

    graph, cells, _ = ev.grid_graph(reach, OFFSETS, cost)
    return graph, cells


def route_terrain_share(
    top_class: np.ndarray,
    reach: np.ndarray,
    grass_factor: float,
    rng: np.random.Generator,
    *,
    res: float = 0.1,
    t_f: float = 0.8,
    graph_res: float = 0.2,
    n_sources: int = 20,
    targets_per_source: int = 10,
) -> float | None:
    """Share of terrain among the terrain and grass cells entered by the cheapest routes between
    random pairs of `reach` cells, terrain costing 1 and grass `grass_factor` (the class table's
    terrain cost times the factor, as the exploration experiment's --set does)."""
    cost = np.where(top_class == GRASS, float(grass_factor), 1.0)
    g, cells = _graph(reach, cost, res, t_f, graph_res)
    if len(cells) < 2:
        return None
    sources = rng.choice(len(cells), size=min(n_sources, len(cells)), replace=False)
    targets = [rng.choice(len(cells), size=targets_per_source) for _ in sources]
    return route_shares(g, cells, top_class, sources, targets)


def route_shares(g, cells: np.ndarray, top_class: np.ndarray, sources, targets) -> float | None:
    """Terrain / (terrain + grass) over the cells entered by the cheapest routes from each
    source node to each of its target nodes (`targets[k]` for `sources[k]`)."""
    _, pred = dijkstra(g, directed=True, indices=np.asarray(sources), return_predecessors=True)
    n_t = n_g = 0
    for k, src in enumerate(sources):
        for t in targets[k]:
            node = int(t)
            while node >= 0 and node != src:
                c = top_class[cells[node, 0], cells[node, 1]]
                n_t += c == TERRAIN
                n_g += c == GRASS
                node = int(pred[k, node])
    return n_t / (n_t + n_g) if n_t + n_g else None


def world_routes(seed: int, size_m: float, factors, world_sets, clearance_m: float) -> dict:
    """{factor: share} for one garden seed (the exploration experiment's world and start)."""
    from .exploration import experiment_world

    cfg, world = experiment_world(seed, size_m, world_sets)
    trav, reach, _ = ev.reachable_from_spawn(world, clearance_m)
    top = world.top_class().data
    out = {}
    for f in factors:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x2047E]))
        out[f] = route_terrain_share(
            top,
            reach,
            f,
            rng,
            res=trav.resolution_m,
            t_f=cfg.planner.t_f,
            graph_res=cfg.navgraph.resolution_m,
        )
    return out


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    from smana.common.cli import positive_int

    r = sub.add_parser(
        "routes",
        help="terrain share of the cheapest routes between random places, per grass cost "
        "(no exploration; measured once: about 5 s)",
        description="The terrain share of the cheapest routes between random places of the "
        "garden at each grass cost, without exploring: what the layout alone decides.",
        epilog="Duration measured once on a 2-core machine: about 1 s per seed (5 seeds x 3 "
        "factors: 4.5 s). "
        "The worlds are the exploration experiment's (same seeds, size and layout; --layout "
        "another sim.garden.layout, its data in data/routes_<layout>.json).",
    )
    r.add_argument(
        "--out", type=Path, help="output directory (default runs/experiment-routes-<time>)"
    )
    r.add_argument("--seeds", type=positive_int, default=5, help="number of seeds (default 5)")
    r.add_argument("--factors", default="1,2,4", help="grass cost factors (default 1,2,4)")
    r.add_argument(
        "--layout",
        choices=garden_layouts(),
        help="garden layout (sim.garden.layout; default the exploration experiment's, 3drms)",
    )


def garden_layouts() -> tuple[str, ...]:
    """The values `sim.garden.layout` takes, read from its type (defined once, in the config)."""
    import typing

    from smana.services.sim.worlds.garden import GardenConfig

    return typing.get_args(typing.get_type_hints(GardenConfig)["layout"])


def main(args, parser, out: Path) -> int:
    from smana.common.config import SmanaConfig

    from .exploration import ExplorationExperimentConfig, run_world_sets

    try:
        factors = [float(v) for v in args.factors.split(",") if v.strip()]
    except ValueError:
        parser.error(f"--factors: expected numbers like 1,2,4, got {args.factors!r}")
    if not factors or min(factors) <= 0:
        parser.error(f"--factors: expected positive numbers, got {args.factors!r}")
    s = ExplorationExperimentConfig()
    layout = getattr(args, "layout", None)
    sets = run_world_sets([f'sim.garden.layout="{layout}"'] if layout else [])
    # the exploration experiment's layout keeps its data file's name; another is a variant
    variant = None if layout in (None, "3drms") else layout
    name = f"routes_{variant}" if variant else "routes"
    command = f"smana experiment routes --seeds {args.seeds} --factors {args.factors}"
    command += f" --layout {layout}" if layout else ""
    seeds = list(range(3, 3 + args.seeds))
    clearance = SmanaConfig.load().navgraph.robot_radius_m
    per_seed = {}
    with progress.bar(len(seeds), "routes", unit="seed") as bar:
        for seed in seeds:
            per_seed[seed] = world_routes(seed, s.size_m, factors, sets, clearance)
            bar.update()
    rows = [
        {"grass_cost_factor": f, **stats.mean_ci([per_seed[k][f] for k in seeds]).as_dict()}
        for f in factors
    ]
    out.mkdir(parents=True, exist_ok=True)
    from .report import write_data

    write_data(
        out,
        "routes",
        [
            {"seed": k, "grass_cost_factor": f, "terrain_share": per_seed[k][f]}
            for k in seeds
            for f in factors
        ],
        {"command": command, "layout": layout or "3drms"},
        variant=variant,
    )
    (out / f"{name}_results.json").write_text(
        json.dumps({"seeds": seeds, "per_seed": per_seed, "summary": rows}, indent=2)
    )
    lines = [
        "# Terrain share of the cheapest routes between random places (no exploration)",
        "",
        f"Seeds {seeds}, garden {s.size_m} m, {' '.join(sets)}, robot clearance "
        f"{clearance} m; 200 routes per seed and factor.",
        "",
        "| grass cost | terrain share of routes, mean [95 % CI] (n) |",
        "|---|---|",
    ]
    for f in factors:
        iv = stats.mean_ci([per_seed[k][f] for k in seeds])
        lines.append(f"| x{f:g} | {iv.format(100, unit=' %')} |")
    (out / f"{name}_summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0
