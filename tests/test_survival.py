"""lab/survival.py and lab/power.py: each estimator against a published example, a hand-worked
one and a slow obvious reference; the edges (all censored, no events, an event and a censoring
at the same time)."""

import math
from fractions import Fraction as F

import numpy as np
import pytest

from smana.lab import power, survival

# Freireich et al. 1963, the 6-MP arm (weeks in remission; "+" censored), the textbook example
# of Kaplan-Meier with Greenwood's errors (Klein and Moeschberger 2003, Table 4.1A; Collett):
# 6, 6, 6, 6+, 7, 9+, 10, 10+, 11+, 13, 16, 17+, 19+, 20+, 22, 23, 25+, 32+, 32+, 34+, 35+
SIX_MP = [6, 6, 6, 6, 7, 9, 10, 10, 11, 13, 16, 17, 19, 20, 22, 23, 25, 32, 32, 34, 35]
SIX_MP_CENSORED = [0, 0, 0, 1, 0, 1, 0, 1, 1, 0, 0, 1, 1, 1, 0, 0, 1, 1, 1, 1, 1]
# its placebo arm: every patient relapsed
PLACEBO = [1, 1, 2, 2, 3, 4, 4, 5, 5, 8, 8, 8, 8, 11, 11, 12, 12, 15, 17, 22, 23]


def test_kaplan_meier_and_greenwood_on_the_6mp_arm():
    km = survival.kaplan_meier(SIX_MP, SIX_MP_CENSORED)
    assert km.times.tolist() == [6, 7, 10, 13, 16, 22, 23]
    assert km.at_risk.tolist() == [21, 17, 15, 12, 11, 7, 6]  # the 6+ is at risk at 6
    # by hand: the product of (1 - d/n)
    s, want = F(1), []
    for n, d in ((21, 3), (17, 1), (15, 1), (12, 1), (11, 1), (7, 1), (6, 1)):
        s *= 1 - F(d, n)
        want.append(float(s))
    assert km.survival.tolist() == pytest.approx(want)
    # the published table, to its three decimals
    assert km.survival.round(3).tolist() == [0.857, 0.807, 0.753, 0.690, 0.627, 0.538, 0.448]
    assert km.se().round(4).tolist() == [0.0764, 0.0869, 0.0963, 0.1068, 0.1141, 0.1282, 0.1346]
    assert km.median() == 23.0  # the published median remission
    assert (
        km.at(5.9) == 1.0 and km.at(6) == pytest.approx(18 / 21) and km.at(100) == km.survival[-1]
    )
    # the log-log interval by its formula, at 13 weeks
    lo, hi = km.ci()
    k = 3
    w = 1.959964 * math.sqrt(km.greenwood[k]) / abs(math.log(km.survival[k]))
    assert (lo[k], hi[k]) == pytest.approx(
        (km.survival[k] ** math.exp(w), km.survival[k] ** math.exp(-w))
    )
    assert (lo <= km.survival).all() and (km.survival <= hi).all() and (hi <= 1).all()


def test_logrank_on_the_6mp_trial_is_the_published_chi_square():
    lr = survival.logrank(SIX_MP, SIX_MP_CENSORED, PLACEBO, [0] * len(PLACEBO))
    assert lr.observed_a == 9 and lr.observed_b == 21
    assert lr.expected_a == pytest.approx(19.25, abs=0.005)
    assert lr.variance == pytest.approx(6.257, abs=0.001)
    assert lr.z**2 == pytest.approx(16.79, abs=0.01)  # Klein and Moeschberger 7.3: 16.79
    assert lr.sooner == "b" and lr.hazard_ratio < 1 and lr.p < 1e-4
    text = lr.describe("6-MP", "placebo")
    assert "two-sided" in text and "the data lean to placebo sooner" in text


