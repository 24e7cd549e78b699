"""The built-in worlds' parameters, `[sim.garden]` (garden.py and its layouts) and `[sim.ply]`
(cloud.py), in a module that imports neither scipy nor the worlds' geometry: the config loader
reads these sections of every config file (worlds/__init__.py's `WORLDS`, `params=`), and loading
a config must not cost the worlds' code. Each world names its section as its `config_class`; an
out-of-tree world may declare its own anywhere (on its class)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param


@dataclass
class GardenConfig(Section, section="sim.garden"):
    """Knobs of the procedural garden (`sim.world = "garden"`, services/sim/worlds/garden.py).
    The "classic" layout: 12 m x 12 m, terrain and grass in about equal parts, objects scattered
    so that about half of the ground is free once the robot's radius is accounted for (~78 %
    seen from above). The "3drms" layout holds the paper's shares seen from above (`free_share`,
    `terrain_share`); the object frequencies, `clutter`, `min_gap_m`, `spawn_clearance_m` and
    `terrain_fraction` are the classic layout's."""

    # "classic": straight gravel strips across noise patches, objects scattered with gaps (~78 %
    # free from above); "3drms": the paper's statistics (section 4.3), gravel paths between plazas,
    # lawns and densely planted beds (services/sim/worlds/garden_3drms.py); the default, for
    # `smana up` and the experiments alike; "wheel": 3drms's statistics, gravel
    # spokes from a central lawn, grass between them: a way through (garden_wheel.py)
    layout: Literal["3drms", "classic", "wheel"] = "3drms"
    size_m: float = param(12.0, ge=2, le=1000)  # side of the square garden
    ground_resolution_m: float = param(0.1, ge=0.01)  # height field / ground class raster cell
    terrain_fraction: float = param(0.5, ge=0, le=0.9)  # of the ground, terrain rather than grass
    height_amplitude_m: float = param(0.25, ge=0)  # of the ground's smooth relief
    max_slope: float = param(0.15, ge=0)  # rise over run
    # share of the area inside the walls to cover with objects, seen from above; the gap between
    # objects caps what random placement reaches at about 0.2 (the default world is ~80 % free,
    # ~55 % free once grown by a 0.3 m robot radius)
    clutter: float = param(0.35, ge=0, le=0.9)
    min_gap_m: float = param(0.7, ge=0)  # between objects, so the free space stays connected
    spawn_clearance_m: float = param(1.2, ge=0)  # free disk kept around the centre (the start)
    wall_height_m: float = 1.0  # the boundary walls
    wall_thickness_m: float = 0.2  # the boundary walls
    hedges: float = param(0.25, ge=0)  # relative frequency of hedges among the objects
    topiaries: float = param(0.2, ge=0)  # relative frequency of topiaries
    roses: float = param(0.2, ge=0)  # relative frequency of roses
    obstacles: float = param(0.2, ge=0)  # relative frequency of rocks and boxes
    trees: float = param(0.15, ge=0)  # relative frequency of trees
    # layout "3drms" only: targets measured from above over the whole raster, walls included
    free_share: float = param(0.48, gt=0, lt=1)  # top class traversable (paper: 48 %)
    terrain_share: float = param(0.55, ge=0, le=1)  # terrain / traversable (paper: 55 %)
    path_width_m: list[float] = param([1.4, 2.0], gt=0)  # [min, max]; >= 1.2 to be followable
    plaza_clearance_m: float = param(2.6, ge=0)  # object-free disk around the spawn (the centre)
    # the wet garden (the risk experiment, docs/risk.md): share of the whole raster, seen from
    # above, turned from lawn into water (class 9, kind "forbidden": flat, traversable by geometry,
    # never to be entered), in ponds beside the paths and across the lawns. Needs a class table
    # with water (general.class_table = "garden3drms_wet"). 0, the default, is the paper's world.
    water_share: float = param(0.0, ge=0, le=0.3)

    def validate(self) -> None:
        if len(self.path_width_m) != 2 or self.path_width_m[0] > self.path_width_m[1]:
            raise ConfigError(
                f"sim.garden.path_width_m: expected [min, max], got {self.path_width_m}"
            )
        if self.ground_resolution_m > self.size_m / 4:
            got = self.ground_resolution_m
            raise ConfigError(f"sim.garden.ground_resolution_m: at most size_m / 4, got {got}")
        if self.size_m / self.ground_resolution_m > 4000:
            raise ConfigError(
                "sim.garden.ground_resolution_m: the ground grid would exceed 4000 x 4000"
            )
        if self.hedges + self.topiaries + self.roses + self.obstacles + self.trees <= 0:
            raise ConfigError("sim.garden: object frequencies (hedges .. trees) are all 0")


@dataclass
class PlyConfig(Section, section="sim.ply"):
    """A world built from a labelled point cloud (`sim.world = "ply:PATH"`,
    services/sim/worlds/cloud.py): ground from the traversable classes, voxels for the rest."""

    voxel_m: float = param(0.05, gt=0)  # object voxels
    ground_resolution_m: float = param(0.1, gt=0)  # height field / ground class raster cell
    label_field: str = ""  # the PLY vertex property holding labels; "" finds a usual name
    walls: bool = True  # add walls around the cloud's extent
    wall_height_m: float = 1.0  # of those walls
    wall_thickness_m: float = 0.2  # of those walls


BUILT_IN = {"garden": GardenConfig, "ply": PlyConfig}
