"""`smana bench pipeline`: the quick run goes through the whole chain and prints every row (no
timing asserted: the machine is shared, so scans overtaken under load fail the bench, not the
test); the per-scan bookkeeping on made-up arrivals."""

from __future__ import annotations

import argparse
import re

import pytest

from smana.lab.bench import pipeline as bench


def made_up_result() -> dict:
    # scan 1 primes; scan 3's delta changed no node (no patch); patch 3 answered with patch 4
    per_scan = [[1, 0, "a", 0.0, 100, 50.0], [2, 1, "b", 0.1, 100, 20.0]]
    per_scan += [[3, 2, "c", 0.2, 100, 25.0], [4, 3, "d", 0.3, 100, 30.0]]
    return {
        "summary": {
            "per_scan": per_scan,
            "published": 4,
            "acknowledged": 4,
            "overtaken": 0,
            "unacknowledged": 0,
            "late_published": 0,
            "late_integrated": 0,
            "lost": 0,
            "recorded_rate_hz": 10.0,
        },
        "deltas": {1: (0.0, 10.0), 2: (0.1, 10.1), 3: (0.2, 10.2), 4: (0.3, 10.3)},
        "patches": {1: (0.0, 10.01), 2: (0.1, 10.105), 3: (0.3, 10.31)},
        "answered": {1: 10.02, 2: 10.11, 3: 10.33},
        "replies": [{"ok": True, "planner_ms": 1.0, "wall_ms": 2.0}],
        "status": {s: {"dropped": {}, "rejected": {}} for s in bench.SERVICES},
        "cpu_s": {"replay": 0.3, "mapper": 0.2, "navgraph": 0.1, "planner": 0.1},
        "wall_s": 0.3,
        "pins": {"mapper": [0]},
        "points_in_scan": 100,
        "load_end": 1.0,
    }


def test_stages_are_matched_per_scan():
    stages = bench.per_scan_ms(made_up_result())
    assert stages["map"] == {1: 50.0, 2: 20.0, 3: 25.0, 4: 30.0}
    assert stages["graph"] == pytest.approx({1: 10.0, 2: 5.0, 4: 10.0})
    assert stages["path"] == pytest.approx({1: 10.0, 2: 5.0, 4: 20.0})
    assert stages["e2e"] == pytest.approx({1: 70.0, 2: 30.0, 4: 60.0})


def test_report_fails_on_drops():
    args = argparse.Namespace(backend="octree-max", res=(0.1, 0.2))
    result = made_up_result()
    text, failures = bench.report(result, args, (0.2, 0.2, 0.2))
    assert (
        failures == []
        and "| p99 ms |" in text
        and "p99 <= 30 ms" in text
        and "| mapper | 0.20 |" in text
    )
    result["summary"] |= {"lost": 1, "overtaken": 1, "acknowledged": 3}
    result["status"]["planner"] = {"dropped": {"queue_full": 2}, "rejected": {}}
    _, failures = bench.report(result, args, (0.2, 0.2, 0.2))
    assert len(failures) == 3


def test_pins_keep_the_replay_off_the_chain():
    cores = len(bench.os.sched_getaffinity(0))
    for how in ("auto", "chain", "mapper"):
        plan = bench.pin_plan(how)
        if cores >= 2:
            assert plan["mapper"].isdisjoint(plan["replay"])
    assert bench.pin_plan("none") == {}


# What a busy machine may cost the quick run: the mapper overtaken by newer scans (counted stale).
LOAD_FAILURES = re.compile(
    r"\d+ scans dropped or lost|only \d+ of 20 scans integrated"
    r"|mapper dropped \{'stale': \d+\} rejected \{\}"
)


@pytest.mark.multiprocess
@pytest.mark.slow
def test_quick_bench_runs_the_chain(tmp_path, capsys):
    rc = bench.cli(["--quick", "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    for row in (
        "| scan published -> MapDelta (mapper) |",
        "| MapDelta -> GraphPatch (navgraph) |",
        "| GraphPatch -> path on it (planner) |",
        "| scan published -> updated path (end to end) |",
        "| replay |",
        "| mapper |",
        "| navgraph |",
        "| planner |",
        "load average",
    ):
        assert row in out, row
    assert (tmp_path / "pipeline_bench.json").is_file()
    # Every scan ends in exactly one of the books: integrated, overtaken or unacknowledged.
    books = re.search(
        r"Drops: 20 scans published, (\d+) integrated by the mapper \(\d+ MapDeltas seen "
        r"here\), (\d+) overtaken \(stale at the mapper\), (\d+) unacknowledged",
        out,
    )
    assert books, out
    integrated, overtaken, unacknowledged = map(int, books.groups())
    assert integrated + overtaken + unacknowledged == 20, books.group(0)
    if rc == 0:
        assert integrated == 20 and "FAILED" not in err
        return
    # On a shared machine the chain may fall behind 10 Hz: the bench must then say so (exit 1,
    # the verdict NOT met, a FAILED line), and nothing but the timing may have failed.
    assert rc == 1 and "NOT met" in out and overtaken > 0, (rc, out, err)
    failed = err.split("FAILED: ", 1)[1].strip().split("; ")
    assert all(LOAD_FAILURES.fullmatch(f) for f in failed), failed