def test_logrank_is_the_sum_of_the_2x2_tables_worked_by_hand():
    # A: 1, 3+, 4; B: 2, 4, 5+. Tables at the event times 1, 2 and 4 (n at risk, n_A, d, d_A):
    # t=1: 6, 3, 1, 1 -> E_A = 1/2, V = 1/4
    # t=2: 5, 2, 1, 0 -> E_A = 2/5, V = (2/5)(3/5) = 6/25
    # t=4: 3, 1, 2, 1 -> E_A = 2/3, V = 2 (1/3)(2/3)(3-2)/(3-1) = 2/9 (the 3+ left before 4)
    lr = survival.logrank([1, 3, 4], [0, 1, 0], [2, 4, 5], [0, 0, 1])
    e_a = F(1, 2) + F(2, 5) + F(2, 3)
    v = F(1, 4) + F(6, 25) + F(2, 9)
    assert lr.observed_a == 2 and lr.expected_a == pytest.approx(float(e_a))
    assert lr.variance == pytest.approx(float(v))
    assert lr.z == pytest.approx(float(2 - e_a) / math.sqrt(float(v)))
    assert lr.sooner == "a" and lr.p == pytest.approx(2 * (1 - _phi(lr.z)))


def _phi(z):
    return 0.5 * (1 + math.erf(z / math.sqrt(2)))


def test_logrank_matches_scipy():
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

        lr = survival.logrank(a, ca, b, cb)
        with np.errstate(invalid="ignore"):
            ref = scipy_logrank(cd(a, ca), cd(b, cb))
        if not np.isfinite(ref.pvalue):  # no variance (one event, or one arm): no evidence
            assert lr.p == 1.0
            continue
        assert lr.p == pytest.approx(ref.pvalue, rel=1e-6, abs=1e-12)
        assert abs(lr.z) == pytest.approx(abs(ref.statistic), rel=1e-6)


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


def _random_runs(rng):
    n = int(rng.integers(2, 9))
    v = [float(x) for x in rng.integers(1, 12, n)]  # ties on purpose
    c = [bool(x) for x in rng.random(n) < 0.35]
    if all(c):
        c[0] = False
    return v, c


def test_kaplan_meier_matches_redistribute_to_the_right_and_scipy():
    from scipy.stats import CensoredData, ecdf

    rng = np.random.default_rng(4)
    for _ in range(200):
        v, c = _random_runs(rng)
        km = survival.kaplan_meier(v, c)
        ref = _km_reference(v, c)
        assert km.times.tolist() == sorted(ref)
        assert km.survival.tolist() == pytest.approx([ref[t] for t in sorted(ref)])
        sc = ecdf(CensoredData(uncensored=[x for x, k in zip(v, c) if not k],
                               right=[x for x, k in zip(v, c) if k])).sf  # fmt: skip
        assert sc.evaluate(km.times).tolist() == pytest.approx(km.survival.tolist())
        below = [t for t in sorted(ref) if ref[t] <= 0.5 + 1e-12]
        assert km.median() == (below[0] if below else None)
        lo, hi = km.median_ci()
        if km.median() is not None:
            assert lo is not None and lo <= km.median() and (hi is None or hi >= km.median())


def _rmst_reference(values, censored, horizon, steps=20_000):
    """The area under the redistribute-to-the-right curve on a fine grid (midpoints), and the
    variance sum over event times of (area from t_j to the horizon)^2 d_j / (n_j (n_j - d_j)),
    each area integrated on the same grid."""
    ref = _km_reference(values, censored)
    times = sorted(ref)
    dt = horizon / steps
    grid = (np.arange(steps) + 0.5) * dt
    heights = np.array([1.0] + [ref[t] for t in times])
    s = heights[np.searchsorted(times, grid, side="right")]
    var = 0.0
    for t in times:
        n = sum(x >= t for x in values)
        d = sum(x == t and not k for x, k in zip(values, censored, strict=True))
        if t <= horizon and n > d:
            var += float(s[grid >= t].sum() * dt) ** 2 * d / (n * (n - d))
    return float(s.sum() * dt), var


