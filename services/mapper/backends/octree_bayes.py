"""Back-end `octree-bayes`: OctoMap occupancy with Semantic Octomap's Bayesian label fusion (the
3 most probable classes per voxel; see `occupancy.py` for the rule)."""

from __future__ import annotations

from smana.services.mapper.backends.occupancy import FUSION_BAYES, OccupancyBackend


class OctreeBayes(OccupancyBackend):
    name = "octree-bayes"
    fusion = FUSION_BAYES
    n_top = 3

    def __init__(self, config, **geometry):
        if len(geometry["class_ids"]) < 2:
            raise ValueError("bayes fusion needs at least 2 semantic classes")
        super().__init__(config, **geometry)
