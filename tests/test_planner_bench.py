"""`smana bench planner --quick` runs, prints both sides of every row, and its A* costs agree
with scipy's Dijkstra (and with pyastar2d's when it is installed)."""

import importlib.util
import sys

from smana.lab.bench.planner import HINT, cli
from smana.services.planner.planner import RISK_MODES


def test_quick_bench_agrees_with_dijkstra(capsys):
    assert cli(["--quick", "--queries", "4", "--risk"]) == 0
    out = capsys.readouterr().out
    assert "all A* costs equal the Dijkstra optimum" in out
    rows = [line for line in out.splitlines() if "scipy Dijkstra" in line]
    # two sizes, four queries: new / patched / repeat / Euclidean, then a new Planner on certain
    # risk layers and per risk mode
    assert len(rows) == 2 * 4 * (4 + 1 + len(RISK_MODES))
    assert sum(" cvar " in line for line in rows) == 2 * 4
    assert sum(" certain " in line for line in rows) == 2 * 4
    assert out.count("risk / no risk") == 2 and "window and enter costs alone" in out
    flat = [line for line in out.splitlines() if "paper " in line and "pyastar2d" in line]
    if importlib.util.find_spec("pyastar2d") is None:
        assert HINT in out
    else:
        assert len(flat) == 2 * 4 * 2  # first and repeat query under the paper's cost
        assert sum("A*, pyastar2d's cost" in line for line in out.splitlines()) == 2 * 4
    assert "load" in out and "cpu" in out and "ratio" in out


def test_without_pyastar2d_a_hint_and_no_flat_rows(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyastar2d", None)  # import raises ImportError
    assert cli(["--quick", "--queries", "1", "--sizes", "40", "--no-euclidean"]) == 0
    out = capsys.readouterr().out
    assert HINT in out and "A*, pyastar2d's cost" not in out
    assert sum("scipy Dijkstra" in line for line in out.splitlines()) == 3
