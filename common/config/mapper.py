"""[mapper] config section, with one sub-section per back-end family ([mapper.octree],
[mapper.tsdf]). The back-end cores receive these sub-sections as they are.

`backend` is a name from the mapper's back-end registry (`services/mapper/backends/`) or a
`module:Class` spec of an out-of-tree one; the registry checks it (common never imports services):
`smana mapper` and `smana up` do so before anything starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config._schema import ConfigError, Section, param, table


@dataclass
class OctreeConfig(Section, section="mapper.octree"):
    """OctoMap's sensor model (its own defaults) and Semantic Octomap's label fusion constants,
    for `octree-max` and `octree-bayes`."""

    prob_hit: float = param(0.7, gt=0, lt=1)
    prob_miss: float = param(0.4, gt=0, lt=1)
    clamp_min: float = param(0.1192, gt=0, lt=1)
    clamp_max: float = param(0.971, gt=0, lt=1)
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

    truncation_voxels: float = param(2.0, gt=0)
    max_weight: float = param(10000.0, gt=0)
    min_range_m: float = param(0.1, ge=0)  # closer points are skipped
    start_voxel_subsampling: float = param(2.0, ge=0)  # voxblox default; 0 disables it
    use_weight_dropoff: bool = True
    label_probability: float = param(0.9, gt=0, lt=1)  # Kimera: p of the measured label
    # Surface extraction: voxels (and their sign-change neighbours) need at least this weight
    # (about the number of rays that reached them, less the drop-off behind the surface).
    # voxblox's mesh default is 1e-4, every voxel a ray reached; 3 is the ablation's choice
    # (docs/experiments.md): under 10 cm / 1.1 deg pose noise a crossing seen once or twice is
    # mostly a misplaced one, and requiring 3 cut the error the noise adds from 56 to 22 mm
    # (octree-max: 51 mm) at no cost without noise (18.3 vs 17.8 mm). A surface must then be
    # seen by 3 rays before it reaches the map and the graph.
    min_weight: float = param(3.0, gt=0)


@dataclass
class MapperConfig(Section, section="mapper"):
    backend: str = "octree-max"  # a registry name or a module:Class spec (see the docstring)
    # A MapDelta carries 0.001 .. 100 m (common/messages.py): finer is refused in validate()
    resolution_m: float = param(0.1, gt=0, le=100.0)
    max_range_m: float = param(10.0, gt=0)
    raycast_range_m: float = param(1.0, ge=0)  # free space carved before a hit; 0 = whole ray
    inputs: list[str] = param(["cloud"])  # "cloud" and/or "scan"
    autosave_period_s: float = param(30.0, ge=0)  # 0 = only on shutdown
    load: str = ""  # resume from this map file; "auto" = save_path when it exists
    save_path: str = ""  # "" = <run_dir>/map.npz (no autosave without a run dir)
    # What `mapper/save` queries may leave beside save_path: .npz files, and their megabytes
    # (the autosave itself is never refused). A save past either is refused, counted `quota`.
    save_max_files: int = param(16, ge=1)
    save_max_mb: float = param(2048.0, gt=0)
    # What the map is made of: "clouds", the robot's own clouds (`inputs`); "fleet", the map
    # deltas of every `fleet.robots` member, merged into one map (services/mapper/fleet.py;
    # run under the fleet's name, `--robot fleet`)
    source: Literal["clouds", "fleet"] = "clouds"
    octree: OctreeConfig = table(OctreeConfig)
    tsdf: TsdfConfig = table(TsdfConfig)

    def validate(self) -> None:
        if self.resolution_m < 1e-3:
            raise ConfigError(f"mapper.resolution_m: at least 0.001 m, got {self.resolution_m!r}")
        if not self.backend.strip():
            raise ConfigError("mapper.backend: expected a back-end name, got ''")
        for name in self.inputs:
            if name not in ("cloud", "scan"):
                raise ConfigError(f"mapper.inputs: 'cloud' and/or 'scan', got {name!r}")
        if not self.inputs:
            raise ConfigError("mapper.inputs: at least one of 'cloud', 'scan'")
