"""The slow, obvious reference of the planner's enter costs, for the tests: the risk pricing of
docs/risk.md node by node in plain Python (`risk_enter_costs`, `cvar`) and the clearance cost
(`add_clearance`). Written apart from common/risk.py on purpose: the planner's kernels and the
costmaps price with that one definition, and a reference that called it would check nothing."""

from __future__ import annotations

import numpy as np


def cvar(atoms, alpha) -> float:
    """CVaR at level alpha of a discrete cost distribution [(cost, probability), ...] summing to
    1: the mean cost of the worst alpha of the probability mass."""
    left, total = alpha, 0.0
    for cost, prob in sorted(atoms, key=lambda a: -a[0]):
        take = min(prob, left)
        if take > 0:
            total += take * cost
            left -= take
    return total / alpha


def risk_enter_costs(
    labels, flags, alt, p_label, p_alt, classes, config, allow_unknown=False, resolution_m=0.2
):
    """Enter cost of every node of dense windows (labels, flags and the risk layers) under
    `config` (a PlannerConfig), one node at a time: the definitions of docs/risk.md as written,
    plus the clearance cost (`add_clearance`) for nodes of `resolution_m`."""
    from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE

    t_f = config.t_f
    out = np.full(np.shape(labels), np.inf)
    for (i, j), lab in np.ndenumerate(labels):
        f = int(flags[i, j])
        if f & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE):
            continue
        if f & FLAG_DOUBTFUL:  # an unconfirmed obstacle class: dear, whatever the risk mode
            out[i, j] = t_f * config.doubtful_cost
            continue
        if not f & FLAG_KNOWN:
            out[i, j] = config.unknown_cost * t_f if allow_unknown else np.inf
            continue
        lab = int(lab)
        T = classes.cost_lut[lab] if lab < classes.size else np.inf
        if lab == 0 and allow_unknown:
            T = config.unknown_cost
        if not np.isfinite(T):
            continue  # a label that cannot be entered: closed in every mode
        if config.risk == "label":
            out[i, j] = t_f * T
            continue
        dist = {lab: int(p_label[i, j]) / 255}
        a = int(alt[i, j])
        if 0 < a < classes.size and int(p_label[i, j]) < 255:
            dist[a] = dist.get(a, 0.0) + min(int(p_alt[i, j]), 255 - int(p_label[i, j])) / 255
        other = 1.0 - sum(dist.values())
        cost = {lab: T}
        p_forbidden = 0.0
        for c in dist:
            if c != lab:
                cost[c] = classes.cost_lut[c]
                if not np.isfinite(cost[c]):
                    p_forbidden += dist[c]
                    cost[c] = config.risk_forbidden_cost
        atoms = [(t_f * cost[c], dist[c]) for c in dist] + [(t_f * config.unknown_cost, other)]
        expected = sum(c * p for c, p in atoms)
        if config.risk == "cvar":
            out[i, j] = cvar(atoms, config.risk_alpha)
        elif config.risk == "chance":
            p_forbidden += other * config.risk_other_forbidden
            out[i, j] = np.inf if p_forbidden > config.max_risk else expected
        else:
            out[i, j] = expected
    return add_clearance(out, flags, config, resolution_m)


def add_clearance(enter, flags, config, resolution_m):
    """The clearance cost added to finite enter costs, node by node: t_f * clearance_cost at a
    blocked node's side, falling linearly to 0 at (ring + 1) nodes from the nearest one (ring =
    clearance_m in nodes, rounded)."""
    from smana.common.navgrid import FLAG_OBSTACLE, FLAG_SAFETY_ZONE

    ring = int(round(config.clearance_m / resolution_m))
    if ring <= 0 or config.clearance_cost == 0:
        return enter
    out = np.array(enter, float)
    blocked = np.argwhere((np.asarray(flags) & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) != 0)
    for (i, j), c in np.ndenumerate(out):
        if not np.isfinite(c) or len(blocked) == 0:
            continue
        near = np.abs(blocked - (i, j)).max(axis=1) <= ring  # within the ring's square
        if near.any():
            d = float(np.hypot(*(blocked[near] - (i, j)).T).min())
            if d < ring + 1:
                out[i, j] = c + config.t_f * config.clearance_cost * (ring + 1 - d) / ring
    return out
