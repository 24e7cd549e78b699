"""Every claim the experiments make, judged from their data alone (lab/stats.py's rules, Holm-
corrected together): the claims of each experiment with data (`verdict_claims`), the verdicts
section of docs/experiments.md (`verdicts_section`) and the seeds each claim needs
(`power_section`, lab/power.py). report.py writes them into the doc."""

from __future__ import annotations

from smana.lab import power, stats


def routes_intervals(data: dict) -> dict[float, stats.Interval]:
    by: dict[float, list] = {}
    for r in data["rows"]:
        by.setdefault(float(r["grass_cost_factor"]), []).append(r["terrain_share"])
    return {f: stats.mean_ci(v) for f, v in sorted(by.items())}


def layout_routes(all_data: dict[str, dict], exploration: dict) -> dict | None:
    """The routes' intervals of the garden layout an exploration ran in (its `--set
    sim.garden.layout`, in its meta's extra items): `routes_<layout>`, or `routes` by default."""
    from .exploration import layout_of

    layout = layout_of(exploration.get("meta", {}).get("extra", []))
    name = f"routes_{layout}" if layout and layout != "3drms" else "routes"
    return routes_intervals(all_data[name]) if name in all_data else None


def _noise_claims(data: dict) -> list[dict]:
    from .noise_report import claims

    out = []
    for c in claims(data["rows"]):
        if c["smana"].n == 0:  # a run without that sweep: the claim is not in this data
            continue
        txt = c["smana"].format(c["scale"], ".1f", c["unit"])
        out.append({**c, "smana": txt, "experiment": "noise"})
    return out


def _where(key: str, data: dict) -> str:
    """How a claim names the run it comes from: the experiment, and for a variant its garden."""
    name = data["experiment"]
    if key == name:
        return name
    return f"{name} ({key[len(name) + 1 :]})"


def _exploration_claims(key: str, data: dict, all_data: dict[str, dict]) -> list[dict]:
    from .exploration import ExplorationExperimentConfig
    from .exploration_report import verdicts

    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    # the routes are computed in the experiments' 12 m garden, of the layout the run chose: they
    # bound the terrain shares of a run in that garden only
    size = data["meta"].get("size_m", ExplorationExperimentConfig.size_m)
    same = size == ExplorationExperimentConfig.size_m
    world = layout_routes(all_data, data) if same else None
    return [{**v, "experiment": _where(key, data)} for v in verdicts(rows, world)]


def _fleet_claims(key: str, data: dict) -> list[dict]:
    from .fleet_report import budgets_of, verdicts

    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    budgets = budgets_of(data.get("meta") or {})
    return [{**v, "experiment": _where(key, data)} for v in verdicts(rows, budgets=budgets)]


def _navnoise_claims(key: str, data: dict) -> list[dict]:
    from .navnoise import verdicts

    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    return [{**v, "experiment": _where(key, data)} for v in verdicts(rows)]


def _risk_claims(key: str, data: dict) -> list[dict]:
    """The closed loop's verdicts (riskloop.py); a committed synthetic run (`--synthetic`,
    `risk_synthetic.json`) gives its own six (risk.py)."""
    rows = [{**r, "ok": bool(r.get("ok"))} for r in data["rows"]]
    if (data.get("meta") or {}).get("form") != "synthetic":
        from .riskloop import verdicts

        return [{**v, "experiment": _where(key, data)} for v in verdicts(rows)]
    from .risk import TARGET_P, claims

    return [
        {
            "claim": c["claim"],
            "paper": "(issue 29, synthetic maps)",
            "smana": c["interval"].format(fmt=".3f"),
            "verdict": c["verdict"],
            "p": c["p"],
            "p_tests": c.get("p_tests"),
            "need": c.get("need"),
            "rule": f"at p = {TARGET_P}",
            "evidence": "",
            "experiment": _where(key, data),
        }
        for c in claims(rows)
    ]


