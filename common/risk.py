"""What a node's class distribution costs under `planner.risk`, node by node in numpy: for a
service that shows what the planner pays (the ROS 2 costmap) without the planner's code, and for
a figure of it (`smana experiment risk --synthetic --figure`): `risk_class_costs`, and
`forbidden_probability`, the share of a node the chance constraint counts as forbidden.

The planner prices the same distributions in its numba kernels (services/planner/planner.py,
`_risk_cost`); `tests/test_costmap_risk.py` holds this function equal to the planner's per-node
reference (services/planner/reference.py, `risk_enter_costs`). docs/risk.md gives the model.
"""

from __future__ import annotations

import numpy as np

from smana.common.navgrid import P_SCALE


def risk_class_costs(labels, alt, p_label, p_alt, cost_lut, planner) -> np.ndarray:
    """T of each node, before `t_f`, under `planner.risk` (a PlannerConfig): float64 of the
    shape of `labels`, inf where the label cannot be entered (obstacle or forbidden class, the
    "unknown" class) and where "chance" closes the node. "label" and a certain node (p_label 255)
    cost T(label), as without risk. `cost_lut` is the class table's (or a request's) T by id."""
    t_label, t_alt, p1, p2, rest = _distribution(labels, alt, p_label, p_alt, cost_lut)
    if planner.risk == "label":
        return t_label
    forbidden = np.isinf(t_alt)
    t_alt = np.where(forbidden, planner.risk_forbidden_cost, t_alt)
    t_rest = planner.unknown_cost
    if planner.risk == "cvar":
        out = _cvar3(t_label, p1, t_alt, p2, np.full_like(p1, t_rest), rest, planner.risk_alpha)
    else:
        with np.errstate(invalid="ignore"):  # inf x 0 on labels that cannot be entered
            out = p1 * t_label + p2 * t_alt + rest * t_rest
        if planner.risk == "chance":
            p_forbidden = np.where(forbidden, p2, 0.0) + rest * planner.risk_other_forbidden
            out = np.where(p_forbidden > planner.max_risk, np.inf, out)
    certain = np.asarray(p_label, np.int64) >= P_SCALE
    out = np.where(certain | ~np.isfinite(t_label), t_label, out)
    return out


def forbidden_probability(labels, alt, p_label, p_alt, cost_lut, planner) -> np.ndarray:
    """P(forbidden) of each node as `chance` counts it: the probability of its named classes of
    infinite cost (label, second class) plus its unnamed mass times
    `planner.risk_other_forbidden`; float64 of the shape of `labels`. A node whose label is
    forbidden is closed in every mode whatever this is; a certain node: 1 or 0."""
    t_label, t_alt, p1, p2, rest = _distribution(labels, alt, p_label, p_alt, cost_lut)
    p = np.where(np.isinf(t_label), p1, 0.0) + np.where(np.isinf(t_alt), p2, 0.0)
    return p + rest * planner.risk_other_forbidden


def _distribution(labels, alt, p_label, p_alt, cost_lut):
    """(T(label), T(second class) (0 where none is named), P(label), P(second), unnamed mass)
    per node, probabilities as float64: the three atoms every mode prices."""
    lut = np.asarray(cost_lut, np.float64)
    labels = np.asarray(labels, np.int64)
    t_label = lut[np.minimum(labels, len(lut) - 1)]
    t_label[labels >= len(lut)] = np.inf
    pl = np.asarray(p_label, np.int64)
    named = (np.asarray(alt) > 0) & (np.asarray(alt) < len(lut))
    alt_i = np.where(named, alt, 0).astype(np.int64)
    pa = np.where(named, np.minimum(p_alt, P_SCALE - pl), 0)
    t_alt = np.where(named, lut[alt_i], 0.0)
    return t_label, t_alt, pl / P_SCALE, pa / P_SCALE, (P_SCALE - pl - pa) / P_SCALE


def _cvar3(c0, p0, c1, p1, c2, p2, alpha: float) -> np.ndarray:
    """CVaR at level alpha of three cost atoms per node (the kernel's `_cvar3`, vectorised):
    the mean cost of the worst alpha of the probability mass."""
    c = np.stack([c0, c1, c2], -1).astype(np.float64)
    p = np.stack([p0, p1, p2], -1).astype(np.float64)
    # dearest first; the order among equal costs does not change the mean
    order = np.argsort(-np.nan_to_num(c, posinf=np.finfo(float).max), axis=-1, kind="stable")
    c = np.take_along_axis(c, order, -1)
    p = np.take_along_axis(p, order, -1)
    take0 = np.minimum(p[..., 0], alpha)
    take1 = np.minimum(p[..., 1], alpha - take0)
    take2 = np.maximum(0.0, alpha - take0 - take1)  # what rounding left is the cheapest atom's
    with np.errstate(invalid="ignore"):
        return (take0 * c[..., 0] + take1 * c[..., 1] + take2 * c[..., 2]) / alpha
