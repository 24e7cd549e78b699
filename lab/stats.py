"""Statistics every experiment reports with: mean and 95 % confidence interval over runs, and a
verdict on a paper claim decided by the intervals, never by one run.

    ci = mean_ci([0.61, 0.55, 0.70, 0.58, 0.66])      # Interval(mean, lo, hi, n)
    verdict_near(ci, 0.60, tolerance=0.10)             # "reproduced" / "not reproduced" / ...
    verdict_less(ci_tsdf, ci_octree)                   # a's interval entirely below b's

The interval is Student's t on the mean (runs are few: 5 to 10), two-sided at `confidence`.
With fewer than two finite values there is no interval: lo and hi are NaN and every verdict is
"inconclusive".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st

REPRODUCED = "reproduced"
NOT_REPRODUCED = "not reproduced"
INCONCLUSIVE = "inconclusive"
VERDICTS = (REPRODUCED, NOT_REPRODUCED, INCONCLUSIVE)


@dataclass(frozen=True)
class Interval:
    """Mean of `n` runs with its two-sided confidence interval [lo, hi]."""

    mean: float
    lo: float
    hi: float
    n: int
    confidence: float = 0.95

    @property
    def half_width(self) -> float:
        return (self.hi - self.lo) / 2

    @property
    def defined(self) -> bool:
        return self.n >= 2 and math.isfinite(self.lo) and math.isfinite(self.hi)

    def format(self, scale: float = 1.0, fmt: str = ".1f", unit: str = "") -> str:
        """ "61.2 % [55.0, 67.4] (n = 5)" with scale=100, unit=" %"."""
        if self.n == 0:
            return "- (n = 0)"
        m = format(self.mean * scale, fmt)
        if not self.defined:
            return f"{m}{unit} (n = {self.n}, no interval)"
        lo, hi = format(self.lo * scale, fmt), format(self.hi * scale, fmt)
        return f"{m}{unit} [{lo}, {hi}] (n = {self.n})"

    def as_dict(self) -> dict:
        return {
            "mean": self.mean,
            "ci_lo": self.lo if math.isfinite(self.lo) else None,
            "ci_hi": self.hi if math.isfinite(self.hi) else None,
            "n": self.n,
            "confidence": self.confidence,
        }


def mean_ci(values, confidence: float = 0.95) -> Interval:
    """Mean and Student-t interval of the finite values (None and NaN are left out)."""
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    v = np.array([x for x in values if x is not None], float)
    v = v[np.isfinite(v)]
    n = len(v)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0, confidence)
    m = float(v.mean())
    if n < 2:
        return Interval(m, math.nan, math.nan, n, confidence)
    sem = float(v.std(ddof=1)) / math.sqrt(n)
    h = float(_st.t.ppf(0.5 + confidence / 2, n - 1)) * sem
    return Interval(m, m - h, m + h, n, confidence)


def verdict_near(ci: Interval, target: float, tolerance: float) -> str:
    """The claim "the value is `target` within `tolerance`": reproduced when the whole interval
    lies within [target - tolerance, target + tolerance], not reproduced when it lies wholly
    outside, inconclusive otherwise (or without an interval)."""
    if not ci.defined:
        return INCONCLUSIVE
    lo, hi = target - tolerance, target + tolerance
    if ci.lo >= lo and ci.hi <= hi:
        return REPRODUCED
    if ci.hi < lo or ci.lo > hi:
        return NOT_REPRODUCED
    return INCONCLUSIVE


def verdict_less(a: Interval, b: Interval) -> str:
    """The claim "a < b": reproduced when a's interval lies entirely below b's, not reproduced
    when it lies entirely above, inconclusive when they overlap (or either has no interval)."""
    if not (a.defined and b.defined):
        return INCONCLUSIVE
    if a.hi < b.lo:
        return REPRODUCED
    if a.lo > b.hi:
        return NOT_REPRODUCED
    return INCONCLUSIVE


def verdict_positive(ci: Interval) -> str:
    """The claim "the value is above 0" (e.g. a paired difference b - a over runs): reproduced
    when the interval lies above 0, not reproduced when below, inconclusive when it holds 0."""
    if not ci.defined:
        return INCONCLUSIVE
    if ci.lo > 0:
        return REPRODUCED
    if ci.hi < 0:
        return NOT_REPRODUCED
    return INCONCLUSIVE
