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
