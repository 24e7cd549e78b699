"""`smana experiment report`: the tables of docs/experiments.md, regenerated from the raw results
committed beside it (docs/experiments/data/), so that a figure in the docs is one the data gives.

Every experiment writes its compact raw results, one row per seed and arm (back-end, noise level,
fleet size), into `<out>/data/<name>.json` (`write_data`); copying that file into
docs/experiments/data/ publishes it. The report then rewrites each generated section of the doc,
the text between

    <!-- generated: NAME -->
    <!-- end generated: NAME -->

from the data alone: `verdicts` (every claim of every experiment with data, by the rules of
lab/stats.py, Holm-corrected together), `routes`, `noise` and one `noise_<variant>` per noise
data file (its tables per sweep: lab/experiments/noise.py `section`), `ablation`, ... An
experiment with no committed data says so in its section instead of a number. `--check` changes
nothing and exits 1 when the doc differs from what the data generates
(tests/test_experiment_report.py runs it on the committed doc). Data whose rules file
(docs/experiments/rules/, lab/experiments/rules.py) changed after its runs is refused.

    smana experiment report [--data DIR] [--doc FILE] [--check]
"""

from __future__ import annotations

import contextvars
import json
import math
import re
import sys
import time
from pathlib import Path

from . import rules
from .claims import power_section, routes_intervals, verdicts_section

ROOT = Path(__file__).resolve().parents[2]
DATA_DIR = ROOT / "docs" / "experiments" / "data"
DOC = ROOT / "docs" / "experiments.md"
# the data files a report reads
EXPERIMENTS = (
    "noise",
    "exploration",
    "ablation",
    "fleet",
    "routes",
    "resources",
    "navnoise",
    "risk",
    "robustness",
)
# the noise experiment's tables are one section per data file, each where its prose is: `noise`
# for noise.json, `noise_<variant>` for noise_<variant>.json
NOISE_SECTION = re.compile(r"noise(_[a-z0-9]+)?")
ROBUSTNESS_SECTION = re.compile(r"robustness_[a-z0-9]+")  # robustness.json's is `robustness`
SECTION = re.compile(
    r"(<!-- generated: (?P<name>[a-z0-9_]+) -->\n)(?P<body>.*?)(<!-- end generated: (?P=name) -->)",
    re.S,
)
NO_OUTPUT = True  # `smana experiment` makes no output directory for this one

# The command line of the `smana experiment` running in this context (set by `cli`), which
# `write_data` records in the data's meta: what made a data file is then in the file.
COMMAND: contextvars.ContextVar[str | None] = contextvars.ContextVar("command", default=None)


# -- the data -------------------------------------------------------------------------------------


def _compact(v):
    """Six significant digits: small files, and the same numbers on every machine's JSON."""
    if isinstance(v, float):
        return float(f"{v:.6g}") if math.isfinite(v) else None
    return v


def compact_rows(rows: list[dict]) -> list[dict]:
    """The scalar fields of each row (curves, per-class tables and other lists left out)."""
    return [
        {k: _compact(v) for k, v in r.items() if not isinstance(v, (dict, list, tuple))}
        for r in rows
    ]


