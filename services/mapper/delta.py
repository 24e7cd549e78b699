"""The map delta: what one integration changed, in the MapDelta message's field convention."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


class DeltaColumns(NamedTuple):
    """A Delta's columns as one argument of a kernel that fills them (`Delta.columns`)."""

    keys: np.ndarray
    centres: np.ndarray
    labels: np.ndarray
    confidences: np.ndarray
    occupied: np.ndarray
    values: np.ndarray
    alt_labels: np.ndarray
    alt_confidences: np.ndarray


@dataclass
class Delta:
    """Voxels whose state changed in one integration, one row each (no voxel twice).

    - `keys`: int32 voxel indices (ix, iy, iz) = floor(coordinate / resolution);
    - `centres`: float32 voxel centres in the world frame;
    - `labels`, `confidences`: the voxel's fused label (0 = none yet) and its confidence;
    - `occupied`: octree: log-odds > 0; tsdf: surface voxel (zero crossing, `backends/tsdf.py`);
    - `values`: octree: occupancy log-odds; tsdf: signed distance in metres;
    - `alt_labels`, `alt_confidences`: the second most likely class (0 = none) and its
      probability, as far as the back-end keeps one (octree-max: none).
    """

    keys: np.ndarray
    centres: np.ndarray
    labels: np.ndarray
    confidences: np.ndarray
    occupied: np.ndarray
    values: np.ndarray
    # a back-end that keeps no second class (an out-of-tree one written before) may leave them out
    alt_labels: np.ndarray | None = None
    alt_confidences: np.ndarray | None = None

    def __post_init__(self):
        n = int(self.keys.shape[0])
        if self.alt_labels is None:
            self.alt_labels = np.zeros(n, np.uint16)
        if self.alt_confidences is None:
            self.alt_confidences = np.zeros(n, np.float32)

    def __len__(self) -> int:
        return int(self.keys.shape[0])

    @classmethod
    def empty(cls, n: int = 0) -> Delta:
        """n rows, uninitialised (a kernel fills them); no rows by default."""
        return cls(
            np.empty((n, 3), np.int32),
            np.empty((n, 3), np.float32),
            np.empty(n, np.uint16),
            np.empty(n, np.float32),
            np.empty(n, np.uint8),
            np.empty(n, np.float32),
            np.empty(n, np.uint16),
            np.empty(n, np.float32),
        )

    def columns(self) -> DeltaColumns:
        """The same arrays (not copies), for a kernel to fill."""
        return DeltaColumns(
            self.keys,
            self.centres,
            self.labels,
            self.confidences,
            self.occupied,
            self.values,
            self.alt_labels,
            self.alt_confidences,
        )

    def subset(self, mask: np.ndarray) -> Delta:
        return Delta(
            self.keys[mask],
            self.centres[mask],
            self.labels[mask],
            self.confidences[mask],
            self.occupied[mask],
            self.values[mask],
            self.alt_labels[mask],
            self.alt_confidences[mask],
        )
