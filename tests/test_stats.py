"""lab/stats.py: the interval against a slow obvious reference, and the verdicts' edges."""

import math

import numpy as np
import pytest

from smana.lab import power, stats, survival

# two-sided 95 % Student t quantiles, from tables
T975 = {1: 12.706, 2: 4.303, 4: 2.776, 9: 2.262}


@pytest.mark.parametrize("n", [2, 3, 5, 10])
def test_mean_ci_matches_textbook(n):
    v = np.random.default_rng(n).normal(3.0, 0.5, n)
    mean = sum(v) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in v) / (n - 1))
    h = T975[n - 1] * sd / math.sqrt(n)
    ci = stats.mean_ci(list(v))
    assert ci.n == n
    assert ci.mean == pytest.approx(mean)
    assert ci.half_width == pytest.approx(h, rel=1e-3)  # the tables give 4 digits
    assert (ci.lo + ci.hi) / 2 == pytest.approx(mean)


def test_missing_values_are_left_out_and_one_run_has_no_interval():
    ci = stats.mean_ci([0.5, None, float("nan")])
    assert ci.n == 1 and ci.mean == 0.5 and not ci.defined
    assert "no interval" in ci.format()
    assert stats.mean_ci([]).n == 0
    assert stats.verdict_near(ci, 0.5, 0.1) == stats.INCONCLUSIVE


def test_verdicts():
    tight = stats.Interval(0.62, 0.58, 0.66, 5)
    assert stats.verdict_near(tight, 0.60, 0.10) == stats.REPRODUCED
    assert stats.verdict_near(tight, 0.88, 0.10) == stats.NOT_REPRODUCED
    assert stats.verdict_near(stats.Interval(0.5, 0.3, 0.7, 5), 0.6, 0.1) == stats.INCONCLUSIVE
    a, b = stats.Interval(1, 0.5, 1.5, 5), stats.Interval(3, 2, 4, 5)
    assert stats.verdict_less(a, b) == stats.REPRODUCED
    assert stats.verdict_less(b, a) == stats.NOT_REPRODUCED
    assert stats.verdict_less(a, stats.Interval(1.4, 1.2, 1.6, 5)) == stats.INCONCLUSIVE
    assert stats.verdict_positive(stats.Interval(0.2, 0.1, 0.3, 5)) == stats.REPRODUCED
    assert stats.verdict_positive(stats.Interval(-0.2, -0.3, -0.1, 5)) == stats.NOT_REPRODUCED
    assert stats.verdict_positive(stats.Interval(0.0, -0.1, 0.1, 5)) == stats.INCONCLUSIVE


# -- the rules fixed before the runs (issue 26), each against a slow obvious reference -----------


def _rows(rng, n):
    """Synthetic per-seed values: a mean, a spread and a count drawn at random."""
    return list(rng.normal(rng.uniform(-1, 1), rng.uniform(0.01, 0.5), n))


def test_decide_near_is_the_interval_rule_with_its_p_values():
    rng = np.random.default_rng(1)
    seen = set()
    for _ in range(400):
        ci = stats.mean_ci(_rows(rng, int(rng.integers(2, 8))))
        target, tol = rng.uniform(-1, 1), rng.uniform(0.05, 0.6)
        # the reference: where the interval lies against the band, read off its ends
        if target - tol <= ci.lo and ci.hi <= target + tol:
            want = stats.REPRODUCED
        elif ci.hi < target - tol or ci.lo > target + tol:
            want = stats.NOT_REPRODUCED
        else:
            want = stats.INCONCLUSIVE
        d = stats.decide_near(ci, target, tol)
        assert d.verdict == want == stats.verdict_near(ci, target, tol)
        assert (d.p < 0.025) == (want != stats.INCONCLUSIVE)
        seen.add(want)
    assert seen == set(stats.VERDICTS)


def test_decide_above_is_verdict_positive_with_its_p_values():
    rng = np.random.default_rng(6)
    for _ in range(300):
        ci = stats.mean_ci(_rows(rng, int(rng.integers(2, 8))))
        d = stats.decide_above(ci)
        assert d.verdict == stats.verdict_positive(ci)
        assert d.p_yes + d.p_no == pytest.approx(1.0)


def test_an_effect_about_plus_d_needs_its_size_not_only_its_sign():
    # smana's exploration, x4 minus x1: +15.6 points [5.9, 25.2] (n = 5); the paper's +28
    paired = stats.Interval(0.156, 0.059, 0.252, 5)
    assert stats.verdict_positive(paired) == stats.REPRODUCED  # the old rule: above 0
    assert stats.decide_near(paired, 0.28, 0.10).verdict == stats.INCONCLUSIVE
    assert stats.decide_near(stats.Interval(0.27, 0.22, 0.33, 5), 0.28, 0.10).verdict == (
        stats.REPRODUCED
    )


