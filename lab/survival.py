"""Time to an event (here: a run reaching 95 % coverage) when some runs never reach it: the
textbook estimators, written from their definitions and checked in tests/test_survival.py
against slow references and published examples.

    km = kaplan_meier(times, censored)     # Kaplan & Meier 1958, Greenwood's variance
    km.at(t), km.ci(), km.median(), km.median_ci()
    km.rmst(horizon)                       # restricted mean time up to a horizon, SE, interval
    logrank(a, a_cens, b, b_cens)          # two groups, two-sided, and which way the data lean
    paired_order(a, a_cens, b, b_cens)     # sign test over the pairs whose order is known

A censored run is one whose event, if it ever comes, comes after its censoring value c (T > c).
At a tie an event comes before a censoring: a run censored at t is still at risk at t (Kaplan
and Meier 1958, section 2). Which runs are censored where is the experiment's to say (the
experiments censor a run that did not reach 95 % at its budget: lab/experiments/exploration.py
`time_to_event`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st


def _arrays(values, censored) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(values, float).reshape(-1)
    c = np.asarray(censored, bool).reshape(-1)
    if v.shape != c.shape:
        raise ValueError(f"values and censored differ in length ({len(v)} and {len(c)})")
    if np.isnan(v).any() or np.isinf(v[~c]).any():
        raise ValueError("every value must be a number, and every event time finite")
    return v, c


def _z(confidence: float) -> float:
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    return float(_st.norm.ppf(0.5 + confidence / 2))


@dataclass(frozen=True)
class Restricted:
    """The restricted mean time up to `horizon` (the area under the survival curve from 0 to
    it: the mean of min(T, horizon)), its standard error and a normal interval."""

    mean: float
    se: float
    horizon: float
    n: int

    def ci(self, confidence: float = 0.95) -> tuple[float, float]:
        h = _z(confidence) * self.se
        return self.mean - h, self.mean + h

    def format(self, fmt: str = ".0f", unit: str = "") -> str:
        lo, hi = self.ci()
        m = format(self.mean, fmt)
        return f"{m}{unit} [{format(lo, fmt)}, {format(hi, fmt)}] (n = {self.n})"


@dataclass(frozen=True)
class KaplanMeier:
    """The Kaplan-Meier curve of "not yet reached": at each distinct event time t_j, n_j runs at
    risk (value >= t_j), d_j events, S(t_j) = prod over t_i <= t_j of (1 - d_i / n_i)."""

    times: np.ndarray  # the distinct event times, ascending
    at_risk: np.ndarray
    events: np.ndarray
    survival: np.ndarray  # S just after each time
    n: int
    last: float  # the largest value observed, event or censored (-inf with no runs)

    @property
    def greenwood(self) -> np.ndarray:
        """Greenwood's sum at each time, sum over t_i <= t_j of d_i / (n_i (n_i - d_i)): the
        variance of log S. Infinite once every run at risk had its event (S is then 0)."""
        with np.errstate(divide="ignore"):
            terms = self.events / (self.at_risk * (self.at_risk - self.events))
        return np.cumsum(terms)

    def at(self, t) -> np.ndarray | float:
        """S(t), right-continuous: 1 before the first event."""
        k = np.searchsorted(self.times, np.asarray(t, float), side="right")
        s = np.concatenate([[1.0], self.survival])[k]
        return float(s) if np.ndim(s) == 0 else s

    def se(self) -> np.ndarray:
        """Greenwood's standard error of S at each time: S sqrt(sum). Where S is 0 (every run
        at risk reached it) the curve is known, its error 0 (the limit of the binomial's)."""
        with np.errstate(invalid="ignore"):
            out = self.survival * np.sqrt(self.greenwood)
        return np.where(self.survival > 0, out, 0.0)

    def ci(self, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Pointwise interval of S at each time, on the log(-log S) scale (Kalbfleisch and
        Prentice 1980: stays within [0, 1], better than the plain one at a few runs):
        S ** exp(+-z sqrt(greenwood) / log S). [0, 0] where S is 0."""
        z = _z(confidence)
        s = self.survival
        lo, hi = np.zeros(len(s)), np.zeros(len(s))
        live = (s > 0) & (s < 1)
        w = z * np.sqrt(self.greenwood[live]) / np.abs(np.log(s[live]))
        lo[live], hi[live] = s[live] ** np.exp(w), s[live] ** np.exp(-w)
        return lo, hi

    def _first(self, curve: np.ndarray, level: float = 0.5) -> float | None:
        hit = np.flatnonzero(curve <= level + 1e-12)
        return float(self.times[hit[0]]) if len(hit) else None

    def median(self) -> float | None:
        """The first event time at which S falls to 0.5 or below; None when it never does (half
        the runs or more never reached it as far as they were followed)."""
        return self._first(self.survival)

    def median_ci(self, confidence: float = 0.95) -> tuple[float | None, float | None]:
        """The times whose pointwise interval holds 0.5 (Brookmeyer and Crowley 1982, on the
        log-log band): from the first time the band's lower edge falls to 0.5 to the first
        time its upper edge does; None for an end the curve never reaches ("not reached")."""
        lo, hi = self.ci(confidence)
        return self._first(lo), self._first(hi)

    def rmst(self, horizon: float) -> Restricted:
        """The restricted mean time up to `horizon`: the area under S from 0 to it, with the
        variance sum over event times t_j <= horizon of A_j^2 d_j / (n_j (n_j - d_j)), A_j the
        area under S from t_j to the horizon (Klein and Moeschberger 2003, 4.5). The curve
        must be known up to the horizon: a horizon past the last run, with S still above 0
        there, is refused."""
        if not horizon > 0 or not math.isfinite(horizon):
            raise ValueError(f"horizon must be positive and finite, got {horizon}")
        s_end = float(self.survival[-1]) if len(self.survival) else 1.0
        if horizon > self.last and s_end > 0:
            raise ValueError(
                f"horizon {horizon:g} is past the last run ({self.last:g}) with S = {s_end:.3g}:"
                " the curve is not known there"
            )
        keep = self.times <= horizon
        t, s = self.times[keep], self.survival[keep]
        edges = np.concatenate([[0.0], t, [horizon]])
        heights = np.concatenate([[1.0], s])
        pieces = np.diff(edges) * heights  # the area of each step up to the horizon
        mean = float(pieces.sum())
        # A_j: the area from t_j on, the steps after the j-th event time
        tail = np.cumsum(pieces[::-1])[::-1][1:]
        n, d = self.at_risk[keep], self.events[keep]
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = np.where(tail > 0, tail**2 * d / (n * (n - d)), 0.0)
        return Restricted(mean, float(math.sqrt(terms.sum())), float(horizon), self.n)


def kaplan_meier(values, censored) -> KaplanMeier:
    """The Kaplan-Meier curve of runs with these values (event or censoring times), `censored`
    True for a run that never had its event (only a lower bound on its time)."""
    v, c = _arrays(values, censored)
    times = np.unique(v[~c])
    at_risk = np.array([np.count_nonzero(v >= t) for t in times], float)
    events = np.array([np.count_nonzero((v == t) & ~c) for t in times], float)
    survival = np.cumprod(1.0 - events / at_risk) if len(times) else np.zeros(0)
    last = float(v.max()) if len(v) else -math.inf
    return KaplanMeier(times, at_risk, events, survival, len(v), last)


# -- two groups ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class LogRank:
    """The log-rank test of two groups, A and B (Mantel 1966; Peto and Peto 1972): at each
    distinct event time, the 2 x 2 table of (group, event) among the runs at risk; A's observed
    events against those expected if both groups had the same hazard, summed over the tables."""

    observed_a: int
    expected_a: float
    observed_b: int
    expected_b: float
    variance: float  # of O_a - E_a: the hypergeometric variances, summed

    @property
    def z(self) -> float:
        """(O_a - E_a) / sqrt(V): above 0 when A reached the event more often than the same
        hazard would give (A sooner), below 0 when B did; 0 without variance."""
        if self.variance <= 0:
            return 0.0
        return (self.observed_a - self.expected_a) / math.sqrt(self.variance)

    @property
    def p(self) -> float:
        """Two-sided: the chance of a |z| this large if both groups had the same hazard."""
        return 1.0 if self.variance <= 0 else float(2 * _st.norm.sf(abs(self.z)))

    @property
    def hazard_ratio(self) -> float:
        """A's hazard over B's, Peto's one-step estimate exp((O_a - E_a) / V); above 1: A
        sooner. NaN without variance."""
        if self.variance <= 0:
            return math.nan
        return math.exp((self.observed_a - self.expected_a) / self.variance)

    @property
    def sooner(self) -> str | None:
        """Which way the data lean: "a", "b", or None (exactly as expected)."""
        diff = self.observed_a - self.expected_a
        return None if abs(diff) < 1e-12 else ("a" if diff > 0 else "b")

    def describe(self, a: str = "A", b: str = "B") -> str:
        """ "log-rank p = 0.29, two-sided; the data lean to B sooner (A: 6 reached where 7.9
        were expected under one hazard)"."""
        head = f"log-rank p = {self.p:.2g}, two-sided"
        if self.variance <= 0:
            return head + "; no event to compare"
        lean = {"a": f"{a} sooner", "b": f"{b} sooner", None: "neither way"}[self.sooner]
        return (
            f"{head}; the data lean to {lean} ({a}: {self.observed_a} reached where "
            f"{self.expected_a:.1f} were expected under one hazard)"
        )


def logrank(a_values, a_censored, b_values, b_censored) -> LogRank:
    """The log-rank test of groups A and B (see `LogRank`)."""
    va, ca = _arrays(a_values, a_censored)
    vb, cb = _arrays(b_values, b_censored)
    v, event = np.concatenate([va, vb]), ~np.concatenate([ca, cb])
    in_a = np.arange(len(v)) < len(va)
    e_a, var = 0.0, 0.0
    for t in np.unique(v[event]):
        risk = v >= t
        n, n_a = np.count_nonzero(risk), np.count_nonzero(risk & in_a)
        d = np.count_nonzero((v == t) & event)
        e_a += d * n_a / n
        if n > 1:
            var += d * (n_a / n) * (1 - n_a / n) * (n - d) / (n - 1)
    o_a, o_b = int(np.count_nonzero(~ca)), int(np.count_nonzero(~cb))
    return LogRank(o_a, float(e_a), o_b, float(o_a + o_b - e_a), float(var))


# -- pairs ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairedOrder:
    """Pairs (a_i, b_i) counted by which had its event first, where that is known: both exact
    and different; or one exact at or below the other's censoring value (a run censored at c
    reaches it after c, if ever). A pair whose order censoring hides (both censored, or one
    censored before the other's event) is `unknown`; equal event times are `tied`. The sign
    test uses the ordered pairs only (ties and unknowns left out, and counted)."""

    a_first: int
    b_first: int
    tied: int
    unknown: int
    through_censoring: int  # ordered pairs known only thanks to a censored run's bound

    @property
    def ordered(self) -> int:
        return self.a_first + self.b_first

    @property
    def p_a_first(self) -> float:
        """One-sided exact sign test: the chance of a_first or more of the ordered pairs going
        A's way if either order were as likely (small when A comes first more often)."""
        return float(_st.binom.sf(self.a_first - 1, self.ordered, 0.5)) if self.ordered else 1.0

    @property
    def p_b_first(self) -> float:
        return float(_st.binom.sf(self.b_first - 1, self.ordered, 0.5)) if self.ordered else 1.0

    @property
    def p(self) -> float:
        """Two-sided: twice the smaller one-sided p, at most 1."""
        return min(1.0, 2 * min(self.p_a_first, self.p_b_first))


def pair_order(a: float, a_cens: bool, b: float, b_cens: bool) -> str:
    """ "a" (A's event first), "b", "tie" or "unknown" for one pair."""
    if not a_cens and not b_cens:
        return "tie" if a == b else ("a" if a < b else "b")
    if not a_cens and a <= b:  # B, censored at b >= a, reaches it after b if ever
        return "a"
    if not b_cens and b <= a:
        return "b"
    return "unknown"


def paired_order(a_values, a_censored, b_values, b_censored) -> PairedOrder:
    """Count the pairs (same index: the same seed) by which came first (see `PairedOrder`).
    For pairs, the log-rank test stratified by pair reduces to this count: an ordered pair's
    table adds +-1/2 to O - E with variance 1/4, a tie or an unknown adds nothing
    (tests/test_survival.py)."""
    va, ca = _arrays(a_values, a_censored)
    vb, cb = _arrays(b_values, b_censored)
    if len(va) != len(vb):
        raise ValueError(f"pairs need as many A as B values ({len(va)} and {len(vb)})")
    counts = {"a": 0, "b": 0, "tie": 0, "unknown": 0}
    through = 0
    for x, xc, y, yc in zip(va, ca, vb, cb, strict=True):
        k = pair_order(float(x), bool(xc), float(y), bool(yc))
        counts[k] += 1
        through += k in ("a", "b") and bool(xc or yc)
    return PairedOrder(counts["a"], counts["b"], counts["tie"], counts["unknown"], through)
