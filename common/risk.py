"""The risk pricing, written once: what a known node's class distribution costs under
`planner.risk` (expected cost, CVaR, or a chance constraint; docs/risk.md gives the model).

- `RiskModel` (`risk_model`): the [planner] risk fields as the kernels read them;
- `RiskPrices` (`risk_prices`): per class id, what its mass as the second class costs;
- `node_risk_cost` (numba, numbers only): one doubtful node's cost. The planner's enter-cost
  kernels (services/planner/enter_costs.py) inline it per node;
- `risk_class_costs`: the same function over arrays of nodes, for what shows the planner's prices
  without the planner (the ROS 2 costmaps, a figure: `smana experiment risk --synthetic
  --figure`), and `forbidden_probability`, the share of a node the chance constraint counts as
  forbidden.

The tests hold it to a slow, obvious reference written apart on purpose
(tests/support/enter_cost_reference.py: every mode node by node as docs/risk.md writes it; a
reference that called this code would check nothing): the planner's costs
(tests/test_planner_risk.py) and the costmaps' (tests/test_costmap_risk.py).

Note for editors: numba's on-disk cache keys a kernel on its own file only, so the planner's
kernels do not notice a change here: after editing this file, delete
`services/planner/__pycache__/*.nbi` and `*.nbc` (or touch those files).
"""

from __future__ import annotations

import typing
from typing import NamedTuple

import numba
import numpy as np

from smana.common.config.planner import PlannerConfig, Risk
from smana.common.navgrid import P_SCALE

RISK_MODES = typing.get_args(Risk)


class RiskModel(NamedTuple):
    """How the risk kernels turn a node's class distribution into its enter cost: the
    [planner] risk fields, costs already scaled by t_f."""

    mode: int  # index in RISK_MODES: 0 expected, 1 cvar, 2 chance
    alpha: float  # CVaR level
    max_risk: float  # chance: largest P(forbidden) of an open node
    forbidden_cost: float  # t_f * T of a forbidden class's mass (expected, cvar)
    other_cost: float  # t_f * T of the unnamed mass (expected, cvar): unknown_cost
    other_forbidden: float  # share of the unnamed mass counted as forbidden (chance)


def risk_model(p: PlannerConfig, t_f: float | None = None) -> RiskModel:
    """The kernels' view of a (checked) PlannerConfig, its costs scaled by `t_f` (the config's;
    1 for the classes' own T, as the costmaps show it)."""
    scale = p.t_f if t_f is None else t_f
    return RiskModel(
        RISK_MODES.index(p.risk),
        float(p.risk_alpha),
        float(p.max_risk),
        float(p.risk_forbidden_cost * scale),
        float(p.unknown_cost * scale),
        float(p.risk_other_forbidden),
    )


class RiskPrices(NamedTuple):
    """What the risk kernels price a distribution with: the model and, per class id, what its
    mass as the second class costs, so that no node looks its second class up twice."""

    model: RiskModel
    alt_cost: np.ndarray  # f8 per class id: t_f * T, a forbidden class's at forbidden_cost; id 0: 0
    alt_forbidden: np.ndarray  # f8 per class id: 1 where the class is forbidden, else 0


def risk_prices(model: RiskModel, lut: np.ndarray) -> RiskPrices:
    """The tables of `RiskPrices` for the scaled costs `lut` (+inf where forbidden). Id 0 (and an
    id outside the table, which the kernels read as 0) names no class: its mass is unnamed."""
    forbidden = ~np.isfinite(lut)
    cost = np.where(forbidden, model.forbidden_cost, lut)
    cost[0] = 0.0
    forbidden[0] = False
    return RiskPrices(model, np.ascontiguousarray(cost, np.float64), forbidden.astype(np.float64))


# P(k) = k / 255 for every stored probability k: the division the kernels did per node, done
# once (the same float64 division, so the same bits).
PROB = np.arange(P_SCALE + 1) / P_SCALE


@numba.njit(cache=True)
def cvar3(c0, p0, c1, p1, c2, p2, alpha):
    """CVaR at level alpha of three cost atoms (cost, probability; the probabilities sum to 1):
    the mean cost of the worst alpha of the probability mass."""
    # sort the atoms by cost, dearest first (three compare-and-swaps)
    if c1 > c0:
        c0, p0, c1, p1 = c1, p1, c0, p0
    if c2 > c1:
        c1, p1, c2, p2 = c2, p2, c1, p1
    if c1 > c0:
        c0, p0, c1, p1 = c1, p1, c0, p0
    take0 = min(p0, alpha)
    take1 = min(p1, alpha - take0)
    take2 = max(0.0, alpha - take0 - take1)  # what rounding left is the cheapest atom's
    return (take0 * c0 + take1 * c1 + take2 * c2) / alpha


