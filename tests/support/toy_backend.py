"""A toy mapping back-end from outside smana, for the registry tests: the set of voxels that points
fell in, each with the label of the last point that did (no fusion, no free space).

It is what a plugin looks like: one class on `MapBackend`, no edit of smana. Load it by spec,
`--set mapper.backend=toy_backend:LastLabel` with this folder on PYTHONPATH, or in-process with
`backends.register("toy-last-label", LastLabel)`.
"""

from __future__ import annotations

import numpy as np

from smana.services.mapper.backends import MapBackend
from smana.services.mapper.block_grid import OBSERVED
from smana.services.mapper.delta import Delta


class LastLabel(MapBackend):
    name = "toy-last-label"
    values_kind = "signed_distance"  # every voxel is a surface voxel: distance 0
    clip_to_extent = True  # keys are computed here, not by a kernel that skips far points

    def fields(self):
        return {"label": (np.uint16, ()), "flags": (np.uint8, ())}

    def integrate(self, points, labels, confs, origin) -> Delta:
        g = self.grid.insert(np.floor(points / self.resolution_m).astype(np.int64))
        # the last point of each voxel: first occurrence in the reversed order
        voxels, first_rev = np.unique(g[::-1], return_index=True)
        last = g.shape[0] - 1 - first_rev
        flags, label = self.grid.cols["flags"], self.grid.cols["label"]
        new = int(np.count_nonzero((flags[voxels] & OBSERVED) == 0))
        label[voxels] = labels[last]
        flags[voxels] |= OBSERVED
        self.n_observed += new
        self.n_occupied += new
        self.last_updates = int(voxels.shape[0])
        return self.rows(voxels)

    def rows(self, g: np.ndarray) -> Delta:
        g = np.asarray(g, np.int64)
        keys = self.grid.coords(g)
        n = g.shape[0]
        return Delta(
            keys.astype(np.int32),
            ((keys + 0.5) * self.resolution_m).astype(np.float32),
            self.grid.cols["label"][g],
            np.ones(n, np.float32),
            np.ones(n, np.uint8),
            np.zeros(n, np.float32),
        )

    def occupied_index(self) -> np.ndarray:
        return self.observed_index()
