"""The end of a run: the summary table `smana up` prints and `report.md` starts with, made from
`metrics.json`'s values, and the two explored areas told apart."""

from __future__ import annotations

import json

from smana.deploy import report
from tests.test_eval_report import run  # noqa: F401 - the fixture: a small hand-made run


def _metrics(run_dir):
    return json.loads((run_dir / "metrics.json").read_text())


def _table(md: str, heading: str) -> dict[str, str]:
    """The `| figure | value |` rows under `heading` in report.md."""
    block = md.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    rows = [r.strip("|").split(" | ") for r in block.splitlines() if r.startswith("| ")]
    return {a.strip(): b.strip() for a, b in rows[1:]}


def test_summary_in_the_terminal_and_report_md_is_metrics_json(run):  # noqa: F811
    run_dir, cfg, _ = run
    state_path = run_dir / "explorer" / "state.json"
    state = json.loads(state_path.read_text())
    state.update(path_queries=7, path_ok=5, elapsed_s=9.5)
    state_path.write_text(json.dumps(state))
    path = report.write_report(run_dir, cfg, ended="explorer finished", wall_time_s=31.4)
    m = _metrics(run_dir)
    ex, ee = m["exploration"], m["explorer"]
    rows = dict(report.summary_rows(m))
    assert rows["outcome"] == "ok" and not m["warnings"]
    for row, name in (
        ("usable coverage (against ground truth)", "usable"),
        ("false obstacles (free, blocked in the map)", "false_obstacle"),
        ("false free (obstacle, free in the map)", "false_free"),
    ):
        assert rows[row] == (
            f"{ex[f'{name}_area_m2']:.1f} m2 = {100 * ex[f'{name}_share']:.1f} % of the "
            f"reachable {ex['reachable_area_m2']:.1f} m2"
        )
    assert ex["coverage"] == ex["usable_share"]
    assert rows["explored area (explorer's own count)"] == f"{ee['explored_m2']:.1f} m2"
    assert rows["distance travelled"] == f"{ex['distance_m']:.1f} m"
    assert rows["collisions"].startswith(f"{ex['collisions']} ({ex['close_calls']} close calls")
    assert rows["path queries"] == "7 (5 answered with a path)"
    assert rows["duration"] == (
        f"{ex['duration_robot_s']:.0f} s robot time, {m['run']['wall_time_s']:.0f} s wall time"
    )
    assert rows["map"] == f"{m['map_content']['n_points']} occupied voxels"
    assert rows["ended because"] == "no_frontier (explorer finished)"
    assert rows["run directory"] == str(run_dir)

    # report.md: the same table, at the top
    md = path.read_text()
    assert md.split("\n")[2] == "## Summary"
    assert _table(md, "Summary") == rows
    # the terminal: the same rows, under a headline
    lines = report.summary_lines(m)
    assert lines[0] == "smana up: ok"
    width = max(map(len, rows))
    assert lines[1:] == [f"  {a:<{width}}  {b}" for a, b in list(rows.items())[1:]]

    # made from the metrics dict alone: change a value, the summary follows
    m["exploration"]["distance_m"] = 123.456
    m["warnings"] = ["the planner never came up"]
    changed = dict(report.summary_rows(m))
    assert changed["distance travelled"] == "123.5 m" and changed["outcome"] == "FAILED (1 warning)"
    lines = report.summary_lines(m)
    assert lines[0] == "smana up: FAILED" and lines[-1] == "  warning: the planner never came up"


def test_without_the_supervisor_the_wall_time_is_the_explorer_s(run):  # noqa: F811
    run_dir, cfg, _ = run
    report.write_report(run_dir, cfg)  # as `smana replay` or a test writes it
    m = _metrics(run_dir)
    assert m["run"]["wall_time_s"] is None and m["explorer"]["wall_time_s"] == 12.0
    assert dict(report.summary_rows(m))["duration"].endswith(", 12 s wall time")


def test_rewriting_a_report_keeps_how_the_run_ended(run):  # noqa: F811
    run_dir, cfg, _ = run
    report.write_report(run_dir, cfg, ended="--duration 60 s reached", wall_time_s=61.0)
    report.write_report(run_dir, cfg)  # `python -m smana.deploy.report RUN_DIR`
    assert _metrics(run_dir)["run"] == {"ended": "--duration 60 s reached", "wall_time_s": 61.0}


def test_the_report_names_both_explored_areas_and_says_which_is_which(run):  # noqa: F811
    run_dir, cfg, _ = run
    md = report.write_report(run_dir, cfg).read_text()
    m = _metrics(run_dir)
    rows = _table(md, "Exploration")
    truth = [v for k, v in rows.items() if k.startswith("usable coverage: reachable traversable")]
    known = [v for k, v in rows.items() if k.startswith("known (any label)")]
    own = [v for k, v in rows.items() if k.startswith("explored area, the explorer's own count")]
    ex = m["exploration"]
    assert truth == [
        f"{ex['usable_area_m2']:.1f} m2 = {100 * ex['usable_share']:.1f} % of the reachable "
        f"{ex['reachable_area_m2']:.1f} m2"
    ]
    assert known and known[0].startswith(f"{ex['known_reachable_area_m2']:.1f} m2 = ")
    assert own == [f"{m['explorer']['explored_m2']:.1f} m2"]
    assert report.EXPLORED_AREAS in md and "explored_m2" in report.EXPLORED_AREAS


def test_a_replay_summary_has_no_ground_truth_figures(tmp_path):
    from smana.common.config import SmanaConfig

    cfg = SmanaConfig.load(None, ["general.class_table=rellis3d"])
    replay = {"mode": "lockstep", "published": 4, "acknowledged": 4, "scans": 4}
    md = report.write_report(tmp_path, cfg, replay=replay).read_text()
    rows = dict(report.summary_rows(_metrics(tmp_path)))
    assert "usable coverage (against ground truth)" not in rows
    assert rows["scans published / integrated"] == "4 / 4"
    assert _table(md, "Summary") == rows