def verdict_claims(all_data: dict[str, dict]) -> list[dict]:
    """Every claim the committed data decides, Holm-corrected together over the table. A claim
    without a p-value (a count, such as the fleet's contacts) is not a test: it is listed, and
    stays out of the correction."""
    table = []
    for key, data in all_data.items():
        if key == "noise":  # a variant (noise_<variant>.json) is an ablation, with no claims
            table += _noise_claims(data)
        elif data["experiment"] == "exploration":
            table += _exploration_claims(key, data, all_data)
        elif data["experiment"] == "fleet":
            table += _fleet_claims(key, data)
        elif data["experiment"] == "resources":
            from .resources import claims as resources_claims

            table += [
                {**c, "experiment": _where(key, data)} for c in resources_claims(data["rows"])
            ]
        elif data["experiment"] == "navnoise":
            table += _navnoise_claims(key, data)
        elif data["experiment"] == "risk":
            table += _risk_claims(key, data)
        elif data["experiment"] == "robustness":
            from .robustness_report import verdicts as robustness_verdicts

            table += [
                {**v, "experiment": _where(key, data)} for v in robustness_verdicts(data["rows"])
            ]
    tested = [c for c in table if c.get("p") is not None]
    # each claim's p is that of the conclusion it reached (Decision.p): the one Holm corrects
    decisions = [
        stats.Decision(c["verdict"], c["p"], c["p"], yes=c.get("p_tests") or "") for c in tested
    ]
    for c, d in zip(tested, stats.holm_table(decisions), strict=True):
        c["holm_verdict"] = d.verdict
        c["holm"] = d.evidence
    for c in table:
        if c.get("p") is None:
            c["holm_verdict"], c["holm"] = c["verdict"], "a count, not a test"
    return table


ORDER = ("reproduced", "not reproduced", "inconclusive", "untestable", "met", "not met")


def verdict_counts(table: list[dict]) -> str:
    """ "7 reproduced, 5 not reproduced, ...": how many claims got each verdict (the words
    before the parenthesis of the table's last column), in ORDER, others after."""
    counts: dict[str, int] = {}
    for c in table:
        word = c["holm_verdict"].split(" (")[0]
        counts[word] = counts.get(word, 0) + 1
    words = [w for w in ORDER if w in counts] + [w for w in counts if w not in ORDER]
    return ", ".join(f"{counts[w]} {w}" for w in words)


def verdicts_section(all_data: dict[str, dict]) -> str:
    table = verdict_claims(all_data)
    have = {d["experiment"] for d in all_data.values()}
    missing = [n for n in ("noise", "exploration", "fleet") if n not in have]
    lines = []
    if table:
        lines += [
            f"Generated from docs/experiments/data/ ({len(table)} claims, Holm over the "
            f"{sum(c.get('p') is not None for c in table)} tested): {verdict_counts(table)}.",
            "",
            "| claim | paper | smana, mean [95 % CI] (n) | rule | p (one-sided: the alternative "
            "it tests) | verdict (Holm-adjusted p, the same side) |",
            "|---|---|---|---|---|---|",
        ]
        for c in table:
            e = c.get("evidence")
            ev = f"; {e}" if e and e not in c["smana"] else ""
            lines.append(
                f"| {c['experiment']}: {c['claim']} | {c['paper']} | {c['smana']}{ev} | "
                f"{c['rule']} | {stats.format_p(c.get('p'), c.get('p_tests'))} | "
                f"{c['holm_verdict']} ({c['holm']}) |"
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


def _measured(need: dict, c: dict) -> str:
    """What a claim's seeds needed were computed from, in the claim's units."""
    scale, unit = c.get("scale") or 1.0, c.get("unit") or ""
    if need["sd"] is not None:
        d, sd = need["effect"], need["sd"]
        if sd == 0 and d == 0:
            return "every seed on the rule's edge (no spread, no difference)"
        ratio = f"{d / sd:.2f}" if sd > 0 else "inf"
        return (
            f"{d * scale:.3g}{unit} from the rule's edge, SD {sd * scale:.3g}{unit} (d = {ratio})"
        )
    return need["detail"]


def _seeds(need: dict) -> str:
    if need["seeds"] is not None:
        return str(need["seeds"])
    if need["effect"] == 0 or (need["how"].startswith("exact sign") and need["effect"] <= 0.5):
        return "none: no difference measured"
    return f"more than {power.MAX_SEEDS:,}"


def power_section(all_data: dict[str, dict]) -> str:
    """Per tested claim of the verdict table: the seeds its rule needs to reach a verdict with
    80 % power, were the true effect and spread those measured (lab/power.py), beside the seeds
    it has."""
    table = [c for c in verdict_claims(all_data) if c.get("p") is not None]
    if not table:
        return "_No tested claim in the committed data: nothing to compute._\n"
    lines = [
        f"Generated from docs/experiments/data/ ({len(table)} tested claims; 80 % power, each "
        f"test one-sided at {power.ALPHA}, before Holm's correction):",
        "",
        "| claim | rule | verdict (Holm) | seeds now | measured | test | seeds for 80 % power |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in table:
        need = c.get("need")
        if need is None:
            cells = "- | - | - | no interval: nothing to compute"
        else:
            cells = f"{need['n']} | {_measured(need, c)} | {need['how']} | {_seeds(need)}"
        lines.append(
            f"| {c['experiment']}: {c['claim']} | {c['rule']} | {c['holm_verdict']} | {cells} |"
        )
    return "\n".join(lines) + "\n"
