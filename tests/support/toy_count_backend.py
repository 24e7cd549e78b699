"""A toy mapping back-end with parameters of its own, from outside smana: each voxel counts the
points that fell in it and is occupied from `min_hits` of them on; its value is the count times
`weight`, its label the last point's.

It is what a plugin with parameters looks like: this one file, no edit of smana. The parameters
are a config `Section` declared beside the back-end (`config_key`, `config_class`), so the config
loader reads them from `[mapper.toy_count]` (TOML or `--set mapper.toy_count.min_hits=3`) once
the back-end is named, by spec (`mapper.backend = "tests.support.toy_count_backend:ToyCount"`)
or after `backends.register("toy-count", ToyCount)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smana.common.config import Section, param
from smana.services.mapper.backends import MapBackend
from smana.services.mapper.block_grid import OBSERVED
from smana.services.mapper.delta import Delta


@dataclass
class ToyCountConfig(Section, section="mapper.toy_count"):
    min_hits: int = param(2, ge=1)  # points a voxel needs to be occupied
    weight: float = param(1.0, gt=0)  # a voxel's value: its count times this


class ToyCount(MapBackend):
    name = "toy-count"
    values_kind = "signed_distance"
    config_key = "toy_count"
    config_class = ToyCountConfig
    clip_to_extent = True

    def fields(self):
        return {"count": (np.uint32, ()), "label": (np.uint16, ()), "flags": (np.uint8, ())}

    def integrate(self, points, labels, confs, origin) -> Delta:
        g = self.grid.insert(np.floor(points / self.resolution_m).astype(np.int64))
        voxels, first_rev, counts = np.unique(g[::-1], return_index=True, return_counts=True)
        cols = self.grid.cols
        cols["count"][voxels] += counts.astype(np.uint32)
        cols["label"][voxels] = labels[len(g) - 1 - first_rev]  # the last point's
        cols["flags"][voxels] |= OBSERVED
        self.recount()  # a toy: the counters from the columns, every cloud
        return self.rows(voxels)

    def rows(self, g) -> Delta:
        keys, n = self.grid.coords(g), len(g)
        centres = ((keys + 0.5) * self.resolution_m).astype(np.float32)
        count = self.grid.cols["count"][g]
        occupied = (count >= self.config.min_hits).astype(np.uint8)
        values = (count * self.config.weight).astype(np.float32)
        label = self.grid.cols["label"][g]
        return Delta(
            keys.astype(np.int32), centres, label, np.ones(n, np.float32), occupied, values
        )

    def occupied_index(self):
        index = self.observed_index()
        return index[self.grid.cols["count"][index] >= self.config.min_hits]
