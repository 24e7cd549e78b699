"""lab/stats.py: the interval against a slow obvious reference, and the verdicts' edges."""

import math

import numpy as np
import pytest

from smana.lab import stats

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


def _km_reference(values, censored):
    """Efron's redistribute-to-the-right: each run holds mass 1/n; in order (an event before a
    censoring at the same value), a censored run hands its mass on equally to every run after
    it. S(t) = 1 - the mass of events at or before t; the same curve as Kaplan-Meier."""
    order = sorted(range(len(values)), key=lambda i: (values[i], censored[i]))
    mass = [1.0 / len(values)] * len(values)
    for k, i in enumerate(order):
        if censored[i] and k + 1 < len(order):
            share = mass[k] / (len(order) - k - 1)
            for j in range(k + 1, len(order)):
                mass[j] += share
            mass[k] = 0.0
    curve, done = {}, 0.0
    for k, i in enumerate(order):
        if not censored[i]:
            done += mass[k]
            curve[values[i]] = 1.0 - done
    return curve


def test_kaplan_meier_matches_redistribute_to_the_right_and_scipy():
    from scipy.stats import CensoredData, ecdf

    rng = np.random.default_rng(4)
    for _ in range(200):
        n = int(rng.integers(2, 9))
        v = [float(x) for x in rng.integers(1, 12, n)]  # ties on purpose
        c = [bool(x) for x in rng.random(n) < 0.35]
        if all(c):
            c[0] = False
        times, surv = stats.kaplan_meier(v, c)
        ref = _km_reference(v, c)
        assert times.tolist() == sorted(ref)
        assert surv.tolist() == pytest.approx([ref[t] for t in sorted(ref)])
        sc = ecdf(CensoredData(uncensored=[x for x, k in zip(v, c) if not k],
                               right=[x for x, k in zip(v, c) if k])).sf  # fmt: skip
        assert sc.evaluate(times).tolist() == pytest.approx(surv.tolist())
        med = stats.km_median(v, c)
        below = [t for t in sorted(ref) if ref[t] <= 0.5 + 1e-12]
        assert med == (below[0] if below else None)


def test_km_median_of_a_garden_with_censored_runs():
    # 20 m garden, NBV: 2 of 3 reached 95 % (at 36 and 65 m), seed 4 stopped at 92.4 % after
    # 80 m: the median is the second event, not the mean of the two that reached
    assert stats.km_median([36.0, 80.0, 65.0], [False, True, False]) == 65.0
    assert stats.km_median([36.0, 80.0, 85.0], [False, True, True]) is None


def test_logrank_matches_scipy_and_decides_which_arm_is_sooner():
    from scipy.stats import CensoredData
    from scipy.stats import logrank as scipy_logrank

    rng = np.random.default_rng(5)
    for _ in range(100):
        a = [float(x) for x in rng.integers(1, 15, int(rng.integers(2, 7)))]
        b = [float(x) for x in rng.integers(3, 20, int(rng.integers(2, 7)))]
        ca = [bool(x) for x in rng.random(len(a)) < 0.3]
        cb = [bool(x) for x in rng.random(len(b)) < 0.3]
        if all(ca) and all(cb):
            continue

        def cd(v, c):
            return CensoredData(
                uncensored=[x for x, k in zip(v, c, strict=True) if not k],
                right=[x for x, k in zip(v, c, strict=True) if k],
            )

        z, p = stats.logrank(a, ca, b, cb)
        with np.errstate(invalid="ignore"):
            ref = scipy_logrank(cd(a, ca), cd(b, cb))
        if not np.isfinite(ref.pvalue):  # no variance (one event, or one arm): no evidence
            assert p == 1.0
            continue
        assert p == pytest.approx(ref.pvalue, rel=1e-6, abs=1e-12)
    fast, slow = [3.0, 4, 5, 6, 7, 8], [20.0, 22, 25, 26, 30, 30]
    no = [False] * 6
    d = stats.decide_sooner_censored(fast, no, slow, [False] * 4 + [True] * 2)
    assert d.verdict == stats.REPRODUCED and "not reached" not in d.evidence
    assert stats.decide_sooner_censored(slow, no, fast, no).verdict == stats.NOT_REPRODUCED
    assert stats.decide_sooner_censored(fast, no, fast, no).verdict == stats.INCONCLUSIVE


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
