"""`smana bench planner --quick` runs and its A* costs agree with scipy's Dijkstra."""

from smana.lab.bench.planner import cli


def test_quick_bench_agrees_with_dijkstra(capsys):
    assert cli(["--quick", "--queries", "4"]) == 0
    out = capsys.readouterr().out
    assert "all A* costs equal the Dijkstra optimum" in out