def test_not_worse_needs_the_declared_margin():
    rng = np.random.default_rng(2)
    for _ in range(300):
        ci = stats.mean_ci(_rows(rng, int(rng.integers(2, 7))))
        margin = rng.uniform(0, 0.5)
        lower = stats.decide_not_worse(ci, margin).verdict
        want = (
            stats.REPRODUCED
            if ci.hi < margin
            else stats.NOT_REPRODUCED
            if ci.lo > margin
            else stats.INCONCLUSIVE
        )
        assert lower == want
        higher = stats.decide_not_worse(ci, margin, higher_is_better=True).verdict
        want = (
            stats.REPRODUCED
            if ci.lo > -margin
            else stats.NOT_REPRODUCED
            if ci.hi < -margin
            else stats.INCONCLUSIVE
        )
        assert higher == want
    # an interval that holds 0 is no longer enough: it must clear the margin
    wide = stats.Interval(0.0, -0.0012, 0.0011, 3)
    assert stats.decide_not_worse(wide, 0.001).verdict == stats.INCONCLUSIVE
    assert stats.decide_not_worse(wide, 0.002).verdict == stats.REPRODUCED
    with pytest.raises(ValueError, match="margin"):
        stats.decide_not_worse(wide, -1.0)


def test_a_claim_the_world_rules_out_says_so_with_the_evidence():
    ci = stats.Interval(0.75, 0.60, 0.90, 5)
    routes = stats.Interval(0.85, 0.82, 0.88, 5)  # the layout alone gives 82 to 88 %
    d = stats.decide_in_world(ci, 0.60, 0.10, routes)
    assert d.verdict == stats.NOT_REPRODUCIBLE_HERE and "routes: 0.85 [0.82, 0.88]" in d.evidence
    # a world whose routes reach the band decides as decide_near does
    near = stats.Interval(0.66, 0.585, 0.738, 5)
    assert stats.decide_in_world(ci, 0.60, 0.10, near) == stats.decide_near(ci, 0.60, 0.10)


def _holm_reference(p, alpha):
    """Holm 1979 as written: sort, test the i-th smallest at alpha / (m - i + 1), stop at the
    first that fails."""
    m = len(p)
    order = sorted(range(m), key=lambda i: p[i])
    rejected = [False] * m
    for rank, i in enumerate(order, start=1):
        if p[i] > alpha / (m - rank + 1):
            break
        rejected[i] = True
    return rejected


def test_holm_matches_the_step_down_loop():
    rng = np.random.default_rng(3)
    for _ in range(300):
        m = int(rng.integers(1, 15))
        p = list(rng.uniform(0, 0.05, m) ** rng.uniform(0.5, 2))
        adj, rejected = stats.holm(p, 0.025)
        assert rejected.tolist() == _holm_reference(p, 0.025)
        assert (adj >= np.asarray(p) - 1e-15).all() and (adj <= 1).all()


def test_holm_table_turns_a_weak_verdict_inconclusive_and_keeps_world_facts():
    strong = stats.Decision(stats.REPRODUCED, 0.001, 0.99)
    weak = stats.Decision(stats.REPRODUCED, 0.02, 0.98)  # under 0.025 alone, not among three
    world = stats.Decision(stats.NOT_REPRODUCIBLE_HERE, 0.5, 0.5, evidence="routes")
    none = stats.Decision(stats.INCONCLUSIVE, 0.3, 0.4)
    out = stats.holm_table([strong, weak, world, none])
    assert [d.verdict for d in out] == [
        stats.REPRODUCED,
        stats.INCONCLUSIVE,
        stats.NOT_REPRODUCIBLE_HERE,
        stats.INCONCLUSIVE,
    ]
    assert out[2].evidence == "routes" and "Holm-adjusted p = 0.003" in out[0].evidence


def test_sooner_censored_is_the_log_rank_one_sided_with_its_sides_named():
    fast, slow = [3.0, 4, 5, 6, 7, 8], [20.0, 22, 25, 26, 30, 30]
    no = [False] * 6
    d = stats.decide_sooner_censored(
        fast, no, slow, [False] * 4 + [True] * 2, names=("NBV", "frontier")
    )
    lr = survival.logrank(fast, no, slow, [False] * 4 + [True] * 2)
    assert d.verdict == stats.REPRODUCED and d.p == pytest.approx(lr.p / 2)
    assert d.tests == "NBV sooner" and "two-sided; the data lean to NBV sooner" in d.evidence
    assert d.need.how == "log-rank (Schoenfeld)" and d.need.seeds is not None
    back = stats.decide_sooner_censored(slow, no, fast, no, names=("NBV", "frontier"))
    assert back.verdict == stats.NOT_REPRODUCED and back.tests == "frontier sooner"
    same = stats.decide_sooner_censored(fast, no, fast, no)
    assert same.verdict == stats.INCONCLUSIVE and same.need.seeds is None


