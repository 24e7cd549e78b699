"""`smana bench planner --quick` runs, prints both sides of every row, and its A* costs agree
with scipy's Dijkstra (and with pyastar2d's when it is installed)."""

import importlib.util
import sys

import pytest

from smana.lab.bench.planner import HINT, cli
from smana.services.planner.planner import RISK_MODES


def test_quick_bench_agrees_with_dijkstra(capsys):
    assert cli(["--quick", "--queries", "4", "--risk"]) == 0
    out = capsys.readouterr().out
    assert "all A* costs equal the Dijkstra optimum" in out
    rows = [line for line in out.splitlines() if "scipy Dijkstra" in line and "->" in line]
    # two sizes, four queries; without risk ("-"): build + first, first on a new Planner,
    # patched, repeat, Euclidean; then on certain risk layers and per risk mode: build + first
    # and first on a new Planner (built just before: its risk enter costs prepared)
    assert len(rows) == 2 * 4 * (5 + 2 * (1 + len(RISK_MODES)))
    assert sum(" cvar " in line for line in rows) == 2 * 4 * 2
    assert sum(" certain " in line for line in rows) == 2 * 4 * 2
    assert out.count("risk / no risk") == 2 * 2 and "window and enter costs alone" in out
    flat = [ln for ln in out.splitlines() if "paper" in ln and "pyastar2d" in ln and "->" in ln]
    if importlib.util.find_spec("pyastar2d") is None:
        assert HINT in out
    else:
        assert len(flat) == 2 * 4 * 3  # new Planner, patched, repeat under the paper's cost
        assert sum("pyastar2d's cost" in ln and "->" in ln for ln in out.splitlines()) == 2 * 4
    assert "load" in out and "cpu" in out and "ratio" in out


def test_without_pyastar2d_a_hint_and_no_flat_rows(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyastar2d", None)  # import raises ImportError
    assert cli(["--quick", "--queries", "1", "--sizes", "40", "--no-euclidean"]) == 0
    out = capsys.readouterr().out
    assert HINT in out and "A*, pyastar2d's cost" not in out
    assert sum("scipy Dijkstra" in ln and "->" in ln for ln in out.splitlines()) == 4


def test_the_spread_over_workload_variants(capsys):
    """Every peer comparison is summarised over the variants run (sizes, obstacle shares, query
    lengths): the median and range of smana / peer, CPU and wall, and the load meanwhile."""
    from smana.lab.bench.planner import spread

    def row(work, peer_ms, smana_ms, load):
        return {
            "work": work,
            "peer": "scipy Dijkstra",
            "peer_ms": peer_ms,
            "smana_ms": smana_ms,
            "load": load,
        }

    results = [
        {"variant": "a", "queries": [{"rows": [row("repeat", (10, 8), (2, 2), 1.0)]}]},
        {"variant": "b", "queries": [{"rows": [row("repeat", (10, 10), (5, 4), 3.0)]}]},
        {"variant": "c", "queries": [{"rows": [row("repeat", (10, 10), (3, 1), 2.0)]}]},
    ]
    (g,) = spread(results)
    assert g["variants"] == 3 and g["queries"] == 3
    assert g["wall"] == (0.3, 0.2, 0.5)
    assert g["cpu"] == (0.25, 0.1, 0.4)
    assert g["load"] == (1.0, 3.0)
    assert (
        cli(
            [
                "--quick",
                "--queries",
                "1",
                "--sizes",
                "40",
                "--no-flat",
                "--no-euclidean",
                "--obstacles",
                "0.05",
                "0.2",
                "--lengths",
                "1",
                "0.5",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert sum("scipy Dijkstra" in ln and "->" in ln for ln in out.splitlines()) == 4 * 4
    assert "4 variants" in out and "median [min, max]" in out


def test_the_risk_rows_per_doubt_share(capsys):
    """`--doubt`: a set of risk rows per share of doubtful free nodes (the mode and the share in
    the risk column, their ratios to the rows without risk), each share of the graph's free nodes
    doubtful as asked."""
    from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE
    from smana.lab.bench.planner_workloads import make_graph, make_risk

    labels, _, flags = make_graph(200, seed=3)
    free = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    for share in (0.05, 0.2, 0.5):
        _, p_label, _ = make_risk(labels, flags, 3, share)
        assert abs((p_label[free] < 255).mean() - share) < 0.01
        assert (p_label[~free] == 255).all()
    argv = ["--quick", "--queries", "1", "--sizes", "40", "--no-flat", "--no-euclidean", "--risk"]
    assert cli([*argv, "--doubt", "0.05", "0.2"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if "scipy Dijkstra" in line and "->" in line]
    for mode in RISK_MODES:
        for share in ("0.05", "0.2"):
            assert sum(f" {mode} {share} " in line for line in rows) == 2
    assert sum(" certain " in line for line in rows) == 2
    assert "expected 0.05 x" in out and "cvar 0.2 x" in out


@pytest.mark.parametrize(
    "bad", [["--lengths", "0"], ["--lengths", "1.5"], ["--obstacles", "x"], ["--doubt", "0"]]
)
def test_a_share_out_of_range_is_one_line_and_exit_2(bad, capsys):
    with pytest.raises(SystemExit) as exc:
        cli(["--quick", *bad])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "expected a number > 0 and <= 1" in err[0]


def test_the_doubtful_share_of_a_real_map(capsys):
    """`--map-doubt`: the wet garden mapped in-process by the TSDF under label noise p = 0.7 has
    doubtful known free nodes (p_label < 255), and the share printed is their count over the
    known free nodes."""
    from smana.lab.bench.planner_workloads import map_doubt

    r = map_doubt(3, 6.0, 160)
    assert r["frames"] > 0 and r["free"] > 0 and 0 < len(r["p_label"]) < r["free"]
    assert (r["p_label"] < 255).all()
    assert cli(["--map-doubt", "3", "--quick"]) == 0
    out = capsys.readouterr().out
    share = len(r["p_label"]) / r["free"]
    assert f"{r['free']} known free nodes, {len(r['p_label'])} doubtful: share {share:.3f}" in out
    assert "P(label) min / quartiles / max" in out