def test_restricted_mean_by_hand_and_against_a_slow_reference():
    # 2, 3+, 4, 6 to a horizon of 5: S = 1 to 2, 3/4 to 4, 3/8 after; area 2 + 1.5 + 0.375;
    # variance (1.5 + 0.375)^2 / (4 x 3) + 0.375^2 / (2 x 1)
    r = survival.kaplan_meier([2, 3, 4, 6], [0, 1, 0, 0]).rmst(5.0)
    assert r.mean == pytest.approx(3.875)
    assert r.se**2 == pytest.approx(1.875**2 / 12 + 0.375**2 / 2)
    lo, hi = r.ci()
    assert (lo + hi) / 2 == pytest.approx(3.875) and hi - lo == pytest.approx(2 * 1.959964 * r.se)
    rng = np.random.default_rng(7)
    for _ in range(25):
        v, c = _random_runs(rng)
        horizon = float(rng.uniform(1, max(v)))
        r = survival.kaplan_meier(v, c).rmst(horizon)
        mean, var = _rmst_reference(v, c, horizon)
        assert r.mean == pytest.approx(mean, abs=horizon / 1000)
        assert r.se**2 == pytest.approx(var, rel=0.01, abs=horizon**2 / 1000)


def test_without_censoring_the_curve_is_the_ecdf_and_the_rmst_the_plain_mean():
    rng = np.random.default_rng(8)
    for _ in range(50):
        x = rng.integers(1, 30, int(rng.integers(2, 12))).astype(float)
        km = survival.kaplan_meier(x, [False] * len(x))
        n = len(x)
        assert km.survival.tolist() == pytest.approx([np.mean(x > t) for t in km.times])
        s = km.survival
        assert km.se().tolist() == pytest.approx(np.sqrt(s * (1 - s) / n).tolist())  # binomial
        tau = float(rng.uniform(1, 35))
        r = km.rmst(tau) if tau <= x.max() or s[-1] == 0 else None
        if r is not None:
            m = np.minimum(x, tau)
            assert r.mean == pytest.approx(m.mean())
            assert r.se**2 == pytest.approx(((m - m.mean()) ** 2).sum() / n**2)  # the plug-in


def test_edges_all_censored_no_events_and_a_tie_with_a_censoring():
    # an event and a censoring at 2: the censored run is at risk at 2 (the event comes first)
    km = survival.kaplan_meier([2.0, 2.0], [False, True])
    assert km.at_risk.tolist() == [2] and km.at(2.0) == 0.5 and km.median() == 2.0
    # every run censored: nothing reached, S is 1, the median and its ends not reached
    km = survival.kaplan_meier([3.0, 5.0, 7.0], [True, True, True])
    assert len(km.times) == 0 and km.at(10.0) == 1.0 and km.median() is None
    assert km.median_ci() == (None, None)
    r = km.rmst(7.0)
    assert r.mean == 7.0 and r.se == 0.0
    with pytest.raises(ValueError, match="past the last run"):
        km.rmst(8.0)
    # censored beyond every distance (a run that never reached it, distance having no budget)
    km = survival.kaplan_meier([1.0, 2.0, math.inf], [False, False, True])
    assert km.survival.tolist() == pytest.approx([2 / 3, 1 / 3]) and km.median() == 2.0
    # no event anywhere: the log-rank test has nothing to say, and says so
    lr = survival.logrank([3.0, 4.0], [True, True], [5.0], [True])
    assert lr.p == 1.0 and lr.z == 0.0 and "no event to compare" in lr.describe()
    # every run reached it: S falls to 0, its error and band 0 there
    km = survival.kaplan_meier([1.0, 2.0], [False, False])
    assert km.se().tolist() == pytest.approx([0.5 / math.sqrt(2), 0.0])
    assert km.ci()[1][-1] == 0.0 and km.rmst(5.0).mean == pytest.approx(1.5)
    with pytest.raises(ValueError):
        survival.kaplan_meier([1.0, math.nan], [False, False])
    with pytest.raises(ValueError):
        survival.kaplan_meier([1.0], [False, True])


def test_paired_order_knows_what_censoring_leaves_known():
    o = survival.pair_order
    assert o(3, False, 5, False) == "a" and o(5, False, 3, False) == "b"
    assert o(4, False, 4, False) == "tie"
    assert o(3, False, 3, True) == "a"  # B censored at A's event time: A first
    assert o(3, False, 2, True) == "unknown"  # B left at 2, before A's event
    assert o(9, True, 5, False) == "b" and o(4, True, 5, False) == "unknown"
    assert o(4, True, 5, True) == "unknown"
    p = survival.paired_order([1, 2, 3, 9, 4], [0, 0, 0, 1, 1], [2, 3, 1, 5, 5], [0, 1, 0, 0, 1])
    assert (p.a_first, p.b_first, p.tied, p.unknown, p.through_censoring) == (2, 2, 0, 1, 2)
    # the exact one-sided sign test: 6 of 6 pairs one way
    six = survival.paired_order(range(6), [0] * 6, [x + 1 for x in range(6)], [0] * 6)
    assert six.p_a_first == pytest.approx(1 / 64) and six.p_b_first == 1.0
    assert six.p == pytest.approx(2 / 64)
    assert survival.paired_order([], [], [], []).p == 1.0