@numba.njit(cache=True, inline="always")
def node_risk_cost(c_label, c_alt, alt_forbidden, pl, pa, model):
    """Enter cost of a known node whose label costs `c_label` (finite, t_f scaled) and is
    doubtful (pl < 255), given its distribution: P(label) = pl / 255, P(alt) = pa / 255 (0 when
    no class is named; pa + pl <= 255), the rest unnamed; the second class costs `c_alt` and is
    forbidden when `alt_forbidden` is 1. See docs/risk.md. Numbers only: a helper called per node
    that takes an array (or a tuple holding one) pays numba's reference counting per call, which
    was most of the pass (14 ms at 1000 x 1000, half the nodes doubtful)."""
    p1 = PROB[pl]
    p2 = PROB[pa]
    r = PROB[P_SCALE - pl - pa]
    if model.mode == 2:
        pf = p2 * alt_forbidden + r * model.other_forbidden
        if pf > model.max_risk:
            return np.inf
    if model.mode == 1:
        return cvar3(c_label, p1, c_alt, p2, model.other_cost, r, model.alpha)
    return p1 * c_label + p2 * c_alt + r * model.other_cost


def risk_class_costs(labels, alt, p_label, p_alt, cost_lut, planner) -> np.ndarray:
    """T of each node, before `t_f`, under `planner.risk` (a PlannerConfig): float64 of the
    shape of `labels`, inf where the label cannot be entered (obstacle or forbidden class, the
    "unknown" class) and where "chance" closes the node. "label" and a certain node (p_label 255)
    cost T(label), as without risk. `cost_lut` is the class table's (or a request's) T by id.
    Each doubtful node is priced by `node_risk_cost`, as the planner prices it."""
    lut = np.asarray(cost_lut, np.float64)
    labels = np.asarray(labels, np.int64)
    if planner.risk == "label":
        t_label = lut[np.minimum(labels, len(lut) - 1)]
        t_label[labels >= len(lut)] = np.inf
        return t_label
    prices = risk_prices(risk_model(planner, t_f=1.0), lut)
    out = np.empty(labels.shape)
    _class_costs(*_flat(labels, alt, p_label, p_alt), lut, prices, out.reshape(-1))
    return out


def forbidden_probability(labels, alt, p_label, p_alt, cost_lut, planner) -> np.ndarray:
    """P(forbidden) of each node as `chance` counts it: the probability of its named classes of
    infinite cost (label, second class) plus its unnamed mass times
    `planner.risk_other_forbidden`; float64 of the shape of `labels`. A node whose label is
    forbidden is closed in every mode whatever this is; a certain node: 1 or 0."""
    lut = np.asarray(cost_lut, np.float64)
    out = np.empty(np.shape(labels))
    other = float(planner.risk_other_forbidden)
    _forbidden(*_flat(labels, alt, p_label, p_alt), lut, other, out.reshape(-1))
    return out


def _flat(labels, alt, p_label, p_alt):
    """The four per-node arrays as the loops below take them: flat int64."""
    return tuple(
        np.ascontiguousarray(a, np.int64).reshape(-1) for a in (labels, alt, p_label, p_alt)
    )


@numba.njit(cache=True, inline="always")
def _second_class(alt, pl, pa, n_lut):
    """A node's second class (0: none, an id outside the table included) and its mass x 255,
    clipped to what the label leaves (P(label) + P(alt) <= 1)."""
    a = alt if alt < n_lut else 0
    return a, (min(pa, P_SCALE - pl) if a > 0 else 0)


@numba.njit(cache=True)
def _class_costs(labels, alt, p_label, p_alt, lut, prices, out):
    """`risk_class_costs` node by node: T(label), and `node_risk_cost` where it is doubtful."""
    model, alt_cost, alt_forbidden = prices
    n_lut = len(lut)
    for k in range(len(labels)):
        c = lut[labels[k]] if labels[k] < n_lut else np.inf
        pl = p_label[k]
        if c < np.inf and pl < P_SCALE:
            a, pa = _second_class(alt[k], pl, p_alt[k], n_lut)
            c = node_risk_cost(c, alt_cost[a], alt_forbidden[a], pl, pa, model)
        out[k] = c


@numba.njit(cache=True)
def _forbidden(labels, alt, p_label, p_alt, lut, other_forbidden, out):
    """`forbidden_probability` node by node."""
    n_lut = len(lut)
    for k in range(len(labels)):
        pl = p_label[k]
        a, pa = _second_class(alt[k], pl, p_alt[k], n_lut)
        label_forbidden = labels[k] >= n_lut or lut[labels[k]] == np.inf
        alt_forbidden = a > 0 and lut[a] == np.inf
        p = PROB[pl] if label_forbidden else 0.0
        p += PROB[pa] if alt_forbidden else 0.0
        out[k] = p + PROB[P_SCALE - pl - pa] * other_forbidden
