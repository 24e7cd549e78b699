"""`smana experiment report`: docs/experiments.md's generated sections are what the committed raw
results in docs/experiments/data/ give, and a hand edit of one is caught."""

from __future__ import annotations

import json

import pytest

from smana.lab import experiments as exp
from smana.lab import stats
from smana.lab.experiments import claims, report
from smana.lab.experiments import exploration_report as exr


def test_the_committed_doc_is_what_the_committed_data_generates(capsys):
    assert exp.cli(["report", "--check"]) == 0, capsys.readouterr().out
    text = report.DOC.read_text()
    names = [m.group("name") for m in report.SECTION.finditer(text)]
    # every section is in the doc, once: the fixed ones and one per noise or robustness data
    # file; besides them only the place of a variant whose data is still to come
    made = report.sections(report.load_data(report.DATA_DIR))
    assert len(names) == len(set(names)) and set(made) <= set(names)
    waiting = set(names) - set(made)
    assert all(report.ROBUSTNESS_SECTION.fullmatch(n) for n in waiting), waiting


def _doc(tmp_path):
    doc = tmp_path / "experiments.md"
    doc.write_text(
        "# page\n\nhand-written\n\n<!-- generated: verdicts -->\nold\n"
        "<!-- end generated: verdicts -->\n\nmore\n\n<!-- generated: routes -->\n"
        "<!-- end generated: routes -->\n"
    )
    return doc


def _exploration_rows():
    rows = []
    for seed in (3, 4, 5):
        for f, share in ((1.0, 0.60), (4.0, 0.88)):
            rows.append(
                {"seed": seed, "arm": f"nbv_x{f:g}", "strategy": "nbv", "grass_cost_factor": f,
                 "path_cost_weight": None, "ok": True, "terrain_share": share + 0.01 * seed,
                 "distance_m": 20.0, "distance_to_95_m": 10.0 + seed, "coverage": 0.99,
                 "time_to_95_s": 30.0, "robot_time_s": 60.0}
            )  # fmt: skip
    return rows


def test_report_rewrites_only_the_generated_sections_from_the_data(tmp_path, capsys):
    doc, data = _doc(tmp_path), tmp_path / "data"
    report.write_data(tmp_path, "routes", [
        {"seed": s, "grass_cost_factor": f, "terrain_share": 0.5 + 0.1 * f + 0.01 * s,
         "curve": [1, 2]} for s in (3, 4, 5) for f in (1.0, 4.0)
    ])  # fmt: skip
    report.write_data(tmp_path, "exploration", _exploration_rows())
    # before the report: the doc does not match its data
    assert exp.cli(["report", "--check", "--doc", str(doc), "--data", str(data)]) == 1
    assert "verdicts, routes" in capsys.readouterr().out
    assert exp.cli(["report", "--doc", str(doc), "--data", str(data)]) == 0
    text = doc.read_text()
    assert text.startswith("# page\n\nhand-written\n") and "\nmore\n" in text
    assert "old" not in text
    # routes: the interval over the seeds of the data file, nothing else
    want = stats.mean_ci([0.6 + 0.01 * s for s in (3, 4, 5)])
    assert f"| x1 | {want.format(100, unit=' %')} |" in text
    # the exploration's claims with their rules and Holm; the missing experiments say so
    assert "| rule | p (one-sided: the alternative it tests) | verdict (Holm-adjusted p, " in text
    assert "exploration: terrain share at grass x1, about the paper's" in text
    assert "Holm-adjusted p" in text
    assert "No raw results of `noise`, `fleet` are committed yet" in text
    assert exp.cli(["report", "--check", "--doc", str(doc), "--data", str(data)]) == 0
    # a hand edit inside a generated section is caught
    doc.write_text(text.replace("| x1 |", "| x1 (edited) |"))
    assert exp.cli(["report", "--check", "--doc", str(doc), "--data", str(data)]) == 1
    assert "routes" in capsys.readouterr().out


def test_no_data_is_said_not_invented(tmp_path):
    doc = _doc(tmp_path)
    assert exp.cli(["report", "--doc", str(doc), "--data", str(tmp_path / "none")]) == 0
    text = doc.read_text()
    assert "No raw results of `smana experiment routes` are committed yet" in text
    assert "No raw results of `noise`, `exploration`, `fleet` are committed yet" in text
    assert "%" not in text.split("<!-- generated: routes -->")[1]


