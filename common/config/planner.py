"""[planner] config section: what `Planner` (services/planner/planner.py) receives as it is.

h_f, t_f, max_step_m, unknown_cost and heuristic are the defaults of every path query; a
PathRequest may override them one by one (checked by these same limits). The risk_* fields and
max_risk say how a node's class distribution (the graph's risk layers) becomes its enter cost:
docs/risk.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import Section, param

# the A* heuristics (services/planner/astar.py implements each)
Heuristic = Literal["octile", "euclidean"]
# how a node's class distribution becomes its enter cost (services/planner/planner.py, docs/risk.md)
Risk = Literal["expected", "cvar", "chance", "label"]


@dataclass
class PlannerConfig(Section, section="planner"):
    h_f: float = param(0.1, ge=0, lt=math.inf)  # weight of the height difference (paper eq. 1)
    t_f: float = param(0.8, ge=0, lt=math.inf)  # weight of the traversability cost T(l)
    max_step_m: float = param(0.3, gt=0, lt=math.inf)  # a steeper step is not traversable
    # T(l) of unknown nodes when a request allows them
    unknown_cost: float = param(2.0, ge=0, lt=math.inf)
    # T(l) of a doubtful node: an obstacle class the navigation graph has not confirmed (no height,
    # too few agreeing views; navgraph.semantic_confirm). Dear, so that paths go round it when
    # they can, but passable, so that a few wrong labels do not wall the robot in.
    doubtful_cost: float = param(10.0, ge=0, lt=math.inf)
    # T(l) added to a node beside the safety zone (or an obstacle), falling linearly to 0 at
    # clearance_m from it: paths keep off the zone's edge where there is room (Nav2's inflation
    # cost beyond the inscribed radius), so that a robot whose pose is a few centimetres off does
    # not put its body on what the zone was drawn round. 0: paths hug the zone as before.
    clearance_cost: float = param(1.0, ge=0, lt=math.inf)
    clearance_m: float = param(0.4, ge=0, le=2.0)
    # Both are exact (admissible and consistent). "euclidean" is the paper's d(n, g); "octile"
    # (octile distance + cheapest enter cost per step) expands 3-5x fewer nodes.
    heuristic: Heuristic = "octile"
    # "expected": sum of p * T over the node's classes; "cvar": mean T of its worst risk_alpha
    # probability mass; "chance": closed when P(forbidden class) > max_risk, else "expected";
    # "label" (the default until the risk experiment chooses a mode): the label's T alone, the
    # distribution ignored (the planner before risk-aware planning, so the paper's results are
    # unchanged).
    # A node whose distribution is certain (or a graph without risk layers) costs t_f * T(l) in
    # every mode, as before.
    risk: Risk = "label"
    risk_alpha: float = param(0.2, gt=0, le=1)  # CVaR level: the worst share of probability mass
    max_risk: float = param(0.1, ge=0, le=1)  # chance: the largest P(forbidden) a node may have
    # T given to the mass of a forbidden class (infinite cost, e.g. water) in "expected" and
    # "cvar": infinity would close any node with the least doubt (and make CVaR all-or-nothing)
    risk_forbidden_cost: float = param(20.0, ge=0, lt=math.inf)
    # the share of a node's unnamed mass (1 - p_label - p_alt) that "chance" counts as forbidden:
    # 1 bounds P(forbidden) whatever that mass is; "expected" and "cvar" price it at unknown_cost
    risk_other_forbidden: float = param(1.0, ge=0, le=1)
    graph_sync_timeout_s: float = param(5.0, gt=0)  # asking navgraph for the graph at start