def test_for_pairs_the_log_rank_stratified_by_pair_is_the_sign_count():
    rng = np.random.default_rng(9)
    for _ in range(100):
        n = int(rng.integers(1, 10))
        a, b = rng.integers(1, 8, n).astype(float), rng.integers(1, 8, n).astype(float)
        ca, cb = rng.random(n) < 0.3, rng.random(n) < 0.3
        o_e = var = 0.0
        for k in range(n):  # one stratum (a 2-run log-rank) per pair
            lr = survival.logrank([a[k]], [ca[k]], [b[k]], [cb[k]])
            o_e += lr.observed_a - lr.expected_a
            var += lr.variance
        p = survival.paired_order(a, ca, b, cb)
        assert o_e == pytest.approx((p.a_first - p.b_first) / 2)
        assert var == pytest.approx(p.ordered / 4)


# -- power -----------------------------------------------------------------------------------


def test_seeds_for_a_t_test_are_the_textbook_sample_sizes():
    # one-sample (paired) t, 80 % power at 0.05 two-sided (0.025 a side): d = 0.5 -> 34,
    # d = 0.8 -> 15, d = 0.2 -> 199 (Cohen 1988; G*Power gives the same)
    assert power.seeds_t(0.5, 1.0) == 34
    assert power.seeds_t(0.8, 1.0) == 15
    assert power.seeds_t(2.0, 10.0) == 199
    n = power.seeds_t(0.37, 1.3)
    assert power.t_power(n, 0.37, 1.3) >= 0.8 > power.t_power(n - 1, 0.37, 1.3)
    assert power.seeds_t(0.0, 1.0) is None and power.seeds_t(1.0, 0.0) == 2
    assert power.seeds_t(1e-4, 1.0) is None  # past MAX_SEEDS
    # both edges of a band: more than either alone
    both = power.seeds_tost(0.5, 0.5, 1.0)
    assert both > power.seeds_t(0.5, 1.0)
    assert 2 * power.t_power(both, 0.5, 1.0) - 1 >= 0.8


def test_seeds_for_the_sign_test_against_a_slow_sum():
    from math import comb

    def slow(n, q, k, alpha=0.025):
        total = 0.0
        for m in range(n + 1):
            crit = next(
                c for c in range(m + 2) if sum(comb(m, j) for j in range(c, m + 1)) / 2**m <= alpha
            )
            win = sum(comb(m, j) * q**j * (1 - q) ** (m - j) for j in range(crit, m + 1))
            total += comb(n, m) * k**m * (1 - k) ** (n - m) * win
        return total

    for n, q, k in ((8, 0.625, 1.0), (12, 0.8, 0.75), (20, 0.7, 0.9), (5, 1.0, 1.0)):
        assert power.sign_power(n, q, k) == pytest.approx(slow(n, q, k))
    assert power.seeds_sign(1.0, 1.0) == 6  # 1/64 < 0.025 < 1/32
    n = power.seeds_sign(0.625, 1.0)
    assert power.sign_power(n, 0.625, 1.0) >= 0.8
    assert power.seeds_sign(0.5, 1.0) is None and power.seeds_sign(0.8, 0.0) is None


def test_seeds_for_the_log_rank_are_schoenfelds():
    # hazard ratio 0.5, 0.025 one-sided, 80 %: D = 4 (1.96 + 0.8416)^2 / ln(2)^2 = 65.3 events
    z = 1.959964 + 0.841621
    assert power.seeds_logrank(math.log(0.5), 1.0) == math.ceil(4 * z * z / math.log(2) ** 2 / 2)
    assert power.seeds_logrank(math.log(0.5), 1.0) == 33
    assert power.seeds_logrank(math.log(0.5), 0.5) == 66  # half the runs have their event
    assert power.seeds_logrank(0.0, 1.0) is None
