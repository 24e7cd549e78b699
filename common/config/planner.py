"""[planner] config section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config._schema import Section, param


@dataclass
class PlannerConfig(Section, section="planner"):
    h_f: float = param(0.1, ge=0)
    t_f: float = param(0.8, ge=0)
    max_step_m: float = param(0.3, gt=0)
    unknown_cost: float = param(2.0, ge=0)  # T(l) of unknown nodes when a request allows them
    # Both are exact (admissible and consistent). "euclidean" is the paper's d(n, g); "octile"
    # (octile distance + cheapest enter cost per step) expands 3-5x fewer nodes.
    heuristic: Literal["octile", "euclidean"] = "octile"
    graph_sync_timeout_s: float = param(5.0, gt=0)  # asking navgraph for the graph at start