def write_data(
    out: Path, name: str, rows: list[dict], meta: dict | None = None, variant: str | None = None
) -> Path:
    """`<out>/data/<name>.json` (or `<name>_<variant>.json` for a run of the experiment in other
    conditions, e.g. a larger garden): {"experiment", "meta", "rows"}, one row a line so that a
    diff of two runs reads row by row. Run by `smana experiment`, the meta also records its
    command line ("command", unless the experiment gave one) and the UTC date ("date")."""
    if variant is not None and not re.fullmatch(r"[a-z0-9]+", variant):
        raise ValueError(f"data variant must be lowercase letters and digits, got {variant!r}")
    path = Path(out) / "data" / (f"{name}_{variant}.json" if variant else f"{name}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(meta or {})
    if COMMAND.get() is not None:
        meta.setdefault("command", COMMAND.get())
        meta.setdefault("date", time.strftime("%Y-%m-%d", time.gmtime()))
        fixed = rules.stamp(name)  # the rules file the runs were decided under (rules.py)
        if fixed is not None:
            meta.setdefault("rules", fixed)
    body = ",\n".join("  " + json.dumps(r, sort_keys=True) for r in compact_rows(rows))
    head = json.dumps({"experiment": name, "meta": meta}, sort_keys=True, default=str)
    path.write_text(head[:-1] + ', "rows": [\n' + body + "\n]}\n")
    return path


def load_data(data_dir: Path) -> dict[str, dict]:
    """{file stem: its data} for every committed data file of a known experiment: `<name>.json`
    and its variants `<name>_<variant>.json` (sorted); a file that is not valid data is a
    one-line ValueError naming it."""
    out = {}
    for name in EXPERIMENTS:
        variants = sorted(Path(data_dir).glob(f"{name}_*.json"))
        for path in [Path(data_dir) / f"{name}.json", *variants]:
            if path.is_file() and re.fullmatch(rf"{name}(_[a-z0-9]+)?", path.stem):
                out[path.stem] = _read_data(path, name)
    return out


def _read_data(path: Path, name: str) -> dict:
    try:
        data = json.loads(path.read_text())
        if data.get("experiment") != name or not isinstance(data.get("rows"), list):
            raise ValueError(f"expected experiment {name!r} and a list of rows")
    except ValueError as exc:
        raise ValueError(f"{path}: not experiment data ({exc})") from None
    return data


# -- the sections ---------------------------------------------------------------------------------


def duration(wall_s) -> str:
    """ "8 min 11 s" (a list of walls, one per run merged into one file: "27 min 27 s + ...")."""
    if isinstance(wall_s, list):
        return " + ".join(duration(w) for w in wall_s)
    m, s = divmod(round(float(wall_s)), 60)
    return f"{m} min {s} s" if m else f"{s} s"


def _missing(name: str) -> str:
    return (
        f"_No raw results of `smana experiment {name}` are committed yet "
        f"(docs/experiments/data/{name}.json): nothing is generated here; the hand-written "
        "tables of this section are transcribed, not yet regenerated._\n"
    )


def routes_section(data: dict | None, name: str = "routes") -> str:
    """The routes' table from `<name>.json`: `routes` (the experiments' layout) or
    `routes_<layout>` (`smana experiment routes --layout <layout>`)."""
    if data is None and name != "routes":
        layout = name.split("_", 1)[1]
        return (
            f"_No raw results of `smana experiment routes --layout {layout}` are committed yet "
            f"(docs/experiments/data/{name}.json): nothing is generated here._\n"
        )
    if data is None:
        return _missing("routes")
    seeds = sorted({r["seed"] for r in data["rows"]})
    lines = [
        f"Generated from docs/experiments/data/{name}.json (seeds {seeds[0]} to {seeds[-1]}):",
        "",
        "| grass cost | routes between random places, terrain share |",
        "|---|---|",
    ]
    for f, ci in routes_intervals(data).items():
        lines.append(f"| x{f:g} | {ci.format(100, unit=' %')} |")
    return "\n".join(lines) + "\n"


def _arm_name(arm: str) -> str:
    kind, _, factor = arm.rpartition("_x")
    return f"{'NBV' if kind == 'nbv' else kind.replace('_', ' ')}, grass x{factor}"


def exploration_section(all_data: dict[str, dict]) -> str:
    """Per exploration data file (the default garden first, then each variant): per arm the
    intervals over seeds, and the distance and time to 95 % as times to an event: how many
    runs reached it, the Kaplan-Meier medians and the restricted mean time up to the budget
    (runs that did not reach it censored, never dropped: exploration.py `time_to_event`)."""
    from .exploration_report import (
        TO_95_HEAD,
        TO_95_NOTE,
        interval_of,
        summarise_exploration,
        to_95_cells,
    )

    keys = [k for k, d in all_data.items() if d["experiment"] == "exploration"]
    if not keys:
        return _missing("exploration")
    lines = []
    for key in keys:
        data = all_data[key]
        rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
        meta = data["meta"]
        seeds = sorted({r["seed"] for r in rows})
        failed = sum(not r["ok"] for r in rows)
        size = float(meta.get("size_m", math.nan))
        lines += [
            f"Generated from docs/experiments/data/{key}.json: garden {size:g} m, "
            f"seeds {seeds[0]} to {seeds[-1]}, budget {meta.get('budget_s', 0):.0f} s of robot "
            f"time per run, {len(rows)} runs"
            + (f", **{failed} failed** (left out of every figure)" if failed else ", none failed")
            + (f"; overrides: {', '.join(meta['extra'])}" if meta.get("extra") else "")
            + ".",
            "",
            f"| arm | terrain share | coverage at the end | distance (m) | {TO_95_HEAD} |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for d in summarise_exploration(rows, meta.get("budget_s")):
            iv = {k: interval_of(d[k]) for k in ("terrain_share", "coverage", "distance_m")}
            lines.append(
                f"| {_arm_name(d['arm'])} | {iv['terrain_share'].format(100, unit=' %')} | "
                f"{iv['coverage'].format(100, unit=' %')} | {iv['distance_m'].format()} | "
                f"{to_95_cells(d)} |"
            )
        lines.append("")
    lines += [TO_95_NOTE, ""]
    return "\n".join(lines)


def fleet_section(all_data: dict[str, dict]) -> str:
    """Per fleet data file, world and fleet size: time and distance to 95 % as times to an event
    (runs that did not reach it censored at the budget, FAILED runs counted as not reached),
    the log-rank test against one robot, and intervals over seeds of coverage, overlap and the
    merged map's scores."""
    from .exploration_report import TO_95_NOTE
    from .fleet import measured
    from .fleet_report import budgets_of, summarise_fleet, summary_table

    keys = [k for k, d in all_data.items() if d["experiment"] == "fleet"]
    if not keys:
        return _missing("fleet")
    lines = []
    for key in keys:
        rows = [{**r, "ok": bool(r.get("ok"))} for r in all_data[key]["rows"]]
        budgets = budgets_of(all_data[key].get("meta") or {})
        seeds = sorted({r["seed"] for r in rows})
        lines += [
            f"Generated from docs/experiments/data/{key}.json (seeds {seeds[0]} to {seeds[-1]}, "
            f"{len(rows)} runs, {sum(not measured(r) for r in rows)} missing; budget "
            + ", ".join(f"{b:.0f} s in {w}" for w, b in budgets.items())
            + "):",
            "",
            *summary_table(summarise_fleet(rows, budgets)),
            "",
        ]
    lines += [
        TO_95_NOTE + " A run that `smana up` ended FAILED on what its robots did (a member that "
        "did not move) counts as not reached; the distance is every member's, added; the "
        "log-rank test of N robots against one is two-sided, with the side the data lean to.",
        "",
    ]
    return "\n".join(lines)


def resources_section(data: dict | None) -> str:
    if data is None:
        return _missing("resources")
    from .resources import table

    meta = data["meta"]
    head = (
        f"Generated from docs/experiments/data/resources.json (`{meta.get('command', '?')}`: "
        f"{meta.get('data', '?')}; {meta.get('duration_s', '?')} s on {meta.get('cpus', '?')} "
        "cpus):"
    )
    return "\n".join([head, "", *table(data["rows"])]) + "\n"


def navnoise_section(data: dict | None) -> str:
    from .navnoise import section

    return section(data)


def risk_section(data: dict | None) -> str:
    from .riskloop import section

    return section(data)


def robustness_section(data: dict | None, key: str = "robustness") -> str:
    from .robustness_report import section

    return section(data, key)


def noise_section(data: dict | None, key: str = "noise") -> str:
    from .noise_report import section

    return section(data, key)


def ablation_section(data: dict | None) -> str:
    from .ablation import section

    return section(data)


def sections(all_data: dict[str, dict]) -> dict[str, str]:
    """{section name: its generated text}: the fixed sections, and one per noise data file."""
    made = {
        "routes_wheel": routes_section(all_data.get("routes_wheel"), "routes_wheel"),
        "verdicts": verdicts_section(all_data),
        "power": power_section(all_data),
        "noise": noise_section(all_data.get("noise")),
        "routes": routes_section(all_data.get("routes")),
        "exploration": exploration_section(all_data),
        "ablation": ablation_section(all_data.get("ablation")),
        "fleet": fleet_section(all_data),
        "resources": resources_section(all_data.get("resources")),
        "navnoise": navnoise_section(all_data.get("navnoise")),
        "risk": risk_section(all_data.get("risk")),
        "robustness": robustness_section(all_data.get("robustness")),
    }
    for key, data in all_data.items():
        if data["experiment"] == "noise":
            made[key] = noise_section(data, key)
        elif data["experiment"] == "robustness" and key != "robustness":
            made[key] = robustness_section(data, key)  # a confirmation on other seeds, ...
    return made


def regenerate(doc_text: str, all_data: dict[str, dict]) -> tuple[str, list[str]]:
    """(the doc with every generated section rewritten, the names of sections that changed). A
    section the report does not know is an error (a misspelt marker would never be checked), and
    so is a noise data file whose section is not in the doc (its table would be nowhere); a
    `noise_<variant>` section without its data file says so."""
    made = sections(all_data)
    changed: list[str] = []
    seen: set[str] = set()

    def sub(m: re.Match) -> str:
        name = m.group("name")
        if name not in made and NOISE_SECTION.fullmatch(name):
            made[name] = noise_section(None, name)
        if name not in made and ROBUSTNESS_SECTION.fullmatch(name):
            made[name] = robustness_section(None, name)
        if name not in made:
            raise ValueError(f"unknown generated section {name!r}; known: {', '.join(made)}")
        seen.add(name)
        if m.group("body") != made[name]:
            changed.append(name)
        return m.group(1) + made[name] + m.group(4)

    text = SECTION.sub(sub, doc_text)
    own = ("noise", "robustness")  # a variant's data file has its own section
    lost = [k for k, d in all_data.items() if d["experiment"] in own and k not in seen]
    if lost:
        raise ValueError(
            f"no generated section for {', '.join(f'{k}.json' for k in lost)} in the doc "
            f"(add <!-- generated: {lost[0]} --> and <!-- end generated: {lost[0]} -->)"
        )
    return text, changed


# -- command line ---------------------------------------------------------------------------------


def add_parser(sub) -> None:
    r = sub.add_parser(
        "report",
        help="regenerate the tables of docs/experiments.md from docs/experiments/data/ (seconds)",
        description="Rewrite the generated sections of the experiments page from the committed "
        "raw results; --check only compares.",
        epilog="Duration: under a second. Exit status: 0 done (or, with --check, the doc "
        "matches its data), 1 with --check when a section differs, 2 for a bad doc or data, "
        "or data whose rules file changed after its runs (its recorded SHA-256 differs).",
    )
    r.add_argument("--data", type=Path, default=DATA_DIR, help="raw results (default: the repo's)")
    r.add_argument("--doc", type=Path, default=DOC, help="the page (default: the repo's)")
    r.add_argument("--check", action="store_true", help="compare only; exit 1 when it differs")
    r.add_argument(
        "--rules",
        type=Path,
        default=rules.RULES_DIR,
        help="the rules files the data's recorded hashes are checked against (default: the "
        "repo's docs/experiments/rules/)",
    )


def main(args, parser, out: Path | None) -> int:
    try:
        text = args.doc.read_text()
        all_data = load_data(args.data)
        new, changed = regenerate(text, all_data)
    except (OSError, ValueError) as exc:
        print(f"smana experiment report: {exc}", file=sys.stderr)
        return 2
    refused = rules.problems(all_data, args.rules)
    for why in refused:
        print(f"smana experiment report: {args.data}/{why}", file=sys.stderr)
    if refused:
        return 2
    if args.check:
        if changed:
            print(
                f"{args.doc}: generated sections differ from {args.data}: "
                f"{', '.join(changed)} (run `smana experiment report`)"
            )
            return 1
        print(f"{args.doc}: every generated section matches {args.data}")
        return 0
    if changed:
        args.doc.write_text(new)
    names = f": {', '.join(changed)}" if changed else ""
    print(f"{args.doc}: {len(changed)} section(s) rewritten{names}")
    return 0
