"""`smana bench explorer` runs and its three implementations of the view gains agree."""

from __future__ import annotations

from smana.lab.bench import explorer as bench


def test_bench_runs_and_agrees(capsys):
    r = bench.run(repeats=1)
    assert r["agree_with_references"]
    assert r["candidates"] > 5 and r["plan_ms"] > 0
    assert bench.cli(["--repeats", "1"]) == 0
    assert "numba kernel" in capsys.readouterr().out
