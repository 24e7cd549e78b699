"""`smana experiment risk`: does planning on the map's label distribution keep
the robot out of a class that only semantics can see? This module holds the command line and
the first form, `--synthetic`; the default form, the closed loop (`smana up` in the wet garden
under the paper's label and pose noise), is lab/experiments/riskloop.py.

The synthetic form is in-process: it does not render frames nor run the mapper's back-ends. Per
seed:

- the ground truth: a flat N x N graph (0.2 m nodes) of terrain, grass patches, patches of a
  forbidden flat class (water of the wet garden's table, garden3drms_wet: infinite cost, not an
  obstacle) and tree discs with their safety zone;
- per label-noise level p: every free node is seen in 1 to 6 frames (smooth over the map); in each
  frame, 3 x 3-node superpixels keep their true class with probability p, else are redrawn to
  another ground class (terrain, grass, forbidden), a stand-in for SLIC + Table 2's confusions
  among the ground classes. The map's distribution per node is the posterior of its counts under
  a Jeffreys prior (count + 0.5), its top 2 named (the graph's risk layers), the rest unnamed; the
  label is the most likely class. Geometry (obstacles, safety zones) is the truth's: no pose noise;
- paths between random pairs of truly free places at least a third of the map apart (joined in
  the truth), planned in every arm.

Arms: `truth` (the planner on the true labels: the reference), `argmax` (the map's labels only,
no distribution: the planner without risk), and the map with its distribution under
`planner.risk` = `expected`, `cvar` (risk_alpha 0.2) and `chance` (max_risk 0.25), the other
[planner] fields at their defaults.

Measured against the truth, never the map, per path: the nodes entered whose true class is
forbidden, the path length, its true cost (eq. 1 with true classes, a forbidden node priced at
`risk_forbidden_cost`), success (a path found that enters no forbidden node). Rules, fixed before
the runs (lab/stats.py, paired per seed), at p = 0.7 for `cvar` and for `chance` against
`expected` (the target fixed before the runs):
1. ">= 50 % fewer forbidden entries": 0.5 x expected's minus the arm's mean entries per path lies
   above 0 (`decide_above`);
2. "<= 10 % longer paths": the arm's mean length over expected's, minus 1, on the pairs both
   found, is not worse than +0.10 (`decide_not_worse`);
3. "no loss of success": the arm's success rate minus expected's is not worse than -0.05
   (`decide_not_worse`, higher is better).
The six verdicts are corrected together (Holm).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from smana.common import progress
from smana.common.classes import ClassTable
from smana.common.config.planner import PlannerConfig
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, P_SCALE, NavGrid
from smana.lab import stats
from smana.services.planner.planner import Planner

RES_M = 0.2
ROBOT_RADIUS_M = 0.4
LEVELS = (1.0, 0.9, 0.8, 0.7)
ARMS = ("truth", "argmax", "expected", "cvar", "chance")
RISK_ARMS = {
    "expected": {"risk": "expected"},
    "cvar": {"risk": "cvar", "risk_alpha": 0.2},
    # not 0.1: the prior alone gives every class >= 0.5 / 7.5 (6 frames), and the unnamed third
    # class counts as forbidden too, so at 0.1 every node was closed (the first full run: 0 %
    # success); at 0.25 a node seen 6 times is closed by one forbidden sighting
    "chance": {"risk": "chance", "max_risk": 0.25},
}
TARGET_P = 0.7
FEWER = 0.5  # rule 1: at least 50 % fewer forbidden entries
LONGER_MARGIN = 0.10  # rule 2: at most 10 % longer
SUCCESS_MARGIN = 0.05  # rule 3: success at most 5 points lower
PRIOR = 0.5  # Jeffreys: the map's posterior is (count + 0.5) / (frames + 1.5)
SUPERPIXEL = 3  # nodes a side
MAX_FRAMES = 6
GRASS, TERRAIN, TREE = 1, 2, 8
FIRST_SEED = 3  # the seeds are 3, 4, ...; --figure draws this one
FIGURE_DPI = 80


def risk_classes() -> tuple[ClassTable, int]:
    """The wet garden's class table (garden3drms_wet) and its forbidden flat class, water."""
    classes = ClassTable.load("garden3drms_wet")
    return classes, int(np.flatnonzero(classes.forbidden_lut)[0])