def test_every_decision_says_which_side_its_p_tests():
    near = stats.decide_near(stats.Interval(0.714, 0.514, 0.914, 5), 0.6, 0.1)
    assert near.verdict == stats.INCONCLUSIVE and near.p == near.p_no
    assert near.tests == "outside the band"
    assert stats.format_p(near.p, near.tests) == f"{near.p:.2g} (one-sided: outside the band)"
    inside = stats.decide_near(stats.Interval(0.6, 0.58, 0.62, 5), 0.6, 0.1)
    assert inside.verdict == stats.REPRODUCED and inside.tests == "inside the band"
    above = stats.decide_above(stats.Interval(-0.2, -0.3, -0.1, 5), yes="TSDF slower", no="faster")
    assert above.verdict == stats.NOT_REPRODUCED and above.tests == "faster"
    worse = stats.decide_not_worse(stats.Interval(0.0, -0.01, 0.01, 3), 0.005)
    assert worse.tests in ("not worse by the margin", "worse by more than the margin")
    f = worse.fields()
    assert (
        f["p"] == worse.p
        and f["p_tests"] == worse.tests
        and f["need"]["how"].startswith("paired t")
    )
    assert stats.format_p(None, None) == "-"
    # Holm keeps the sides and the seeds needed
    (h,) = stats.holm_table([near])
    assert h.tests == near.tests and h.need == near.need


def test_seeds_needed_follow_the_rule_and_the_measured_spread():
    # terrain share at x1: 71.4 % [51.4, 91.4] against 60 +/- 10: the mean lies 1.4 points past
    # the band's edge with an SD of 16 points: about a thousand seeds
    d = stats.decide_near(stats.Interval(0.714, 0.514, 0.914, 5), 0.6, 0.1)
    sd = stats.spread(stats.Interval(0.714, 0.514, 0.914, 5))
    assert sd == pytest.approx(0.2 / 2.776445 * math.sqrt(5))
    assert d.need.effect == pytest.approx(0.014) and d.need.sd == pytest.approx(sd)
    assert d.need.seeds == power.seeds_t(0.014, sd) and 900 < d.need.seeds < 1200
    # inside the band: both edges, TOST
    d = stats.decide_near(stats.Interval(0.6, 0.55, 0.65, 5), 0.6, 0.1)
    assert d.need.how.startswith("TOST") and d.need.seeds <= 5
    assert stats.decide_near(stats.Interval(0.6, math.nan, math.nan, 1), 0.6, 0.1).need is None


def test_first_paired_is_the_exact_sign_test_over_the_known_pairs():
    order = survival.paired_order([1, 2, 3, 4, 5, 9], [0] * 5 + [1], [2, 3, 4, 5, 6, 9],
                                  [0] * 5 + [1])  # fmt: skip
    assert (order.a_first, order.unknown) == (5, 1)
    d = stats.decide_first_paired(order, "fleet sooner", "fleet later")
    assert d.p_yes == pytest.approx(1 / 32) and d.verdict == stats.INCONCLUSIVE
    assert d.tests == "fleet sooner" and d.need.how == "exact sign test"
    assert d.need.detail == "5 of 5 ordered pairs one way, 5 of 6 pairs ordered"
    six = survival.paired_order(range(6), [0] * 6, range(1, 7), [0] * 6)
    assert stats.decide_first_paired(six, "y", "n").verdict == stats.REPRODUCED
    late = survival.paired_order(range(1, 7), [0] * 6, range(6), [0] * 6)
    assert stats.decide_first_paired(late, "y", "n").verdict == stats.NOT_REPRODUCED


def test_ratio_ci_is_fiellers_the_ratios_the_paired_t_test_keeps():
    """ratio_ci against the slow definition: R is inside the interval exactly when the interval
    of the per-seed differences a - R b holds 0 (a scan of R)."""
    rng = np.random.default_rng(5)
    b = rng.uniform(2, 6, 10)
    a = 0.4 * b + rng.normal(0, 0.5, 10)
    ci = stats.ratio_ci(a, b)
    assert ci.n == 10 and ci.mean == pytest.approx(a.mean() / b.mean())
    assert ci.lo < ci.mean < ci.hi
    for r in np.linspace(ci.lo - 0.3, ci.hi + 0.3, 301):
        d = stats.mean_ci(a - r * b)
        kept = d.lo <= 0 <= d.hi
        if min(abs(r - ci.lo), abs(r - ci.hi)) > 1e-6:
            assert kept == (ci.lo <= r <= ci.hi), r
    # a denominator whose mean is not clearly away from 0: no interval, as with one pair
    assert not stats.ratio_ci([1.0, 2.0, 0.5], [1.0, -1.0, 0.2]).defined
    assert not stats.ratio_ci([1.0], [2.0]).defined and stats.ratio_ci([1.0], [2.0]).mean == 0.5
    assert stats.ratio_ci([1.0, None, 3.0], [2.0, 1.0, 6.0]).n == 2
