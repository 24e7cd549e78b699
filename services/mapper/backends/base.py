"""What every mapping back-end is: a voxel map on the hashed block grid that integrates one
labelled cloud at a time and reports the voxels it changed.

A back-end declares, as class attributes, its registry `name`, the `values_kind` of its deltas
(what `MapDelta.values` holds: "log_odds" or "signed_distance", so that consumers need no back-end
names), and the config sub-section it takes (`config_class`, found at `[mapper.<config_key>]`).
It is built by `SemanticMap`, which checks every input first: back-ends trust their arguments.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from smana.services.mapper.block_grid import OBSERVED, BlockGrid
from smana.services.mapper.delta import Delta


class MapBackend(ABC):
    """Base class of the back-ends. Subclasses set the class attributes, `fields()` (the per-voxel
    columns, one of them `flags` with the `OBSERVED` bit), `integrate`, `rows` and
    `occupied_index`; the rest (queries, counters, save/restore through `grid`) is shared."""

    name: ClassVar[str]
    values_kind: ClassVar[str]  # "log_odds" | "signed_distance"
    config_key: ClassVar[str | None] = None  # its sub-section of MapperConfig, e.g. "octree"
    # that section's class, a dataclass (a config `Section`): saved maps store it; None: no
    # parameters
    config_class: ClassVar[type | None] = None
    # drop points outside the map's key range before `integrate` (a back-end whose kernel does
    # not skip such rays itself)
    clip_to_extent: ClassVar[bool] = False
    # carves free space over `raycast_range_m` before a hit (0: the whole ray)
    uses_ray_length: ClassVar[bool] = False

    def __init__(
        self,
        config: Any,
        *,
        resolution_m: float,
        max_range_m: float,
        raycast_range_m: float,
        class_ids: np.ndarray,
        block_bits: int = 3,
    ):
        self.config = config
        self.resolution_m = float(resolution_m)
        self.max_range_m = float(max_range_m)
        self.raycast_range_m = float(raycast_range_m)  # [mapper] raycast_range_m; 0: whole ray
        self.class_ids = np.asarray(class_ids, np.uint16)  # the classes worth fusing, sorted
        self.grid = BlockGrid(block_bits, self.fields())
        self.last_updates = 0  # voxel updates of the last cloud (for benchmarks)
        self.n_observed = 0  # kept up to date by integrate: stats() never scans the map
        self.n_occupied = 0

    @classmethod
    def default_config(cls) -> Any:
        return cls.config_class() if cls.config_class is not None else None

    # -- what a back-end implements ----------------------------------------------------------

    @abstractmethod
    def fields(self) -> dict[str, tuple[Any, tuple[int, ...]]]:
        """Per-voxel columns: name -> (dtype, trailing shape). Saved maps store them by name."""

    @abstractmethod
    def integrate(self, points, labels, confs, origin) -> Delta:
        """One cloud: float32 N x 3 world points, uint16 labels, float32 confidences, float32
        origin (all checked, contiguous, inside the extent when `clip_to_extent`)."""

    @abstractmethod
    def rows(self, g: np.ndarray) -> Delta:
        """The Delta rows of global voxel indices `g`."""

    @abstractmethod
    def occupied_index(self) -> np.ndarray:
        """Global indices of the occupied (octree) or surface (tsdf) voxels."""

    # -- shared ------------------------------------------------------------------------------

    def observed_index(self) -> np.ndarray:
        return np.flatnonzero(self.grid.used("flags") & OBSERVED)

    def known(self, g: np.ndarray) -> np.ndarray:
        return (self.grid.cols["flags"][g] & OBSERVED).astype(bool)

    def recount(self) -> None:
        """Recompute the counters from the columns (after a load)."""
        self.n_observed = int(self.observed_index().shape[0])
        self.n_occupied = int(self.occupied_index().shape[0])

    def bytes_per_voxel(self) -> int:
        return sum(
            col.dtype.itemsize * int(np.prod(col.shape[1:])) for col in self.grid.cols.values()
        )