def true_world(seed: int, n: int, forbidden: int):
    """Ground truth: labels (u2) and flags (u1) of an n x n flat garden."""
    rng = np.random.default_rng(seed)
    smooth = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=n / 15, mode="wrap")
    labels = np.where(smooth > np.quantile(smooth, 0.6), GRASS, TERRAIN).astype(np.uint16)
    wet = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=n / 30, mode="wrap")
    labels[wet > np.quantile(wet, 0.9)] = forbidden  # patches over about 10 % of the ground
    tree = np.zeros((n, n), bool)
    xx, yy = np.mgrid[0:n, 0:n]
    for _ in range(int(0.05 * n * n / (np.pi * (0.6 / RES_M) ** 2))):
        cx, cy = rng.integers(0, n, 2)
        r = rng.uniform(0.3, 0.9) / RES_M
        tree |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    labels[tree] = TREE
    near = ndimage.distance_transform_edt(~tree) * RES_M <= ROBOT_RADIUS_M + 1e-9
    flags = (
        FLAG_KNOWN | np.where(tree, FLAG_OBSTACLE, 0) | np.where(near & ~tree, FLAG_SAFETY_ZONE, 0)
    )
    return labels, flags.astype(np.uint8)


def noisy_map(truth, flags, ground, p: float, rng):
    """The map's labels and risk layers (alt_labels, p_label, p_alt) after frames whose
    superpixels keep their true ground class with probability p (see the module docstring)."""
    n = truth.shape[0]
    ground = np.asarray(ground)
    free = (flags & FLAG_OBSTACLE) == 0
    true_k = np.argmax(truth[..., None] == ground, axis=-1)  # index in `ground`
    b = 5  # frames per node: smooth over 5 x 5-node blocks
    frames = np.kron(rng.integers(1, MAX_FRAMES + 1, (n // b + 1, n // b + 1)), np.ones((b, b)))
    frames = frames[:n, :n].astype(int)
    counts = np.zeros((n, n, len(ground)))
    s = SUPERPIXEL
    for f in range(MAX_FRAMES):
        ox, oy = rng.integers(0, s, 2)
        nb = n // s + 2
        redraw = np.kron(rng.random((nb, nb)) >= p, np.ones((s, s), bool))[ox : ox + n, oy : oy + n]
        shift = np.kron(rng.integers(1, len(ground), (nb, nb)), np.ones((s, s), int))
        seen_k = np.where(redraw, (true_k + shift[ox : ox + n, oy : oy + n]) % len(ground), true_k)
        seen = free & (frames > f)
        np.add.at(counts, (*np.nonzero(seen), seen_k[seen]), 1.0)
    post = (counts + PRIOR) / (frames[..., None] + PRIOR * len(ground))
    order = np.argsort(-(post + rng.random(post.shape) * 1e-9), axis=-1)  # ties: at random
    top, second = order[..., 0], order[..., 1]
    p1 = np.take_along_axis(post, top[..., None], -1)[..., 0]
    p2 = np.take_along_axis(post, second[..., None], -1)[..., 0]
    labels = np.where(free, ground[top], truth).astype(np.uint16)
    p_label = np.where(free, np.rint(p1 * P_SCALE), P_SCALE).astype(np.uint8)
    alt = np.where(free, ground[second], 0).astype(np.uint16)
    p_alt = np.where(free, np.minimum(np.rint(p2 * P_SCALE), P_SCALE - p_label), 0)
    return labels, (alt, p_label, p_alt.astype(np.uint8))


def make_grid(labels, flags, risk=None) -> NavGrid:
    n = labels.shape[0]
    grid = NavGrid((0.0, 0.0), labels.shape, RES_M, tile_size=32)
    cells = np.argwhere(np.ones((n, n), bool))
    heights = np.zeros(n * n, np.float32)
    risk = None if risk is None else [r.ravel() for r in risk]
    grid.apply_patch(cells, labels.ravel(), heights, flags.ravel(), risk=risk)
    return grid


def pairs_of(truth_planner: Planner, truth, flags, forbidden, k: int, rng):
    """k start/goal pairs on truly free ground (not forbidden, no obstacle or safety zone), at
    least a third of the map apart, joined in the truth."""
    n = truth.shape[0]
    ok = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    ok &= truth != forbidden
    free = np.argwhere(ok)
    out = []
    for _ in range(50 * k):
        if len(out) == k:
            break
        a, b = free[rng.integers(0, len(free), 2)]
        if np.hypot(*(a - b)) < n / 3:
            continue
        xy = truth_planner.grid.cell_centre(np.array([a[0], b[0]]), np.array([a[1], b[1]]))
        if truth_planner.plan(xy[0], xy[1]).ok:
            out.append((xy[0], xy[1]))
    return out


def judge(res, truth, forbidden, classes, config: PlannerConfig) -> dict:
    """A path measured against the truth."""
    if not res.ok:
        return {"found": False, "forbidden": 0, "length_m": None, "true_cost": None, "ok": False}
    entered = res.cells[1:]
    true = truth[entered[:, 0], entered[:, 1]]
    n_bad = int(np.count_nonzero(true == forbidden))
    t = np.where(true == forbidden, config.risk_forbidden_cost, classes.cost_lut[true])
    cost = res.cost_distance + config.t_f * float(t.sum())
    return {
        "found": True,
        "forbidden": n_bad,
        "length_m": float(res.cost_distance),
        "true_cost": cost,
        "ok": n_bad == 0,
    }


def arm_planners(truth_planner: Planner, labels, flags, risk, classes, base) -> dict:
    """{arm: Planner} of every arm (ARMS) on one noisy map (labels and its risk layers)."""
    planners = {
        "truth": truth_planner,
        "argmax": Planner(make_grid(labels, flags), classes, base),
    }
    risky = make_grid(labels, flags, risk)
    for arm, fields in RISK_ARMS.items():
        planners[arm] = Planner(risky, classes, dataclasses.replace(base, **fields))
    return planners


class SeedWorld(NamedTuple):
    """One seed's ground truth, the planner on it and the seed's start/goal pairs."""

    classes: ClassTable
    forbidden: int
    truth: np.ndarray
    flags: np.ndarray
    base: PlannerConfig
    truth_planner: Planner
    pairs: list


def seed_world(seed: int, n: int, n_pairs: int) -> SeedWorld:
    classes, forbidden = risk_classes()
    truth, flags = true_world(seed, n, forbidden)
    # the planner's cost as this experiment measured it: its question is the risk modes, and
    # the clearance cost beside safety zones (added later, a closed-loop matter) is off
    base = PlannerConfig(clearance_cost=0.0)
    truth_planner = Planner(make_grid(truth, flags), classes, base)
    rng = np.random.default_rng(1000 + seed)
    pairs = pairs_of(truth_planner, truth, flags, forbidden, n_pairs, rng)
    return SeedWorld(classes, forbidden, truth, flags, base, truth_planner, pairs)


def seed_map(w: SeedWorld, seed: int, p: float):
    """The map (labels, risk layers) of a seed's world at label-noise level p."""
    ground = [TERRAIN, GRASS, w.forbidden]
    return noisy_map(w.truth, w.flags, ground, p, np.random.default_rng([seed, int(p * 100)]))


def seed_rows(seed: int, n: int, n_pairs: int, levels) -> list[dict]:
    """Every arm's paths at every level on one seed's world: one row per (level, arm, pair)."""
    w = seed_world(seed, n, n_pairs)
    rows = []
    for p in levels:
        labels, risk = seed_map(w, seed, p)
        planners = arm_planners(w.truth_planner, labels, w.flags, risk, w.classes, w.base)
        for arm in ARMS:
            for i, (a, b) in enumerate(w.pairs):
                res = planners[arm].plan(a, b)
                row = {"seed": seed, "p": p, "arm": arm, "pair": i}
                rows.append(row | judge(res, w.truth, w.forbidden, w.classes, w.base))
    return rows


# -- the figure ----------------------------------------------------------------------------------


def figure_case(seed: int, n: int, n_pairs: int) -> dict:
    """What `--figure` draws: one seed's world and its map at p = TARGET_P, and every arm's path
    between one of the seed's pairs, the one the map's labels alone (`argmax`) plan into the
    forbidden class most often (the first such pair on a tie), each judged by `judge`."""
    w = seed_world(seed, n, n_pairs)
    labels, risk = seed_map(w, seed, TARGET_P)
    planners = arm_planners(w.truth_planner, labels, w.flags, risk, w.classes, w.base)

    def scored(arm, pair):
        res = planners[arm].plan(*pair)
        return res, judge(res, w.truth, w.forbidden, w.classes, w.base)

    worst = max(
        range(len(w.pairs)), key=lambda i: (scored("argmax", w.pairs[i])[1]["forbidden"], -i)
    )
    paths = {arm: scored(arm, w.pairs[worst]) for arm in ARMS}
    return {
        "world": w,
        "labels": labels,
        "risk": risk,
        "configs": {arm: planners[arm].config for arm in ARMS},
        "pair": worst,
        "paths": paths,
    }


def figure_main(args) -> int:
    """`--figure PATH`: the figure of the first seed, written to PATH; no experiment, no --out."""
    from smana.lab.paper_figures import risk_map_figure, save_palette

    seed = FIRST_SEED
    n = args.nodes or 150
    case = figure_case(seed, n, args.pairs or 20)
    fig = risk_map_figure(case, seed, RES_M)
    path = save_palette(fig, args.figure, dpi=FIGURE_DPI)
    print(f"{path}: seed {seed}, {n} x {n} nodes, p = {TARGET_P}, pair {case['pair']}")
    return 0


# -- the verdicts --------------------------------------------------------------------------------


def _of(rows, p, arm, seed):
    return [r for r in rows if r["p"] == p and r["arm"] == arm and r["seed"] == seed]


def per_seed(rows, p, arm) -> dict[int, dict]:
    """{seed: mean forbidden entries per path, success rate} of an arm at a level."""
    out = {}
    for seed in sorted({r["seed"] for r in rows}):
        rs = _of(rows, p, arm, seed)
        if rs:
            out[seed] = {
                "forbidden": float(np.mean([r["forbidden"] for r in rs])),
                "success": float(np.mean([r["ok"] for r in rs])),
            }
    return out


def length_ratio(rows, p, arm, seed) -> float | None:
    """The arm's mean path length over expected's on the pairs both found, minus 1."""
    mine = {r["pair"]: r for r in _of(rows, p, arm, seed) if r["found"]}
    ref = {r["pair"]: r for r in _of(rows, p, "expected", seed) if r["found"]}
    both = sorted(set(mine) & set(ref))
    if not both:
        return None
    return sum(mine[i]["length_m"] for i in both) / sum(ref[i]["length_m"] for i in both) - 1


def claims(rows) -> list[dict]:
    """The six verdicts at p = TARGET_P (the module docstring's rules), corrected together."""
    if TARGET_P not in {r["p"] for r in rows}:
        return []
    exp = per_seed(rows, TARGET_P, "expected")
    out, decisions = [], []
    for arm in ("cvar", "chance"):
        mine = per_seed(rows, TARGET_P, arm)
        seeds = sorted(set(exp) & set(mine))
        fewer = stats.mean_ci([FEWER * exp[s]["forbidden"] - mine[s]["forbidden"] for s in seeds])
        ratios = [length_ratio(rows, TARGET_P, arm, s) for s in seeds]
        longer = stats.mean_ci([v for v in ratios if v is not None])
        success = stats.mean_ci([mine[s]["success"] - exp[s]["success"] for s in seeds])
        for claim, ci, d in (
            (
                f"{arm}: >= 50 % fewer forbidden entries than expected",
                fewer,
                stats.decide_above(fewer),
            ),
            (
                f"{arm}: paths <= 10 % longer than expected's",
                longer,
                stats.decide_not_worse(longer, LONGER_MARGIN),
            ),
            (
                f"{arm}: no loss of success against expected",
                success,
                stats.decide_not_worse(success, SUCCESS_MARGIN, higher_is_better=True),
            ),
        ):
            out.append({"claim": claim, "interval": ci})
            decisions.append(d)
    for c, d in zip(out, stats.holm_table(decisions), strict=True):
        c.update(d.fields())
    return out


# -- command line --------------------------------------------------------------------------------

CLOSED_LOOP_ONLY = ("budget", "jobs", "size", "arms")
SYNTHETIC_ONLY = ("pairs", "nodes", "figure")


def add_parser(sub) -> None:
    from smana.common.cli import int_in, positive_float, positive_int

    r = sub.add_parser(
        "risk",
        help="risk-aware navigation: closed-loop exploration of the wet garden under "
        "label and pose noise, planner.risk expected vs cvar vs chance (measured once: 2 seeds "
        "in 6.5 min, so 10 seeds about 33 min at that load; --quick 1.5 min)",
        description="Closed loop (the default): one `smana up` per arm (noise-free reference; "
        "expected, cvar, chance under label noise p = 0.7 and pose noise) and seed in the wet "
        "garden, measured against ground truth: forbidden-class entries and time, true path "
        "cost, length, contacts, coverage; verdicts on the targets fixed before the runs "
        "(lab/experiments/riskloop.py). --synthetic: the first form, in-process on synthetic "
        "maps (lab/experiments/risk.py).",
        epilog="Duration on a 2-core machine shared with other work, measured once: the full "
        "form (10 seeds x 4 arms = 40 runs of smana up, 2 at once, 10 m garden, 75 s of robot "
        "time each) took 31 min at load 9 to 12 (2026-12-03). --quick (the 4 arms of 1 seed, 20 s "
        "each in a 6 m garden): 1 min 34 s. --synthetic: 25 s (10 seeds); --figure: 5 s of CPU, "
        "12 to 56 s wall. A rerun into the same --out keeps the runs that finished and runs the "
        "rest. Exits 1 if any run failed (a run "
        "that ended only because the robot did not move or found no path is a result).",
    )
    r.add_argument(
        "--out", type=Path, help="output directory (default runs/experiment-risk-<time>)"
    )
    r.add_argument(
        "--quick",
        action="store_true",
        help="test-sized: the 4 arms of 1 seed, 20 s each in a 6 m garden (synthetic: 2 seeds, "
        "small maps, p 1 and 0.7)",
    )
    r.add_argument("--seeds", type=int_in(2), help="number of seeds (default 10; 2 or more)")
    r.add_argument(
        "--size", type=positive_float, help="side of the wet garden, m (default 10; quick 6)"
    )
    r.add_argument(
        "--budget",
        type=positive_float,
        help="time budget per run, s of robot time (default 75; quick 20)",
    )
    r.add_argument("--jobs", type=positive_int, help="runs of smana up at once (default 2)")
    r.add_argument("--set", dest="extra", action="append", default=[], help="extra config override")
    r.add_argument(
        "--arms",
        help="comma-separated arms (default clean,expected,cvar,chance; also label: the default "
        "planner under the same noise, in no verdict)",
    )
    r.add_argument(
        "--synthetic",
        action="store_true",
        help="the first form: planning between random pairs on synthetic maps, in-process",
    )
    r.add_argument(
        "--pairs", type=positive_int, help="synthetic: start/goal pairs per seed (default 20)"
    )
    r.add_argument(
        "--nodes", type=int_in(30, 1000), help="synthetic: map size in nodes a side (default 150)"
    )
    r.add_argument(
        "--figure",
        type=Path,
        metavar="PNG",
        help="synthetic: instead of the experiment, draw its first seed at p = 0.7 coloured by "
        "risk into this file (docs/risk_map.png): the true classes, the map's most likely class, "
        "P(forbidden), the node costs under expected, cvar and chance, each arm's path between "
        "one start and goal with its true water entries",
    )


def check_args(args, parser=None) -> None:
    """Refuse options of the other form and a bad --set now, in one line."""
    from smana.common.cli import UsageError

    other = SYNTHETIC_ONLY if not args.synthetic else (*CLOSED_LOOP_ONLY, "extra")
    given = [k for k in other if getattr(args, k)]
    if given:
        names = ", ".join(f"--{'set' if k == 'extra' else k}" for k in given)
        form = "the closed loop" if args.synthetic else "--synthetic"
        raise UsageError(f"{names}: an option of {form} only")
    if args.figure is not None:
        from smana.common.cli import output_file

        given = [k for k in ("out", "quick", "seeds") if getattr(args, k)]
        if given:
            raise UsageError(f"--{given[0]}: not with --figure, which draws one seed into a file")
        output_file(args.figure, "--figure")
    if not args.synthetic:
        from smana.common.config import SmanaConfig

        from . import exploration as ex
        from .riskloop import ARMS, arms_of

        SmanaConfig.load(overrides=[*ex.WORLD_SETS, *ARMS[-1].sets, *args.extra])
        if args.arms is not None:
            arms_of(args.arms)


def needs_output(args) -> bool:
    """Whether `smana experiment` makes the run directory: not for `--figure`, one file."""
    return args.figure is None


def main(args, parser, out: Path | None) -> int:
    if args.figure is not None:
        return figure_main(args)
    if args.synthetic:
        return synthetic_main(args, out)
    from .riskloop import run

    return run(args, out)


def synthetic_main(args, out: Path) -> int:
    """The first form (`--synthetic`): in-process, on synthetic maps."""
    from .report import write_data

    seeds = list(range(FIRST_SEED, FIRST_SEED + (args.seeds or (2 if args.quick else 10))))
    n = args.nodes or (60 if args.quick else 150)
    n_pairs = args.pairs or (6 if args.quick else 20)
    levels = (1.0, TARGET_P) if args.quick else LEVELS
    rows = []
    with progress.bar(len(seeds), "risk", unit="seed") as bar:
        for seed in seeds:
            rows += seed_rows(seed, n, n_pairs, levels)
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "seeds": seeds,
        "size": n,
        "pairs": n_pairs,
        "levels": list(levels),
        "form": "synthetic",
    }
    write_data(out, "risk", rows, meta, "synthetic")
    decided = claims(rows)
    lines = [
        "# Risk-aware planning under label noise (synthetic maps)",
        "",
        f"Seeds {seeds}, {n} x {n} nodes at {RES_M} m, {n_pairs} pairs per seed; mean per seed "
        "[95 % CI] (n seeds).",
        "",
        "| p | arm | forbidden entries per path | success | path length m |",
        "|---|---|---|---|---|",
    ]
    for p in levels:
        for arm in ARMS:
            ps = per_seed(rows, p, arm)
            lengths = []
            for s in ps:
                found = [r["length_m"] for r in _of(rows, p, arm, s) if r["found"]]
                if found:
                    lengths.append(float(np.mean(found)))
            f = stats.mean_ci([v["forbidden"] for v in ps.values()])
            ok = stats.mean_ci([v["success"] for v in ps.values()])
            ln = stats.mean_ci(lengths)
            lines.append(
                f"| {p:g} | {arm} | {f.format(fmt='.2f')} | {ok.format(100, unit=' %')} | "
                f"{ln.format(fmt='.2f')} |"
            )
    lines += [
        "",
        f"Verdicts at p = {TARGET_P} (Holm-corrected):",
        "",
        "| claim | value | verdict |",
    ]
    lines.append("|---|---|---|")
    for c in decided:
        lines.append(f"| {c['claim']} | {c['interval'].format(fmt='.3f')} | {c['verdict']} |")
    (out / "risk_summary.md").write_text("\n".join(lines) + "\n")
    (out / "risk_results.json").write_text(
        json.dumps(
            {"meta": meta, "claims": [c | {"interval": c["interval"].as_dict()} for c in decided]},
            indent=2,
        )
    )
    print("\n".join(lines))
    return 0
