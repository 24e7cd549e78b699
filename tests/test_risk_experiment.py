"""`smana experiment risk --synthetic` (issue 29, the first form, on synthetic maps): its noise
model, the judge against the truth, the rules decided on synthetic rows, and the quick form end
to end. The closed loop: tests/test_risk_loop.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, P_SCALE
from smana.lab import stats
from smana.lab.experiments import cli
from smana.lab.experiments import risk as rk
from smana.services.planner.planner import PlanResult


def test_the_world_has_a_flat_forbidden_class_and_noise_only_moves_ground_labels():
    classes, forbidden = rk.risk_classes()
    assert classes.cost_lut[forbidden] == np.inf and not classes.obstacle_lut[forbidden]
    truth, flags = rk.true_world(3, 60, forbidden)
    free = (flags & FLAG_OBSTACLE) == 0
    assert 0.03 < np.mean(truth[free] == forbidden) < 0.2
    assert (flags & FLAG_KNOWN).all()
    ground = [rk.TERRAIN, rk.GRASS, forbidden]
    clean, (alt, p_label, p_alt) = rk.noisy_map(truth, flags, ground, 1.0, np.random.default_rng(0))
    np.testing.assert_array_equal(clean, truth)  # p = 1: every frame right
    assert (p_label.astype(int) + p_alt <= P_SCALE).all()
    assert (p_label[free] < P_SCALE).all() and (p_label[~free] == P_SCALE).all()  # the prior
    noisy, _ = rk.noisy_map(truth, flags, ground, 0.7, np.random.default_rng(0))
    wrong = noisy[free] != truth[free]
    assert 0.02 < wrong.mean() < 0.5
    np.testing.assert_array_equal(noisy[~free], truth[~free])  # obstacles are geometry


def test_the_judge_counts_forbidden_nodes_entered_by_their_true_class():
    classes, forbidden = rk.risk_classes()
    truth = np.full((5, 5), rk.TERRAIN, np.uint16)
    truth[2, 1] = forbidden
    cells = np.array([[2, 0], [2, 1], [2, 2]])
    res = PlanResult(True, cells=cells, cost_distance=0.4)
    got = rk.judge(res, truth, forbidden, classes, rk.PlannerConfig())
    assert got["forbidden"] == 1 and not got["ok"] and got["length_m"] == 0.4
    assert got["true_cost"] == pytest.approx(0.4 + 0.8 * (20 + 1))
    start_only = rk.judge(
        PlanResult(True, cells=cells[1:], cost_distance=0.2), truth, forbidden, classes,
        rk.PlannerConfig(),
    )  # fmt: skip
    assert start_only["forbidden"] == 0  # the start is never entered
    assert not rk.judge(PlanResult(False), truth, forbidden, classes, rk.PlannerConfig())["ok"]


def _rows(entries, success, length, seeds=(3, 4, 5, 6)):
    """Synthetic rows at p = 0.7: per arm its forbidden entries, success and length per path."""
    rows = []
    for s in seeds:
        for arm in rk.ARMS:
            for i in range(4):
                w = 0.01 * ((s + i) % 3)
                rows.append(
                    {"seed": s, "p": 0.7, "arm": arm, "pair": i, "found": True,
                     "forbidden": entries[arm] + (i == s % 4), "ok": i < 4 * success[arm],
                     "length_m": length[arm] + w, "true_cost": 1.0}
                )  # fmt: skip
    return rows


def test_verdicts_follow_the_rules_declared_before_the_run():
    arms = {a: 0 for a in rk.ARMS}
    good = rk.claims(
        _rows(arms | {"expected": 4}, arms | {"expected": 1, "cvar": 1, "chance": 1},
              {a: 10.0 for a in rk.ARMS} | {"cvar": 10.5})
    )  # fmt: skip
    assert [c["verdict"] for c in good] == [stats.REPRODUCED] * 6
    bad = rk.claims(
        _rows(arms | {"expected": 1, "cvar": 1, "chance": 1}, arms | {"expected": 1},
              {a: 10.0 for a in rk.ARMS} | {"cvar": 13.0, "chance": 13.0})
    )  # fmt: skip
    assert [c["verdict"] for c in bad] == [stats.NOT_REPRODUCED] * 6


def test_risk_quick(tmp_path, capsys):
    """The quick form runs end to end: every arm's paths at p 1 and 0.7, the truth never enters
    the forbidden class, the map's labels alone plan as the truth when there is no noise, and six
    verdicts."""
    out = tmp_path / "risk"
    assert cli(["risk", "--synthetic", "--quick", "--out", str(out)]) == 0
    data = json.loads((out / "data" / "risk_synthetic.json").read_text())
    rows = data["rows"]
    assert {r["arm"] for r in rows} == set(rk.ARMS) and {r["p"] for r in rows} == {1.0, 0.7}
    assert len(rows) == 2 * 2 * len(rk.ARMS) * 6
    truth = [r for r in rows if r["arm"] == "truth"]
    assert all(r["ok"] and r["forbidden"] == 0 for r in truth)

    def lengths(arm):
        return {
            (r["seed"], r["pair"]): r["length_m"] for r in rows if r["arm"] == arm and r["p"] == 1
        }

    assert lengths("argmax") == lengths("truth")  # p = 1: the map's labels are the truth's
    claims = json.loads((out / "risk_results.json").read_text())["claims"]
    assert len(claims) == 6 and all(c["verdict"] in stats.VERDICTS for c in claims)
    summary = (out / "risk_summary.md").read_text()
    assert "| 0.7 | chance |" in summary and "Verdicts at p = 0.7" in summary
    assert "Verdicts at p = 0.7" in capsys.readouterr().out


def test_one_seed_is_refused_in_one_line_before_any_output(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli(["risk", "--seeds", "1", "--out", str(tmp_path / "risk")])
    assert exc.value.code == 2 and not (tmp_path / "risk").exists()
    err = capsys.readouterr().err.strip()
    assert "--seeds" in err and "\n" not in err
