"""How many seeds a claim needs: the smallest number at which its rule (lab/stats.py) reaches a
verdict with 80 % power, were the true effect and spread those measured. Each rule's one-sided
tests are at 0.025 (the end of a 95 % interval); Holm's correction over a table of claims asks
more of all but its weakest, so these are lower bounds for a claim decided in the table.

    seeds_t(delta, sd)                 a one-sided t test on per-seed (paired) values
    seeds_tost(delta_lo, delta_hi, sd) both one-sided tests of an "about X" band
    seeds_sign(q, ordered)             the exact sign test over the pairs whose order is known
    seeds_logrank(log_hr, reached)     the log-rank test (Schoenfeld 1983)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st

ALPHA = 0.025  # one-sided, each test
POWER = 0.8
MAX_SEEDS = 100_000  # past this, "more than"


@dataclass(frozen=True)
class Need:
    """Seeds a rule needs, with what they were computed from: `effect` is the distance from the
    measured mean to the rule's edge (t rules, in the claim's units), the share of ordered
    pairs going the majority's way (sign test), or the log hazard ratio (log-rank); `sd` the
    spread of the per-seed values (t rules). `seeds` None: no number up to MAX_SEEDS decides
    it (no effect to find, or too small a one). `n`: how many the measurement had."""

    seeds: int | None
    how: str
    effect: float
    sd: float | None = None
    detail: str = ""
    n: int = 0  # the seeds (pairs, scans) the measurement came from


def _smallest(power_of: Callable[[int], float], lo: int = 2) -> int | None:
    """The smallest n in [lo, MAX_SEEDS] with power_of(n) >= POWER, by bisection (power grows
    with n; an exact discrete test's saw-tooths by a seed or two around it)."""
    hi = MAX_SEEDS
    if power_of(hi) < POWER:
        return None
    while lo < hi:
        mid = (lo + hi) // 2
        if power_of(mid) >= POWER:
            hi = mid
        else:
            lo = mid + 1
    return lo


def t_power(n: int, delta: float, sd: float, alpha: float = ALPHA) -> float:
    """Power of the one-sided t test at level `alpha` with n values whose mean lies `delta`
    beyond the tested edge, spread `sd`: P(t > t_crit) under the noncentral t."""
    df = n - 1
    crit = float(_st.t.ppf(1 - alpha, df))
    return float(_st.nct.sf(crit, df, delta * math.sqrt(n) / sd))


def seeds_t(delta: float, sd: float, alpha: float = ALPHA) -> int | None:
    """Seeds for a one-sided t test (an interval's end past an edge) to decide with 80 % power,
    the mean `delta` past the edge. No spread: two seeds decide; no distance: none do."""
    if not delta > 0:
        return None
    if sd == 0:
        return 2
    return _smallest(lambda n: t_power(n, delta, sd, alpha))


def seeds_tost(delta_lo: float, delta_hi: float, sd: float, alpha: float = ALPHA) -> int | None:
    """Seeds for both one-sided tests of a band (the mean `delta_lo` above its lower edge and
    `delta_hi` below its upper one) to reject together with 80 % power; the power of both is
    at least P(lower) + P(upper) - 1 (Bonferroni), which is what is asked of."""
    if not (delta_lo > 0 and delta_hi > 0):
        return None
    if sd == 0:
        return 2
    return _smallest(
        lambda n: t_power(n, delta_lo, sd, alpha) + t_power(n, delta_hi, sd, alpha) - 1
    )


def sign_power(n: int, q: float, ordered: float, alpha: float = ALPHA) -> float:
    """Power of the one-sided exact sign test over n pairs, each ordered (not tied, not hidden
    by censoring) with chance `ordered` and then going the tested way with chance q: the sum
    over the number m of ordered pairs of P(m) P(wins >= the critical count at m)."""
    m = np.arange(n + 1)
    p_m = _st.binom.pmf(m, n, ordered)
    crit = _st.binom.isf(alpha, m, 0.5) + 1  # the fewest wins whose p is <= alpha
    return float(np.sum(p_m * _st.binom.sf(crit - 1, m, q)))


def seeds_sign(q: float, ordered: float, alpha: float = ALPHA) -> int | None:
    """Seeds for the exact sign test to decide with 80 % power when a share q of the ordered
    pairs goes one way and a share `ordered` of all pairs is ordered."""
    if not (q > 0.5 and ordered > 0):
        return None
    return _smallest(lambda n: sign_power(n, q, ordered, alpha), lo=1)


def seeds_logrank(log_hr: float, reached: float, alpha: float = ALPHA) -> int | None:
    """Seeds (one run per group each) for the log-rank test to decide with 80 % power:
    Schoenfeld's events D = 4 (z_(1-alpha) + z_power)^2 / log(HR)^2 for two equal groups,
    over the events a seed gives (2 runs times the share `reached` that had their event)."""
    if log_hr == 0 or not math.isfinite(log_hr) or not reached > 0:
        return None
    z = float(_st.norm.ppf(1 - alpha) + _st.norm.ppf(POWER))
    seeds = math.ceil(4 * z * z / log_hr**2 / (2 * reached))
    return seeds if seeds <= MAX_SEEDS else None
