"""`smana bench navgraph --quick` runs and the graph agrees with the numpy one-shot reference."""

from smana.lab.bench.navgraph import cli


def test_quick_bench_agrees_with_reference(capsys):
    assert cli(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "agrees with the reference node for node: yes" in out
