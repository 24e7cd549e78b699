"""`smana experiment report`: the tables of docs/experiments.md, regenerated from the raw results
committed beside it (docs/experiments/data/), so that a figure in the docs is one the data gives.

Every experiment writes its compact raw results, one row per seed and arm (back-end, noise level,
fleet size), into `<out>/data/<name>.json` (`write_data`); copying that file into
docs/experiments/data/ publishes it. The report then rewrites each generated section of the doc,
the text between

    <!-- generated: NAME -->
    <!-- end generated: NAME -->

from the data alone: `verdicts` (every claim of every experiment with data, by the rules of
lab/stats.py, Holm-corrected together), `routes`. An experiment with no committed data says so
in its section instead of a number. `--check` changes nothing and exits 1 when the doc differs
from what the data generates (tests/test_experiment_report.py runs it on the committed doc).

    smana experiment report [--data DIR] [--doc FILE] [--check]
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

from smana.lab import stats

ROOT = Path(__file__).resolve().parents[2]
DATA_DIR = ROOT / "docs" / "experiments" / "data"
DOC = ROOT / "docs" / "experiments.md"
# the data files a report reads
EXPERIMENTS = ("noise", "exploration", "fleet", "routes", "navnoise")
SECTION = re.compile(
    r"(<!-- generated: (?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- end generated: (?P=name) -->)",
    re.S,
)
NO_OUTPUT = True  # `smana experiment` makes no output directory for this one


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


def write_data(out: Path, name: str, rows: list[dict], meta: dict | None = None) -> Path:
    """`<out>/data/<name>.json`: {"experiment", "meta", "rows"}, one row a line so that a diff
    of two runs reads row by row."""
    path = Path(out) / "data" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    body = ",\n".join("  " + json.dumps(r, sort_keys=True) for r in compact_rows(rows))
    head = json.dumps({"experiment": name, "meta": meta or {}}, sort_keys=True, default=str)
    path.write_text(head[:-1] + ', "rows": [\n' + body + "\n]}\n")
    return path


def load_data(data_dir: Path) -> dict[str, dict]:
    """{experiment: its data} for every committed data file; a file that is not valid data is a
    one-line ValueError naming it."""
    out = {}
    for name in EXPERIMENTS:
        path = Path(data_dir) / f"{name}.json"
        if not path.is_file():
            continue
        try:
            data = json.loads(path.read_text())
            if data.get("experiment") != name or not isinstance(data.get("rows"), list):
                raise ValueError(f"expected experiment {name!r} and a list of rows")
        except ValueError as exc:
            raise ValueError(f"{path}: not experiment data ({exc})") from None
        out[name] = data
    return out


# -- the sections ---------------------------------------------------------------------------------


def _missing(name: str) -> str:
    return (
        f"_No raw results of `smana experiment {name}` are committed yet "
        f"(docs/experiments/data/{name}.json): nothing is generated here; the hand-written "
        "tables of this section are transcribed, not yet regenerated._\n"
    )


def _routes_intervals(data: dict) -> dict[float, stats.Interval]:
    by: dict[float, list] = {}
    for r in data["rows"]:
        by.setdefault(float(r["grass_cost_factor"]), []).append(r["terrain_share"])
    return {f: stats.mean_ci(v) for f, v in sorted(by.items())}


def routes_section(data: dict | None) -> str:
    if data is None:
        return _missing("routes")
    seeds = sorted({r["seed"] for r in data["rows"]})
    lines = [
        f"Generated from docs/experiments/data/routes.json (seeds {seeds[0]} to {seeds[-1]}):",
        "",
        "| grass cost | routes between random places, terrain share |",
        "|---|---|",
    ]
    for f, ci in _routes_intervals(data).items():
        lines.append(f"| x{f:g} | {ci.format(100, unit=' %')} |")
    return "\n".join(lines) + "\n"


def _noise_claims(data: dict) -> list[dict]:
    from .noise import claims

    out = []
    for c in claims(data["rows"]):
        if c["smana"].n == 0:  # a run without that sweep: the claim is not in this data
            continue
        txt = c["smana"].format(c["scale"], ".1f", c["unit"])
        out.append({**c, "smana": txt, "experiment": "noise"})
    return out


def _exploration_claims(data: dict, routes: dict | None) -> list[dict]:
    from .exploration import verdicts

    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    return [{**v, "experiment": "exploration"} for v in verdicts(rows, routes)]


def _navnoise_claims(data: dict) -> list[dict]:
    from .navnoise import verdicts

    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    return [{**v, "experiment": "navnoise"} for v in verdicts(rows)]


def verdict_claims(all_data: dict[str, dict]) -> list[dict]:
    """Every claim the committed data decides, Holm-corrected together over the table."""
    routes = _routes_intervals(all_data["routes"]) if "routes" in all_data else None
    table = []
    if "noise" in all_data:
        table += _noise_claims(all_data["noise"])
    if "exploration" in all_data:
        table += _exploration_claims(all_data["exploration"], routes)
    if "navnoise" in all_data:
        table += _navnoise_claims(all_data["navnoise"])
    # each claim's p is that of the conclusion it reached (Decision.p): the one Holm corrects
    decisions = [stats.Decision(c["verdict"], c["p"], c["p"]) for c in table]
    for c, d in zip(table, stats.holm_table(decisions), strict=True):
        c["holm_verdict"] = d.verdict
        c["holm"] = d.evidence
    return table


def verdicts_section(all_data: dict[str, dict]) -> str:
    table = verdict_claims(all_data)
    missing = [n for n in ("noise", "exploration", "fleet") if n not in all_data]
    lines = []
    if table:
        lines += [
            f"Generated from docs/experiments/data/ ({len(table)} claims, Holm over all of them):",
            "",
            "| claim | paper | smana, mean [95 % CI] (n) | rule | p | verdict (Holm) |",
            "|---|---|---|---|---|---|",
        ]
        for c in table:
            ev = f"; {c['evidence']}" if c.get("evidence") else ""
            lines.append(
                f"| {c['experiment']}: {c['claim']} | {c['paper']} | {c['smana']}{ev} | "
                f"{c['rule']} | {c['p']:.2g} | {c['holm_verdict']} ({c['holm']}) |"
            )
        lines.append("")
    if "noise" in all_data:
        have = {c["claim"].split(")")[0] + ")" for c in table if c["experiment"] == "noise"}
        lacking = [k for k in ("(a)", "(b)", "(c)", "(c')") if k not in have]
        if lacking:
            meta = all_data["noise"]["meta"]
            how = (
                meta.get("command")
                or "; ".join(meta.get("commands") or [])
                or f"sweeps {', '.join(meta.get('sweeps') or ['?'])}"
            )
            lines.append(
                f"_The committed noise data has no rows for claim {', '.join(lacking)} "
                f"(a run of some sweeps only: {how})._"
            )
            lines.append("")
    if missing:
        names = ", ".join(f"`{n}`" for n in missing)
        lines.append(
            f"_No raw results of {names} are committed yet (docs/experiments/data/): their "
            "claims are not generated here"
            + (", and the Holm correction above covers only the claims generated" if table else "")
            + ". The table below is transcribed from the runs of those experiments, not yet "
            "regenerated, relabelled by hand with the rules above._"
        )
    return "\n".join(lines) + "\n"


def navnoise_section(data: dict | None) -> str:
    from .navnoise import section

    return section(data)


def sections(all_data: dict[str, dict]) -> dict[str, str]:
    return {
        "verdicts": verdicts_section(all_data),
        "routes": routes_section(all_data.get("routes")),
        "navnoise": navnoise_section(all_data.get("navnoise")),
    }


def regenerate(doc_text: str, all_data: dict[str, dict]) -> tuple[str, list[str]]:
    """(the doc with every generated section rewritten, the names of sections that changed). A
    section the report does not know is an error (a misspelt marker would never be checked)."""
    made = sections(all_data)
    changed: list[str] = []

    def sub(m: re.Match) -> str:
        name = m.group("name")
        if name not in made:
            raise ValueError(f"unknown generated section {name!r}; known: {', '.join(made)}")
        if m.group("body") != made[name]:
            changed.append(name)
        return m.group(1) + made[name] + m.group(4)

    return SECTION.sub(sub, doc_text), changed


# -- command line ---------------------------------------------------------------------------------


def add_parser(sub) -> None:
    r = sub.add_parser(
        "report",
        help="regenerate the tables of docs/experiments.md from docs/experiments/data/ (seconds)",
        description="Rewrite the generated sections of the experiments page from the committed "
        "raw results; --check only compares.",
        epilog="Duration: under a second. Exit status: 0 done (or, with --check, the doc "
        "matches its data), 1 with --check when a section differs, 2 for a bad doc or data.",
    )
    r.add_argument("--data", type=Path, default=DATA_DIR, help="raw results (default: the repo's)")
    r.add_argument("--doc", type=Path, default=DOC, help="the page (default: the repo's)")
    r.add_argument("--check", action="store_true", help="compare only; exit 1 when it differs")


def main(args, parser, out: Path | None) -> int:
    try:
        text = args.doc.read_text()
        new, changed = regenerate(text, load_data(args.data))
    except (OSError, ValueError) as exc:
        print(f"smana experiment report: {exc}", file=sys.stderr)
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
