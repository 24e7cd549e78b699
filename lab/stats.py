"""Statistics every experiment reports with: mean and 95 % confidence interval over runs, and a
verdict on a paper claim decided by the intervals, never by one run.

    ci = mean_ci([0.61, 0.55, 0.70, 0.58, 0.66])      # Interval(mean, lo, hi, n)
    verdict_near(ci, 0.60, tolerance=0.10)             # "reproduced" / "not reproduced" / ...
    verdict_less(ci_tsdf, ci_octree)                   # a's interval entirely below b's
    decide_near(paired_ci, 0.28, tolerance=0.10)       # "about +28 points", with its p-values
    decide_sooner_censored(a, ac, b, bc)               # time to an event, censored runs kept
    decide_first_paired(order, "2 robots", "...")      # the same paired per seed (sign test)
    holm_table([d1, d2, ...])                          # the verdict table corrected together

The interval is Student's t on the mean (runs are few: 5 to 10), two-sided at `confidence`.
With fewer than two finite values there is no interval: lo and hi are NaN and every verdict is
"inconclusive". Every decision says which one-sided alternative its p tests (`Decision.tests`)
and how many seeds its rule would need to decide at 80 % power (`Decision.need`, lab/power.py);
the censored estimators are lab/survival.py's.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy import stats as _st

from . import power as _pw
from . import survival as _sv

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

    def share_error_bars(self) -> tuple[float, float]:
        """Error bar lengths below and above the mean of a share, its interval clipped to
        [0, 1] (a t interval can pass 100 %); none without an interval."""
        if not self.defined:
            return 0.0, 0.0
        return self.mean - max(self.lo, 0.0), min(self.hi, 1.0) - self.mean

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


def ratio_ci(a, b, confidence: float = 0.95) -> Interval:
    """mean(a) / mean(b) of paired values (a[i] and b[i] from one seed) with Fieller's interval:
    the ratios R for which the paired t test of a - R b does not reject mean(a - R b) = 0 at
    `confidence`. The interval is defined only when mean(b) is itself clearly away from 0 (the
    set is then bounded); otherwise lo and hi are NaN ("no interval"), as with fewer than two
    pairs. Pairs with a missing value are left out."""
    pairs = [
        (float(x), float(y))
        for x, y in zip(a, b, strict=True)
        if x is not None and y is not None and math.isfinite(x) and math.isfinite(y)
    ]
    n = len(pairs)
    x = np.array([p[0] for p in pairs])
    y = np.array([p[1] for p in pairs])
    ratio = float(x.mean() / y.mean()) if n and y.mean() != 0 else math.nan
    if n < 2 or not math.isfinite(ratio):
        return Interval(ratio, math.nan, math.nan, n, confidence)
    t2 = float(_st.t.ppf(0.5 + confidence / 2, n - 1)) ** 2
    cov = np.cov(x, y, ddof=1) / n  # of the two means
    # (mean_x - R mean_y)^2 <= t^2 var(mean_x - R mean_y): a quadratic in R, <= 0 inside
    qa = y.mean() ** 2 - t2 * cov[1, 1]
    qb = -2 * (x.mean() * y.mean() - t2 * cov[0, 1])
    qc = x.mean() ** 2 - t2 * cov[0, 0]
    disc = qb * qb - 4 * qa * qc
    if qa <= 0 or disc < 0:
        return Interval(ratio, math.nan, math.nan, n, confidence)
    root = math.sqrt(disc)
    return Interval(ratio, (-qb - root) / (2 * qa), (-qb + root) / (2 * qa), n, confidence)


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


# -- rules fixed before the runs (issue 26) -------------------------------------------------------
#
# Every rule below is the interval rule above written as one-sided tests, so that each verdict
# has the p-value that decided it and a table of verdicts can be corrected together (Holm). A
# t interval at `confidence` lies above c exactly when the one-sided test of "mean <= c" has
# p < (1 - confidence) / 2: the same decision, now with its p.

NOT_REPRODUCIBLE_HERE = "not reproducible in this world"


@dataclass(frozen=True)
class Decision:
    """A verdict with the p-values of its two one-sided conclusions: `p_yes` that the claim
    holds (reproduced / met), `p_no` that it does not. `alpha` is the one-sided level each is
    held to: (1 - confidence) / 2, 0.025 for 95 % intervals. `yes` and `no` say in words what
    each test's alternative is ("NBV sooner", "outside the band"), so that a printed p carries
    the direction it tests; `need` is the seeds the rule would need (lab/power.py)."""

    verdict: str
    p_yes: float
    p_no: float
    alpha: float = 0.025
    evidence: str = ""
    yes: str = "the claim holds"
    no: str = "the claim fails"
    need: _pw.Need | None = None

    @property
    def p(self) -> float:
        """The p-value of the conclusion reached (or of the nearer one when inconclusive)."""
        if self.verdict == REPRODUCED:
            return self.p_yes
        if self.verdict == NOT_REPRODUCED:
            return self.p_no
        return min(self.p_yes, self.p_no)

    @property
    def tests(self) -> str:
        """The alternative `p` tests, one-sided: `yes` or `no`, whichever p it is."""
        if self.verdict == REPRODUCED or (
            self.verdict != NOT_REPRODUCED and self.p_yes <= self.p_no
        ):
            return self.yes
        return self.no

    def fields(self) -> dict:
        """What a claim row of a report carries from its decision, beside its own texts: the
        verdict, p and what it tests, and the seeds needed (a dict, for the JSON outputs)."""
        return {
            "verdict": self.verdict,
            "p": self.p,
            "p_tests": self.tests,
            "need": None if self.need is None else asdict(self.need),
        }


def format_p(p: float | None, tests: str | None) -> str:
    """ "0.15 (one-sided: nearest frontier sooner)"; "-" for a claim that is not a test."""
    if p is None:
        return "-"
    return f"{p:.2g} (one-sided: {tests})" if tests else f"{p:.2g} (one-sided)"


def _t_sf(ci: Interval, c: float) -> float:
    """p of the one-sided test "mean <= c" (small when the mean is well above c)."""
    t_star = float(_st.t.ppf(0.5 + ci.confidence / 2, ci.n - 1))
    sem = ci.half_width / t_star
    if sem == 0:
        return 0.0 if ci.mean > c else 1.0
    return float(_st.t.sf((ci.mean - c) / sem, ci.n - 1))


def _t_cdf(ci: Interval, c: float) -> float:
    """p of the one-sided test "mean >= c" (small when the mean is well below c)."""
    t_star = float(_st.t.ppf(0.5 + ci.confidence / 2, ci.n - 1))
    sem = ci.half_width / t_star
    if sem == 0:
        return 0.0 if ci.mean < c else 1.0
    return float(_st.t.cdf((ci.mean - c) / sem, ci.n - 1))


def _decide(p_yes: float, p_no: float, alpha: float, evidence: str = "", **labels) -> Decision:
    if p_yes < alpha:
        v = REPRODUCED
    elif p_no < alpha:
        v = NOT_REPRODUCED
    else:
        v = INCONCLUSIVE
    return Decision(v, p_yes, p_no, alpha, evidence, **labels)


def _undefined(ci: Interval, **labels) -> Decision | None:
    if ci.defined:
        return None
    return Decision(INCONCLUSIVE, 1.0, 1.0, (1 - ci.confidence) / 2, **labels)


def spread(ci: Interval) -> float:
    """The standard deviation of the values behind a t interval (its half-width over t, times
    sqrt(n)); NaN without an interval."""
    if not ci.defined:
        return math.nan
    return ci.half_width / float(_st.t.ppf(0.5 + ci.confidence / 2, ci.n - 1)) * math.sqrt(ci.n)


def _need_t(ci: Interval, edge: float, alpha: float) -> _pw.Need | None:
    """Seeds for a one-sided t test of the interval's mean against `edge`, were the mean and
    spread those measured (whichever side the mean lies: the verdict it points to)."""
    if not ci.defined:
        return None
    sd, delta = spread(ci), abs(ci.mean - edge)
    return _pw.Need(_pw.seeds_t(delta, sd, alpha), "paired t (noncentral t)", delta, sd, n=ci.n)


def decide_near(ci: Interval, target: float, tolerance: float) -> Decision:
    """ "About X": reproduced when the interval lies within X +/- tol (both one-sided tests of the
    two edges reject: TOST), not reproduced when it lies wholly outside the band. The same rule
    decides a paired difference "about +D" (give it the per-seed differences' interval): the
    effect's size is tested, not only its sign."""
    labels = {"yes": "inside the band", "no": "outside the band"}
    alpha = (1 - ci.confidence) / 2
    lo, hi = target - tolerance, target + tolerance
    need = None
    if ci.defined:
        sd = spread(ci)
        if lo < ci.mean < hi:
            d_lo, d_hi = ci.mean - lo, hi - ci.mean
            seeds = _pw.seeds_tost(d_lo, d_hi, sd, alpha)
            how = "TOST (noncentral t, Bonferroni)"
            need = _pw.Need(seeds, how, min(d_lo, d_hi), sd, n=ci.n)
        else:
            need = _need_t(ci, lo if ci.mean <= lo else hi, alpha)
    return _undefined(ci, **labels) or _decide(
        max(_t_sf(ci, lo), _t_cdf(ci, hi)),
        min(_t_cdf(ci, lo), _t_sf(ci, hi)),
        alpha,
        need=need,
        **labels,
    )


def decide_above(
    ci: Interval, c: float = 0.0, yes: str | None = None, no: str | None = None
) -> Decision:
    """A direction the paper gives without a size ("A loses less than B"), tested on the paired
    per-seed difference: reproduced when its interval lies above `c`, not reproduced when below
    (`verdict_positive` with its p-values). `yes` and `no` name the two sides in the claim's
    words (default "above c", "below c")."""
    labels = {"yes": yes or f"above {c:g}", "no": no or f"below {c:g}"}
    alpha = (1 - ci.confidence) / 2
    return _undefined(ci, **labels) or _decide(
        _t_sf(ci, c), _t_cdf(ci, c), alpha, need=_need_t(ci, c, alpha), **labels
    )


def decide_not_worse(
    ci: Interval,
    margin: float,
    higher_is_better: bool = False,
    yes: str | None = None,
    no: str | None = None,
) -> Decision:
    """Non-inferiority of B against A from the per-seed differences B - A, with a margin
    declared before the runs: met when the interval lies on the good side of the margin (below
    +margin where lower is better, above -margin where higher is better), not met when it lies
    wholly on the bad side; a difference whose interval holds 0 is not enough. `yes` and `no`
    name the two sides in the claim's words."""
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    labels = {
        "yes": yes or "not worse by the margin",
        "no": no or "worse by more than the margin",
    }
    alpha = (1 - ci.confidence) / 2
    edge = -margin if higher_is_better else margin
    need = _need_t(ci, edge, alpha)
    if higher_is_better:
        return _undefined(ci, **labels) or _decide(
            _t_sf(ci, edge), _t_cdf(ci, edge), alpha, need=need, **labels
        )
    return _undefined(ci, **labels) or _decide(
        _t_cdf(ci, edge), _t_sf(ci, edge), alpha, need=need, **labels
    )


def decide_in_world(
    ci: Interval, target: float, tolerance: float, world: Interval, what: str = "routes"
) -> Decision:
    """ "About X" where the world itself may rule X out: when the interval of what the world's
    layout alone gives (`world`, e.g. `smana experiment routes`) lies wholly outside X +/- tol,
    the verdict is "not reproducible in this world", with that interval as the evidence;
    otherwise `decide_near`."""
    lo, hi = target - tolerance, target + tolerance
    d = decide_near(ci, target, tolerance)
    if world.defined and (world.lo > hi or world.hi < lo):
        w = f"{world.mean:.4g} [{world.lo:.4g}, {world.hi:.4g}]"
        ev = f"{what}: {w}, wholly outside [{lo:.4g}, {hi:.4g}]"
        return replace(d, verdict=NOT_REPRODUCIBLE_HERE, evidence=ev)
    return d


def decide_sooner_censored(
    a_values,
    a_censored,
    b_values,
    b_censored,
    alpha: float = 0.025,
    names: tuple[str, str] = ("A", "B"),
) -> Decision:
    """ "A reaches it sooner (less time, less distance) than B", censored runs kept: the log-rank
    test (lab/survival.py) on the same seed set (the caller passes both arms' runs of the seeds
    where both ran), each side one-sided at `alpha` (the two-sided p is twice the smaller).
    The evidence gives both Kaplan-Meier medians and the test with the side the data lean to;
    the seeds needed are Schoenfeld's, from Peto's hazard ratio and the share that reached."""
    a, b = names
    lr = _sv.logrank(a_values, a_censored, b_values, b_censored)
    ma = _sv.kaplan_meier(a_values, a_censored).median()
    mb = _sv.kaplan_meier(b_values, b_censored).median()

    def f(m):
        return "not reached by half" if m is None else f"{m:.3g}"

    ev = f"Kaplan-Meier medians {f(ma)} vs {f(mb)}; {lr.describe(a, b)}"
    runs = len(np.atleast_1d(a_values)) + len(np.atleast_1d(b_values))
    reached = (lr.observed_a + lr.observed_b) / runs if runs else 0.0
    log_hr = math.log(lr.hazard_ratio) if lr.variance > 0 else 0.0
    need = _pw.Need(
        _pw.seeds_logrank(log_hr, reached, alpha),
        "log-rank (Schoenfeld)",
        log_hr,
        detail=f"hazard ratio {lr.hazard_ratio:.2g}, {100 * reached:.0f} % of runs reached it",
        n=min(len(np.atleast_1d(a_values)), len(np.atleast_1d(b_values))),
    )
    return _decide(
        float(_st.norm.sf(lr.z)),
        float(_st.norm.cdf(lr.z)),
        alpha,
        ev,
        yes=f"{a} sooner",
        no=f"{b} sooner",
        need=need,
    )


def decide_first_paired(
    order: _sv.PairedOrder, yes: str, no: str, alpha: float = 0.025, evidence: str = ""
) -> Decision:
    """ "A comes first" over paired runs (the same seed), censored runs kept: the exact sign
    test over the pairs whose order is known (lab/survival.py `paired_order`: for pairs, the
    log-rank test stratified by seed); ties and pairs whose order censoring hides are left out
    of the test and counted in the evidence. Reproduced when A first significantly often, not
    reproduced when B; the seeds needed are the sign test's at the measured shares."""
    m = order.ordered
    q = max(order.a_first, order.b_first) / m if m else 0.5
    pairs = m + order.tied + order.unknown
    known = m / pairs if pairs else 0.0
    need = _pw.Need(
        _pw.seeds_sign(q, known, alpha),
        "exact sign test",
        q,
        detail=f"{max(order.a_first, order.b_first)} of {m} ordered pairs one way, "
        f"{m} of {pairs} pairs ordered",
        n=pairs,
    )
    return _decide(order.p_a_first, order.p_b_first, alpha, evidence, yes=yes, no=no, need=need)


def holm(pvalues, alpha: float = 0.025) -> tuple[np.ndarray, np.ndarray]:
    """Holm's step-down correction of a family of p-values: (adjusted p-values, rejected).
    Sorted ascending, the i-th smallest (from 0) is held to alpha / (m - i) and the first one
    that fails stops the rest; adjusted p = running max of (m - i) p, capped at 1."""
    p = np.asarray(pvalues, float)
    m = len(p)
    order = np.argsort(p, kind="stable")
    adj = np.empty(m)
    adj[order] = np.minimum(np.maximum.accumulate((m - np.arange(m)) * p[order]), 1.0)
    return adj, adj <= alpha


def holm_table(decisions: list[Decision]) -> list[Decision]:
    """The verdict table corrected together (Holm over every decided claim's p): a reached
    verdict whose adjusted p exceeds its alpha becomes inconclusive; "not reproducible in this
    world" is a fact of the world, not a test, and stays."""
    tested = [i for i, d in enumerate(decisions) if d.verdict != NOT_REPRODUCIBLE_HERE]
    out = list(decisions)
    if not tested:
        return out
    alpha = decisions[tested[0]].alpha
    adj, keep = holm([decisions[i].p for i in tested], alpha)
    for i, a, k in zip(tested, adj, keep, strict=True):
        d = decisions[i]
        verdict = d.verdict if k or d.verdict == INCONCLUSIVE else INCONCLUSIVE
        out[i] = replace(d, verdict=verdict, evidence=f"Holm-adjusted p = {a:.3g}")
    return out
