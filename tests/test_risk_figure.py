"""`smana experiment risk --synthetic --figure PNG` (docs/risk.md, the figure of a map coloured
by risk): the command writes a readable PNG and nothing else, each panel's path title counts the
water entries the experiment's own rows give that path (`seed_rows`, judged by `judge`), and the
P(forbidden) drawn is what the chance constraint closes on."""

from __future__ import annotations

import re

import numpy as np
import pytest

from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE
from smana.common.risk import forbidden_probability, risk_class_costs
from smana.lab.experiments import cli
from smana.lab.experiments import risk as rk
from smana.lab.paper_figures import risk_map_figure

N, PAIRS = 60, 6  # the quick form's map and pairs: a test-sized world


def test_the_command_writes_a_readable_png_and_no_run_directory(tmp_path, monkeypatch, capsys):
    from PIL import Image

    monkeypatch.chdir(tmp_path)
    png = tmp_path / "risk_map.png"
    args = ["risk", "--synthetic", "--figure", str(png), "--nodes", "40", "--pairs", "3"]
    assert cli(args) == 0
    with Image.open(png) as im:
        im.load()
        assert im.format == "PNG" and im.size[0] > 600 and im.size[1] > 400
    assert sorted(p.name for p in tmp_path.iterdir()) == ["risk_map.png"]  # no runs/
    assert "seed 3, 40 x 40 nodes, p = 0.7" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, what",
    [
        (["--synthetic", "--quick"], "--quick: not with --figure"),
        (["--synthetic", "--out", "x"], "--out: not with --figure"),
        (["--synthetic", "--seeds", "3"], "--seeds: not with --figure"),
        ([], "--figure: an option of --synthetic only"),
    ],
    ids=["quick", "out", "seeds", "closed-loop"],
)
def test_figure_is_refused_with_the_options_of_a_run_and_without_synthetic(tmp_path, extra, what):
    from smana.common.cli import UsageError

    with pytest.raises(UsageError, match=what):
        cli(["risk", "--figure", str(tmp_path / "f.png"), *extra])
    assert not list(tmp_path.iterdir())


def test_the_titles_count_the_water_entries_the_experiments_rows_give():
    seed = rk.FIRST_SEED
    case = rk.figure_case(seed, N, PAIRS)
    fig = risk_map_figure(case, seed, rk.RES_M)
    titles = {ax.get_label(): ax.get_title() for ax in fig.axes if ax.get_label() in rk.ARMS}
    assert set(titles) == set(rk.ARMS)
    rows = rk.seed_rows(seed, N, PAIRS, [rk.TARGET_P])
    mine = {r["arm"]: r for r in rows if r["pair"] == case["pair"]}
    counts = {}
    for arm, title in titles.items():
        found = re.search(r"(\d+) water entr(y|ies), ([\d.]+) m", title)
        if not mine[arm]["found"]:
            assert found is None and re.search(r"path[^:\n]*: none found", title), title
            continue
        assert found, title
        counts[arm] = int(found.group(1))
        assert counts[arm] == mine[arm]["forbidden"], (arm, title)
        assert float(found.group(3)) == pytest.approx(mine[arm]["length_m"], abs=0.05)
    # the pair drawn is the one the labels alone plan into water most often (the first on a tie)
    argmax = [r["forbidden"] for r in sorted(rows, key=lambda r: r["pair"]) if r["arm"] == "argmax"]
    assert case["pair"] == int(np.argmax(argmax))
    assert counts["truth"] == 0 and counts["argmax"] > 0  # a figure where the counts mean something
    # the three cost panels: one log scale from 1 (terrain) to risk_forbidden_cost
    for arm in ("expected", "cvar", "chance"):
        ax = next(ax for ax in fig.axes if ax.get_label() == arm)
        norm = ax.get_images()[0].norm
        assert type(norm).__name__ == "LogNorm" and (norm.vmin, norm.vmax) == (1.0, 20.0)


def test_p_forbidden_is_what_the_chance_constraint_closes_on():
    case = rk.figure_case(rk.FIRST_SEED, N, PAIRS)
    w, labels, (alt, p_label, p_alt) = case["world"], case["labels"], case["risk"]
    chance, lut = case["configs"]["chance"], w.classes.cost_lut
    free = (w.flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    enterable = free & np.isfinite(lut[labels])
    pf = forbidden_probability(labels, alt, p_label, p_alt, lut, chance)
    closed = ~np.isfinite(risk_class_costs(labels, alt, p_label, p_alt, lut, chance))
    np.testing.assert_array_equal(closed[enterable], pf[enterable] > chance.max_risk)
    assert 0 < closed[enterable].sum() < enterable.sum()
    assert ((pf >= 0) & (pf <= 1 + 1e-12)).all()
    # a node whose label is water counts its own share; certain nodes are 0 or 1
    water = labels == w.forbidden
    assert (pf[water & free] >= p_label[water & free] / 255 - 1e-12).all()
    certain = p_label == 255
    assert set(np.unique(pf[certain])) <= {0.0, 1.0}


def test_docs_describe_the_figure_the_command_draws():
    """docs/risk.md, "A map coloured by risk": the numbers it quotes are those of the committed
    figure's case (seed 3, 150 x 150 nodes, 20 pairs: the command's defaults)."""
    from pathlib import Path

    doc = " ".join((Path(__file__).parents[1] / "docs" / "risk.md").read_text().split())
    case = rk.figure_case(rk.FIRST_SEED, 150, 20)
    score = {arm: s for arm, (_, s) in case["paths"].items()}
    said = (
        f"On it the labels alone enter water {score['argmax']['forbidden']} times in "
        f"{score['argmax']['length_m']:.1f} m, `expected` none in "
        f"{score['expected']['length_m']:.1f} m, `cvar` twice in "
        f"{score['cvar']['length_m']:.1f} m, "
        "and `chance` finds no path."
    )
    assert said in doc
    assert score["expected"]["forbidden"] == 0 and score["cvar"]["forbidden"] == 2
    assert not score["chance"]["found"] and score["truth"]["forbidden"] == 0
    assert "smana experiment risk --synthetic --figure docs/risk_map.png" in doc
    # "`cvar` prices 46 % of the nodes it may enter at 10 or more", "`chance` closes 43 % of the
    # nodes the other modes may enter"
    w, labels, (alt, p_label, p_alt) = case["world"], case["labels"], case["risk"]
    lut = w.classes.cost_lut
    enterable = ((w.flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0) & np.isfinite(lut[labels])

    def costs(arm):
        return risk_class_costs(labels, alt, p_label, p_alt, lut, case["configs"][arm])[enterable]

    dear = round(100 * np.mean(costs("cvar") >= 10))
    closed = round(100 * np.mean(~np.isfinite(costs("chance"))))
    assert np.isfinite(costs("cvar")).all() and np.isfinite(costs("expected")).all()
    assert f"`cvar` prices {dear} % of the nodes it may enter at 10 or more" in doc
    assert f"`chance` closes {closed} % of the nodes the other modes may enter" in doc
    assert (Path(__file__).parents[1] / "docs" / "risk_map.png").stat().st_size < 300_000
