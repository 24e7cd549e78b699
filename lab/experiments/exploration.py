"""`smana experiment exploration` (paper 4.3): the whole stack (`smana up`) explores the garden
with the grass traversability cost at x1 (costs ignored: grass costs what terrain costs), x2 (the
class table) and x4, over several world seeds; the share of travelled graph nodes on terrain (vs
grass), explored area and distance are read from each run's metrics.json.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.zenoh_config import free_loopback_port
from smana.lab import plots

PAPER_TERRAIN_SHARE = {1.0: 0.60, 2.0: 0.70, 4.0: 0.88}  # grass cost factor -> terrain share


# -- exploration experiment ----------------------------------------------------------------------


@dataclass
class ExplorationExperimentConfig:
    """What `smana experiment exploration` runs: one `smana up` per seed and grass cost factor."""

    seeds: tuple[int, ...] = (3, 4, 5)
    cost_factors: tuple[float, ...] = (1.0, 2.0, 4.0)
    size_m: float = 12.0
    budget_s: float = 480.0
    extra: tuple[str, ...] = ()  # more --set overrides for every run

    @classmethod
    def quick(cls) -> ExplorationExperimentConfig:
        # a 6 m garden, a small camera and a 10 cm map: two short closed loops for the test suite
        small = (
            "sim.camera.width=160",
            "sim.camera.height=160",
            "mapper.resolution_m=0.1",
            "navgraph.bounds_min_xy=[-4.0, -4.0]",
            "navgraph.bounds_max_xy=[4.0, 4.0]",
            # no hot spares: a 20 s run would start five only to stop them
            "deploy.standby_delay_s=3600",
        )
        return cls(seeds=(3,), cost_factors=(1.0, 4.0), size_m=6.0, budget_s=20.0, extra=small)


def exploration_run(
    out: Path, seed: int, factor: float, s: ExplorationExperimentConfig, log=progress.say
):
    """One `smana up` run with grass at `factor` times terrain's cost; returns its metrics."""
    from smana.common.classes import ClassTable

    table = ClassTable.load("garden3drms")
    terrain = table.by_name("terrain").cost
    # absolute: the supervisor starts each service inside the run directory
    run_dir = (out / f"seed{seed}_grass_x{factor:g}").resolve()
    # a robot name of its own: stray processes of another stack that reach this router (a reused
    # port) then talk on other keys
    robot = f"exp{os.getpid()}-s{seed}-x{factor:g}".replace(".", "_")
    sets = [
        f'general.robot="{robot}"',
        f"sim.seed={seed}",
        f"sim.garden.size_m={s.size_m}",
        f"explorer.time_budget_s={s.budget_s}",
        f'explorer.class_costs=["grass={factor * terrain}"]',
        *s.extra,
    ]
    port = free_loopback_port()
    argv = [
        sys.executable,
        "-m",
        "smana.deploy.cli",
        "up",
        "--run-dir",
        str(run_dir),
        "--set",
        f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
    ]
    for item in sets:
        argv += ["--set", item]
    t0 = time.perf_counter()
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "up.log", "w") as f:
        code = subprocess.call(
            argv, stdout=f, stderr=subprocess.STDOUT, timeout=s.budget_s * 3 + 180
        )
    metrics = None
    if (run_dir / "metrics.json").is_file():
        metrics = json.loads((run_dir / "metrics.json").read_text())
    log(f"seed {seed} grass x{factor:g}: exit {code}, {time.perf_counter() - t0:.0f} s")
    return code, metrics or {}


def run_exploration(s: ExplorationExperimentConfig, out: Path, log=progress.say) -> list[dict]:
    rows = []
    # one step per `smana up`: each runs to its time budget or to the end of the frontiers
    runs = progress.bar(len(s.seeds) * len(s.cost_factors), "exploration", unit="run")
    for seed in s.seeds:
        for factor in s.cost_factors:
            runs.set_postfix_str(f"seed {seed} grass x{factor:g}")
            code, m = exploration_run(out, seed, factor, s, log)
            runs.update()
            ex = m.get("exploration") or {}
            ee = m.get("explorer") or {}
            rows.append(
                {
                    "seed": seed,
                    "grass_cost_factor": factor,
                    "exit_code": code,
                    "terrain_share": ex.get("terrain_share"),
                    "coverage": ex.get("coverage"),
                    "explored_area_m2": ex.get("explored_reachable_area_m2"),
                    "distance_m": ex.get("distance_m"),
                    "min_clearance_m": ex.get("min_clearance_m"),
                    "done_reason": ee.get("done_reason"),
                    "wall_time_s": ee.get("wall_time_s"),
                }
            )
            log(f"  terrain share {rows[-1]['terrain_share']}, coverage {rows[-1]['coverage']}")
    runs.close()
    write_exploration_outputs(rows, s, out)
    return rows


def summarise_exploration(rows: list[dict]) -> list[dict]:
    out = []
    for f in sorted({r["grass_cost_factor"] for r in rows}):
        sel = [r for r in rows if r["grass_cost_factor"] == f]

        def stat(key, sel=sel):
            v = np.array([r[key] for r in sel if r[key] is not None], float)
            return (float(v.mean()), float(v.std())) if len(v) else (None, None)

        ts, cov, dist = stat("terrain_share"), stat("coverage"), stat("distance_m")
        out.append(
            {
                "grass_cost_factor": f,
                "runs": len(sel),
                "terrain_share_mean": ts[0],
                "terrain_share_std": ts[1],
                "coverage_mean": cov[0],
                "coverage_std": cov[1],
                "distance_mean_m": dist[0],
                "distance_std_m": dist[1],
                "paper_terrain_share": PAPER_TERRAIN_SHARE.get(f),
            }
        )
    return out


