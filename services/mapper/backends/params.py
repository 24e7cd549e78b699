"""The built-in back-ends' parameters, `[mapper.octree]` (octree-max, octree-bayes:
occupancy.py) and `[mapper.tsdf]` (tsdf.py), in a module that imports no numba: the config loader
reads these sections of every config file (backends/__init__.py's `BACKENDS`, `params=`), and
loading a config must not cost the back-ends' kernels. Each back-end names its section as its
`config_class`; an out-of-tree back-end may declare its own anywhere (on its class)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param


@dataclass
class OctreeConfig(Section, section="mapper.octree"):
    """OctoMap's sensor model (its own defaults) and Semantic Octomap's label fusion constants,
    for `octree-max` and `octree-bayes`."""

    prob_hit: float = param(0.7, gt=0, lt=1)  # occupancy probability of a hit
    prob_miss: float = param(0.4, gt=0, lt=1)  # occupancy probability of a pass-through
    clamp_min: float = param(0.1192, gt=0, lt=1)  # occupancy never falls below this
    clamp_max: float = param(0.971, gt=0, lt=1)  # nor rises above this
    # octree-max, same label: "average" is Semantic Octomap's `SemanticsMax::semanticFusion`
    # (c = (c + c_obs) / 2); "gain" is smana's earlier rule, kept as a variant:
    # c += max_same_gain * c_obs * (1 - c), agreement always raising c
    max_fusion: Literal["average", "gain"] = "average"
    max_same_gain: float = param(0.5, ge=0, le=1)  # used by max_fusion = "gain" only
    max_disagree_factor: float = param(0.9, gt=0, le=1)  # other label: the winner's c times this
    # Bayes: keeps c in [eps, 1 - eps] so that no class reaches 0 or 1
    bayes_min_confidence: float = param(1e-3, gt=0, lt=0.5)

    def validate(self) -> None:
        if not self.prob_miss < 0.5 < self.prob_hit:
            raise ConfigError("mapper.octree.prob_miss / prob_hit: need prob_miss < 0.5 < prob_hit")
        if not self.clamp_min < 0.5 < self.clamp_max:
            raise ConfigError(
                "mapper.octree.clamp_min / clamp_max: need clamp_min < 0.5 < clamp_max"
            )


@dataclass
class TsdfConfig(Section, section="mapper.tsdf"):
    """voxblox's fast TSDF integrator and Kimera's semantic label probabilities, for `tsdf`."""

    truncation_voxels: float = param(2.0, gt=0)  # band each side of a point, in voxels
    max_weight: float = param(10000.0, gt=0)  # a voxel's weight is capped here
    min_range_m: float = param(0.1, ge=0)  # closer points are skipped
    start_voxel_subsampling: float = param(2.0, ge=0)  # voxblox default; 0 disables it
    use_weight_dropoff: bool = True  # weights fall behind the surface (voxblox)
    label_probability: float = param(0.9, gt=0, lt=1)  # Kimera: p of the measured label
    # Surface extraction: voxels (and their sign-change neighbours) need at least this weight
    # (about the number of rays that reached them, less the drop-off behind the surface).
    # voxblox's mesh default is 1e-4, every voxel a ray reached; 3 is the ablation's choice
    # (docs/experiments.md): under 10 cm / 1.1 deg pose noise a crossing seen once or twice is
    # mostly a misplaced one, and requiring 3 cut the error the noise adds from 56 to 22 mm
    # (octree-max: 51 mm) for 0.5 mm more without noise (18.3 vs 17.8 mm), at a cost in surface
    # (completeness 22 vs 26 %, a lower F-score at every noise level). A surface must then be
    # seen by 3 rays before it reaches the map and the graph.
    min_weight: float = param(3.0, gt=0)
    # Integration threads: 0 is numba's thread count (every core, or NUMBA_NUM_THREADS), 1 the
    # serial kernel; more than numba's count is capped at it. The map is the same bit for bit.
    threads: int = param(0, ge=0)


BUILT_IN = {"octree-max": OctreeConfig, "octree-bayes": OctreeConfig, "tsdf": TsdfConfig}
