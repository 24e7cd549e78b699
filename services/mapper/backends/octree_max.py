"""Back-end `octree-max`: OctoMap occupancy with Semantic Octomap's max label fusion (one label
and its confidence per voxel; see `occupancy.py` for the rule)."""

from __future__ import annotations

from smana.services.mapper.backends.occupancy import FUSION_MAX, OccupancyBackend


class OctreeMax(OccupancyBackend):
    name = "octree-max"
    fusion = FUSION_MAX
    n_top = 1