def write_exploration_outputs(rows: list[dict], s: ExplorationExperimentConfig, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "exploration_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise_exploration(rows)
    (out / "exploration_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "summary": summary}, indent=2)
    )
    xs = [d["grass_cost_factor"] for d in summary]
    ok = [d for d in summary if d["terrain_share_mean"] is not None]
    shares = {
        d["grass_cost_factor"]: [
            r["terrain_share"]
            for r in rows
            if r["grass_cost_factor"] == d["grass_cost_factor"] and r["terrain_share"] is not None
        ]
        for d in ok
    }
    ns = sorted({len(v) for v in shares.values()})
    n_text = f"n = {ns[0]}" if len(ns) == 1 else f"n = {ns[0]}-{ns[-1]}"
    n_text += " seed" if ns == [1] else " seeds"
    mean = [d["terrain_share_mean"] for d in ok]
    spread = None  # with one seed there is no spread to draw
    if ns and ns[-1] > 1:
        spread = (
            [m - min(shares[d["grass_cost_factor"]]) for m, d in zip(mean, ok)],
            [max(shares[d["grass_cost_factor"]]) - m for m, d in zip(mean, ok)],
        )
    label = f"smana, mean and min-max ({n_text})" if spread else f"smana ({n_text})"
    series = [plots.Series(label, [d["grass_cost_factor"] for d in ok], mean, spread)]
    paper = [(f, v) for f, v in PAPER_TERRAIN_SHARE.items() if f in xs]
    if paper:
        series.append(
            plots.Series("paper", [f for f, _ in paper], [v for _, v in paper], dashed=True)
        )
    plots.save(
        plots.line_plot(
            series,
            f"Travelled nodes on terrain vs grass cost ({n_text})",
            "grass cost factor (x terrain's cost)",
            "terrain share of travelled nodes",
            {f: f"x{f:g}" for f in xs},
        ),
        out / "exploration_terrain_share.png",
    )
    lines = [
        "# Exploration experiment (paper 4.3)",
        "",
        f"Seeds {list(s.seeds)}, garden {s.size_m} m, budget {s.budget_s:.0f} s per run.",
        "",
        "| grass cost | runs | terrain share | paper | coverage | distance (m) |",
        "|---|---|---|---|---|---|",
    ]

    def pm(m, sd, scale=1.0, fmt=".1f"):
        return "-" if m is None else f"{format(m * scale, fmt)} +- {format(sd * scale, fmt)}"

    for d in summary:
        paper_v = d["paper_terrain_share"]
        lines.append(
            f"| x{d['grass_cost_factor']:g} | {d['runs']} | "
            f"{pm(d['terrain_share_mean'], d['terrain_share_std'], 100)} % | "
            f"{'-' if paper_v is None else f'{100 * paper_v:.0f} %'} | "
            f"{pm(d['coverage_mean'], d['coverage_std'], 100)} % | "
            f"{pm(d['distance_mean_m'], d['distance_std_m'])} |"
        )
    shares = [d["terrain_share_mean"] for d in summary if d["terrain_share_mean"] is not None]
    if len(shares) >= 2:
        rising = all(b >= a for a, b in zip(shares[:-1], shares[1:], strict=True))
        lines += [
            "",
            "Direction of the paper's effect (terrain share rises with the grass cost): "
            + ("reproduced" if rising else "NOT reproduced")
            + ".",
        ]
    lines += ["", "![terrain share](exploration_terrain_share.png)", ""]
    (out / "exploration_summary.md").write_text("\n".join(lines))


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `exploration` subcommand of `smana experiment`."""
    from smana.common.cli import positive_float, positive_int

    e = sub.add_parser(
        "exploration",
        help="terrain share vs grass traversability cost (about 30 min; --quick 1.5 min)",
        description="Paper 4.3: one `smana up` per world seed and grass cost factor (x1, x2, "
        "x4); the share of travelled nodes on terrain.",
        epilog="Duration on a 2-core machine: about 30 minutes (3 seeds x 3 grass costs = 9 "
        "runs of smana up, each up to --budget seconds); --quick about 1.5 minutes (2 runs of "
        "20 s in a 6 m garden). A progress bar with an ETA shows on a terminal "
        "(SMANA_PROGRESS=1 forces it, 0 hides it).",
    )
    e.add_argument(
        "--quick", action="store_true", help="2 runs of 20 s in a 6 m garden (about 1.5 min)"
    )
    e.add_argument("--out", type=Path)
    e.add_argument("--seeds", type=positive_int, help="number of world seeds (3, 4, ...)")
    e.add_argument("--budget", type=positive_float, help="time budget per run, seconds")
    e.add_argument(
        "--set",
        dest="extra",
        action="append",
        default=[],
        help="extra config override for every run",
    )


def check_args(args) -> None:
    """Refuse a bad --set now, not in every run (ConfigError, one line)."""
    from smana.common.config import SmanaConfig

    SmanaConfig.load(overrides=args.extra)


def main(args, parser, out: Path) -> int:
    s = ExplorationExperimentConfig.quick() if args.quick else ExplorationExperimentConfig()
    if args.seeds:
        s.seeds = tuple(range(3, 3 + args.seeds))
    if args.budget:
        s.budget_s = args.budget
    s.extra = (*s.extra, *args.extra)
    run_exploration(s, out)
    print(f"results in {out} (exploration_summary.md)")
    return 0
