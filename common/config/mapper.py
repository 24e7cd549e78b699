"""[mapper] config section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config._schema import ConfigError, Section, param

Backend = Literal["octree-max", "octree-bayes", "tsdf"]


@dataclass
class MapperConfig(Section, section="mapper"):
    backend: Backend = "octree-max"
    resolution_m: float = param(0.1, gt=0)
    max_range_m: float = param(10.0, gt=0)
    raycast_range_m: float = param(1.0, ge=0)  # free space carved before a hit; 0 = whole ray
    inputs: list[str] = param(["cloud"])  # "cloud" and/or "scan"
    autosave_period_s: float = param(30.0, ge=0)  # 0 = only on shutdown
    load: str = ""  # resume from this map file; "auto" = save_path when it exists
    save_path: str = ""  # "" = <run_dir>/map.npz (no autosave without a run dir)
    # OctoMap sensor model (its defaults) and Semantic Octomap fusion constants
    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    max_same_gain: float = 0.5  # same label: c += gain * c_obs * (1 - c)
    max_disagree_factor: float = 0.9  # other label: the winner's confidence times this
    # TSDF (voxblox fast integrator, Kimera semantics)
    tsdf_truncation_voxels: float = param(2.0, gt=0)
    tsdf_label_probability: float = 0.9
    tsdf_max_weight: float = param(10000.0, gt=0)

    def validate(self) -> None:
        for name in self.inputs:
            if name not in ("cloud", "scan"):
                raise ConfigError(f"mapper.inputs: 'cloud' and/or 'scan', got {name!r}")
        if not self.inputs:
            raise ConfigError("mapper.inputs: at least one of 'cloud', 'scan'")
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "tsdf_label_probability"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ConfigError(f"mapper.{name}: expected 0 < p < 1, got {getattr(self, name)}")
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise ConfigError("mapper.prob_miss / prob_hit: need prob_miss < 0.5 < prob_hit")
        if not self.clamp_min < 0.5 < self.clamp_max:
            raise ConfigError("mapper.clamp_min / clamp_max: need clamp_min < 0.5 < clamp_max")
        if not 0.0 <= self.max_same_gain <= 1.0:
            raise ConfigError(f"mapper.max_same_gain: expected 0..1, got {self.max_same_gain}")
        if not 0.0 < self.max_disagree_factor <= 1.0:
            raise ConfigError(
                f"mapper.max_disagree_factor: expected (0, 1], got {self.max_disagree_factor}"
            )