def test_bad_doc_or_data_is_one_line_and_exit_2(tmp_path, capsys):
    doc = tmp_path / "experiments.md"
    doc.write_text("<!-- generated: nope -->\n<!-- end generated: nope -->\n")
    assert exp.cli(["report", "--doc", str(doc), "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown generated section 'nope'" in err
    (tmp_path / "routes.json").write_text(json.dumps({"experiment": "noise", "rows": []}))
    assert exp.cli(["report", "--doc", str(_doc(tmp_path)), "--data", str(tmp_path)]) == 2
    assert "routes.json: not experiment data" in capsys.readouterr().err
    assert exp.cli(["report", "--doc", str(tmp_path / "missing.md")]) == 2


def test_write_data_is_compact_and_round_trips(tmp_path):
    rows = [{"seed": 3, "x": 0.123456789, "curve": {"t": [1.0]}, "per": [1], "ok": True}]
    path = report.write_data(tmp_path, "noise", rows, {"seeds": [3]})
    assert path == tmp_path / "data" / "noise.json"
    data = report.load_data(tmp_path / "data")["noise"]
    assert data["rows"] == [{"seed": 3, "x": 0.123457, "ok": True}]
    assert data["meta"] == {"seeds": [3]}
    assert len(path.read_text().splitlines()) == 3  # the head, one line a row, the end


def test_routes_writes_its_data_file(tmp_path):
    assert exp.cli(["routes", "--seeds", "1", "--factors", "1,4", "--out", str(tmp_path)]) == 0
    rows = report.load_data(tmp_path / "data")["routes"]["rows"]
    assert [(r["seed"], r["grass_cost_factor"]) for r in rows] == [(3, 1.0), (3, 4.0)]
    assert all(0 < r["terrain_share"] <= 1 for r in rows)


def test_noise_data_of_one_sweep_generates_its_claims_and_names_the_missing(tmp_path):
    rows = []
    for seed in (3, 4, 5):
        for backend, loss in (("tsdf", 0.10), ("octree-max", 0.30)):
            for level, ratio in (("none", 0.95), ("high", 0.95 - loss - 0.002 * seed)):
                rows.append(
                    {"seed": seed, "backend": backend, "sweep": "label", "level": level,
                     "classification_ratio": ratio, "error_mean_m": 0.02, "f_score": 0.8}
                )  # fmt: skip
    report.write_data(tmp_path, "noise", rows, {"sweeps": ["label"]})
    table = claims.verdict_claims(report.load_data(tmp_path / "data"))
    assert [c["claim"][:3] for c in table] == ["(a)", "(a)", "(b)"]
    assert all(c["holm_verdict"] == stats.REPRODUCED for c in table)
    text = claims.verdicts_section(report.load_data(tmp_path / "data"))
    assert "no rows for claim (c), (c') (a run of some sweeps only: sweeps label)" in text
    # claims refuted by the data stay refuted after the correction (tsdf losing 40 points)
    far = [{**r, "classification_ratio": r["classification_ratio"] - 0.3}
           if r["backend"] == "tsdf" and r["level"] == "high" else r for r in rows]  # fmt: skip
    report.write_data(tmp_path, "noise", far, {"sweeps": ["label"]})
    table = claims.verdict_claims(report.load_data(tmp_path / "data"))
    assert [c["holm_verdict"] for c in table] == [
        stats.NOT_REPRODUCED,
        stats.REPRODUCED,
        stats.NOT_REPRODUCED,
    ]


def test_variants_and_the_fleet_are_claims_of_their_own(tmp_path):
    """A run in another garden is a data file of its own (`exploration_garden20.json`) whose
    claims name it and are not bounded by the default garden's routes; the fleet's tested claims
    carry their p into the Holm correction, its contact count stays out of it."""
    from smana.lab.experiments import exploration as ex

    assert exr.data_variant(ex.ExplorationExperimentConfig()) is None
    assert exr.data_variant(ex.ExplorationExperimentConfig(size_m=20.0)) == "garden20"
    assert exr.data_variant(ex.ExplorationExperimentConfig.quick()) == "quick"
    laid = ex.ExplorationExperimentConfig(extra=('sim.garden.layout="paths"',))
    assert exr.data_variant(laid) == "garden12paths"
    report.write_data(tmp_path, "exploration", _exploration_rows(), {"size_m": 20.0}, "garden20")
    report.write_data(tmp_path, "routes", [
        {"seed": s, "grass_cost_factor": 1.0, "terrain_share": 0.95} for s in (3, 4, 5)
    ])  # fmt: skip
    fleet = []
    for seed in (3, 4, 5, 6, 7, 8):
        for n, t in ((1, 300.0), (2, 150.0 + seed)):
            fleet.append(
                {"seed": seed, "world": "garden22", "n_robots": n, "ok": True,
                 "time_to_95_s": t, "map_error_m": 0.02, "classification_ratio": 0.9 + 0.001 * seed,
                 "robot_contacts": 0, "size_m": 22.0, "distance_to_95_m": 50.0, "coverage": 0.99,
                 "overlap": 0.4 if n > 1 else None}
            )  # fmt: skip
    meta = {"worlds": [{"name": "garden22", "size_m": 22.0, "budget_s": 700.0}]}
    report.write_data(tmp_path, "fleet", fleet, meta)
    data = report.load_data(tmp_path / "data")
    assert sorted(data) == ["exploration_garden20", "fleet", "routes"]
    table = claims.verdict_claims(data)
    big = [c for c in table if c["experiment"] == "exploration (garden20)"]
    # the default garden's routes (95 % at x1) would make x1 "not reproducible in this world"
    assert big and all(c["verdict"] != stats.NOT_REPRODUCIBLE_HERE for c in big)
    fl = [c for c in table if c["experiment"] == "fleet"]
    ratio = next(c for c in fl if "time to 95 %" in c["claim"])
    assert ratio["verdict"] == "met" and ratio["p"] == 1 / 64
    assert ratio["rule"] == "at most T, sign test" and ratio["need"]["seeds"] == 6
    contacts = next(c for c in fl if "contacts" in c["claim"])
    assert contacts["p"] is None and contacts["holm"] == "a count, not a test"
    text = report.exploration_section(data)
    assert "docs/experiments/data/exploration_garden20.json: garden ? m" not in text
    assert "| NBV, grass x1 | " in text and "| NBV, grass x4 | " in text
    section = report.fleet_section(data)
    assert (
        "| garden22 | 2 | 6 (0; 0) | 6 of 6 |" in section and "budget 700 s in garden22" in section
    )
    # Kaplan-Meier median of 153.0 to 158.0 s (the first at or below half: the 3rd), the
    # restricted mean their plain mean: every run reached it
    assert "| 155 [153, 158] (n = 6) | 156 [" in section
    assert "p = 0.00051, two-sided; the data lean to 2 robots sooner" in section
    n_tested = sum(c["p"] is not None for c in table)
    verdicts = claims.verdicts_section(data)
    assert f"Holm over the {n_tested} tested" in verdicts
    # every p printed says the side it tests
    assert "| 0.016 (one-sided: at most 0.6 x one robot's) | met (Holm-adjusted p = " in verdicts
    tested = [
        ln for ln in verdicts.splitlines() if ln.startswith("| exploration") or "fleet: g" in ln
    ]
    assert tested and all("(one-sided: " in ln for ln in tested)
    # the seeds each claim needs at 80 % power, with what they were computed from
    power = claims.power_section(data)
    assert power.startswith(f"Generated from docs/experiments/data/ ({n_tested} tested claims;")
    row = next(ln for ln in power.splitlines() if "time to 95 %" in ln)
    assert row.endswith(
        "| 6 | 6 of 6 ordered pairs one way, 6 of 6 pairs ordered | exact sign test | 6 |"
    )
    share = next(ln for ln in power.splitlines() if "terrain share at grass x1" in ln)
    assert " points from the rule's edge, SD " in share and "(d = " in share
    bad = tmp_path / "data" / "fleet_x.json"
    bad.write_text('{"experiment": "noise", "rows": []}')
    try:
        report.load_data(tmp_path / "data")
    except ValueError as exc:
        assert "fleet_x.json: not experiment data" in str(exc)
    else:
        raise AssertionError("a fleet variant holding another experiment's data was accepted")


def _noise_rows(seeds=(3, 4, 5), backends=("octree-max", "tsdf@min_weight=0.0001"), label=True):
    """Synthetic noise rows: the label sweep at none (always: the pose sweep's "none") and high,
    the pose sweep at high; each value moves with the seed so that intervals have a width."""
    rows = []
    for seed in seeds:
        for k, b in enumerate(backends):
            for sweep, level in [("label", "none"), *([("label", "high")] * label),
                                 ("pose", "high")]:  # fmt: skip
                noisy = level == "high"
                rows.append(
                    {"seed": seed, "backend": b, "sweep": sweep, "level": level,
                     "error_mean_m": 0.02 + 0.001 * seed + (0.03 + 0.01 * k) * (sweep == "pose"
                                                                                 and noisy),
                     "precision": 0.99 - 0.3 * (sweep == "pose" and noisy),
                     "completeness": 0.25 + 0.01 * seed - 0.02 * k,
                     "f_score": 0.4 + 0.01 * seed - 0.05 * (sweep == "pose" and noisy),
                     "classification_ratio": 0.99 - (0.3 - 0.2 * k + 0.001 * seed)
                     * (sweep == "label" and noisy)}
                )  # fmt: skip
    return rows


def test_noise_section_is_the_data_per_sweep_back_end_and_level():
    from smana.lab.experiments import noise_report as noise

    rows = _noise_rows()
    meta = {"command": "smana experiment noise --sweeps label,pose", "wall_s": 491.0,
            "jobs": 2, "date": "2026-12-03"}  # fmt: skip
    text = noise.section({"experiment": "noise", "meta": meta, "rows": rows}, "noise_x")
    assert text.startswith(
        "Generated from docs/experiments/data/noise_x.json, made by `smana experiment noise "
        "--sweeps label,pose` (8 min 11 s wall with 2 jobs, 2026-12-03): seeds 3, 4, 5; "
        "back-ends octree-max, tsdf@min_weight=0.0001 (octree-bayes, tsdf not run: not in this "
        "data)."
    )
    lines = text.splitlines()
    assert "Label noise sweep, levels none, high:" in lines
    assert "Localisation (pose) noise sweep, levels none, high:" in lines

    def ci(values, scale=100.0, unit=" %"):
        return stats.mean_ci(values).format(scale, ".1f", unit)

    # a cell is the interval over seeds of that back-end, sweep and level; the pose sweep's
    # "none" row is the label sweep's noise-free map
    none = [0.02 + 0.001 * s for s in (3, 4, 5)]
    pose_none = f"| octree-max | none | {ci(none, 1000.0, '')} | 99.0 % [99.0, 99.0] (n = 3) |"
    assert sum(ln.startswith(pose_none) for ln in lines) == 2  # once per sweep
    high = [e + 0.04 for e in none]
    assert f"| tsdf@min_weight=0.0001 | high | {ci(high, 1000.0, '')} | 69.0 %" in text
    # the paired table: what the highest level adds (error) or loses (shares), per seed
    pose_head = lines.index("Localisation (pose) noise sweep, levels none, high:")
    paired = [ln for ln in lines[pose_head:] if ln.startswith("| tsdf@")][-1]
    assert paired.startswith(f"| tsdf@min_weight=0.0001 | {ci([0.04] * 3, 1000.0, '')} | ")
    assert f"| {ci([0.05] * 3, unit='')} |" in paired  # the F-score lost, in points
    label_lost = [0.3 + 0.001 * s for s in (3, 4, 5)]
    assert f"| octree-max | {ci(label_lost, unit='')} |" in lines[:pose_head]
    # a metric no seed changed is left out of the paired table, and said so: label noise moves
    # no point; this pose noise changes no completeness and no label
    assert "left out: error, precision, completeness, F-score:" in lines[pose_head - 7]
    assert (
        "| back-end | error added by high (mm) | precision (5 cm) lost to high | F-score " in text
    )
    assert lines[-1].startswith("| tsdf@") and "left out: completeness, classification" in text
    # a pose sweep alone (its "none" is a label row): no label table of one level
    alone = noise.section({"experiment": "noise", "meta": {}, "rows": _noise_rows(label=False)})
    assert "Label noise sweep" not in alone and "pose) noise sweep, levels none, high" in alone
    assert "made by a command it does not record" in alone
    # older rows without a metric: no number is invented
    old = [{k: v for k, v in r.items() if k != "f_score"} for r in rows]
    text = noise.section({"experiment": "noise", "meta": {}, "rows": old})
    assert "- (n = 0)" in text and "F-score (5 cm) lost to high |" in text
    assert "left out: error, precision, completeness:" in text  # not "unchanged": not measured


def _noise_doc(tmp_path, *names):
    doc = tmp_path / "experiments.md"
    doc.write_text(
        "# page\n\n<!-- generated: verdicts -->\n<!-- end generated: verdicts -->\n"
        + "".join(f"\n{n}:\n<!-- generated: {n} -->\n<!-- end generated: {n} -->\n" for n in names)
    )
    return doc


def test_noise_data_files_each_fill_their_section_and_a_hand_edit_is_caught(tmp_path, capsys):
    data = tmp_path / "data"
    report.write_data(tmp_path, "noise", _noise_rows(backends=("octree-max", "tsdf")))
    report.write_data(tmp_path, "noise", _noise_rows(seeds=(8, 9)), {}, "heldout")
    doc = _noise_doc(tmp_path, "noise", "noise_heldout", "noise_spacing1")
    args = ["--doc", str(doc), "--data", str(data)]
    assert exp.cli(["report", *args]) == 0
    text = doc.read_text()
    held = text.split("<!-- generated: noise_heldout -->\n")[1].split("<!-- end generated")[0]
    assert held.startswith("Generated from docs/experiments/data/noise_heldout.json")
    assert "seeds 8, 9;" in held and "seeds 3, 4, 5" not in held
    assert "data/noise_spacing1.json: nothing is generated here" in text  # no file, no number
    assert exp.cli(["report", "--check", *args]) == 0
    # a number changed by hand in a generated noise table: --check fails and names the section
    cell = held.splitlines()[6]
    assert cell.startswith("| octree-max | none | ")
    doc.write_text(text.replace(cell, cell.replace("| none |", "| none | 1.0 |"), 1))
    capsys.readouterr()
    assert exp.cli(["report", "--check", *args]) == 1
    assert "noise_heldout (run `smana experiment report`)" in capsys.readouterr().out
    # the paper's claims come from noise.json alone: a variant (here seeds 8 and 9 of both
    # sweeps) is an ablation, it adds no claim to the table and no test to Holm's correction
    alone = claims.verdict_claims({"noise": report.load_data(data)["noise"]})
    assert len(claims.verdict_claims(report.load_data(data))) == len(alone) == 5
    # a noise data file with no section in the doc: its table would be nowhere
    report.write_data(tmp_path, "noise", _noise_rows(), {}, "spacing2")
    assert exp.cli(["report", "--check", *args]) == 2
    assert "no generated section for noise_spacing2.json" in capsys.readouterr().err


def test_write_data_records_the_command_that_made_it(tmp_path):
    token = report.COMMAND.set("smana experiment routes --seeds 1")
    try:
        report.write_data(tmp_path, "routes", [{"seed": 3}])
        report.write_data(tmp_path, "noise", [{"seed": 3}], {"command": "given"})
    finally:
        report.COMMAND.reset(token)
    data = report.load_data(tmp_path / "data")
    assert data["routes"]["meta"]["command"] == "smana experiment routes --seeds 1"
    assert data["routes"]["meta"]["date"][:2] == "20"
    assert data["noise"]["meta"]["command"] == "given"  # an experiment's own is kept
    report.write_data(tmp_path, "routes", [{"seed": 3}])  # outside `smana experiment`
    assert report.load_data(tmp_path / "data")["routes"]["meta"] == {}


def test_a_data_file_records_no_path_of_this_machine():
    """The command a data file records keeps --out and --python as placeholders."""
    from smana.lab.experiments import recorded

    words = ["robustness", "--jobs", "2", "--out", "/work/x", "--python=/v/bin/python", "a b"]
    assert recorded(words) == "robustness --jobs 2 --out <out> --python=<python> 'a b'"
    assert recorded(["fleet", "--out"]) == "fleet --out"


def test_the_page_counts_its_verdicts_at_the_top():
    from smana.lab.experiments.claims import verdict_counts

    table = [{"holm_verdict": v} for v in ("inconclusive", "reproduced", "not met (2 of 10)")]
    table += [{"holm_verdict": "inconclusive"}, {"holm_verdict": "odd"}]
    assert verdict_counts(table) == "1 reproduced, 2 inconclusive, 1 not met, 1 odd"
    doc = report.DOC.read_text().splitlines()
    top = next(ln for ln in doc if ln.startswith("Generated from docs"))
    assert " reproduced, " in top and top.endswith(".")


def test_data_records_its_rules_file_and_the_report_refuses_it_once_they_change(tmp_path, capsys):
    """`smana experiment` records the SHA-256 of docs/experiments/rules/<name>.toml in the data it
    writes; the report refuses data whose rules file changed since, and takes data with none."""
    from smana.lab.experiments import rules

    rules_dir = tmp_path / "rules"
    rules_dir.mkdir()
    (rules_dir / "routes.toml").write_text('experiment = "routes"\n')
    token = report.COMMAND.set("smana experiment routes")
    try:
        old = rules.RULES_DIR
        rules.RULES_DIR = rules_dir
        report.write_data(tmp_path / "out", "routes", [{"seed": 3}])
    finally:
        rules.RULES_DIR = old
        report.COMMAND.reset(token)
    data = report.load_data(tmp_path / "out" / "data")
    fixed = data["routes"]["meta"]["rules"]
    assert fixed["file"] == "docs/experiments/rules/routes.toml" and len(fixed["sha256"]) == 64
    assert rules.problems(data, rules_dir) == []
    assert "decided under `docs/experiments/rules/routes.toml`" in rules.line(data["routes"])
    # the committed robustness rules are a TOML file the report can hash
    assert rules.stamp("robustness")["sha256"] == rules.digest(rules.rules_file("robustness"))

    # the report refuses it: a committed data file given the stamp, its rules then changed
    committed = json.loads((report.DATA_DIR / "routes.json").read_text())
    committed["meta"]["rules"] = fixed
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    (data_dir / "routes.json").write_text(json.dumps(committed))
    doc = tmp_path / "doc.md"
    doc.write_text("# x\n")
    args = ["report", "--data", str(data_dir), "--doc", str(doc), "--rules", str(rules_dir)]
    assert exp.cli(args) == 0
    (rules_dir / "routes.toml").write_text('experiment = "routes"\nmargin = 2\n')  # changed
    assert exp.cli(args) == 2
    err = capsys.readouterr().err
    assert "routes.json was decided under docs/experiments/rules/routes.toml" in err
    assert "its rules changed after the runs" in err
    (rules_dir / "routes.toml").unlink()  # gone
    assert exp.cli(args) == 2
    assert "which is gone" in capsys.readouterr().err
    # data made before rules files records none, and passes
    assert rules.problems({"noise": {"meta": {}}}, rules_dir) == []
    assert "records no rules file" in rules.line({"meta": {}})


def test_a_confirmation_of_the_robustness_rules_is_a_data_file_with_its_own_section(tmp_path):
    """`robustness_<variant>.json` (a run on other seeds) gets its own generated section and its
    own rows of verdicts; the doc must have a place for it."""
    data = tmp_path / "data"
    data.mkdir()
    committed = (report.DATA_DIR / "robustness.json").read_text()
    (data / "robustness.json").write_text(committed)
    (data / "robustness_confirm.json").write_text(committed)
    all_data = report.load_data(data)
    doc = "".join(
        f"<!-- generated: {k} -->\nold\n<!-- end generated: {k} -->\n"
        for k in ("verdicts", "robustness", "robustness_confirm")
    )
    text, changed = report.regenerate(doc, all_data)
    assert "Generated from docs/experiments/data/robustness_confirm.json" in text
    assert "| robustness (confirm): octree-max at high label noise" in text
    assert set(changed) == {"verdicts", "robustness", "robustness_confirm"}
    with pytest.raises(ValueError, match="robustness_confirm.json"):
        report.regenerate(doc.split("<!-- generated: robustness_confirm")[0], all_data)
    # a place for a confirmation not committed yet says so
    text, _ = report.regenerate(
        "<!-- generated: robustness_later -->\n<!-- end generated: robustness_later -->\n", {}
    )
    assert "docs/experiments/data/robustness_later.json" in text
