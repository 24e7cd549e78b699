"""[planner] config section: what `Planner` (services/planner/planner.py) receives as it is.

h_f, t_f, max_step_m, unknown_cost and heuristic are the defaults of every path query; a
PathRequest may override them one by one (checked by these same limits)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from smana.common.config._schema import Section, param

# the A* heuristics (services/planner/astar.py implements each)
Heuristic = Literal["octile", "euclidean"]


@dataclass
class PlannerConfig(Section, section="planner"):
    h_f: float = param(0.1, ge=0, lt=math.inf)  # weight of the height difference (paper eq. 1)
    t_f: float = param(0.8, ge=0, lt=math.inf)  # weight of the traversability cost T(l)
    max_step_m: float = param(0.3, gt=0, lt=math.inf)  # a steeper step is not traversable
    # T(l) of unknown nodes when a request allows them
    unknown_cost: float = param(2.0, ge=0, lt=math.inf)
    # Both are exact (admissible and consistent). "euclidean" is the paper's d(n, g); "octile"
    # (octile distance + cheapest enter cost per step) expands 3-5x fewer nodes.
    heuristic: Heuristic = "octile"
    graph_sync_timeout_s: float = param(5.0, gt=0)  # asking navgraph for the graph at start
