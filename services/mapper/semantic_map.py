"""`SemanticMap`: the mapper's library API (no zenoh), one object for every back-end.

    m = SemanticMap(backend="octree-max", resolution_m=0.1, max_range_m=10.0, raycast_range_m=1)
    m = SemanticMap.from_config(config.mapper)   # the same from the [mapper] section, as it is
    delta = m.integrate(points, labels, confidences, origin)   # what changed, voxel by voxel
    m.occupied_voxels(box=((0, 0, -1), (5, 5, 2)))
    m.query(points); m.stats(); m.save("map.npz"); SemanticMap.load("map.npz")
    m.export_ply("map.ply")

Inputs are checked here, in plain Python, and rejected with a ValueError naming the problem; the
back-ends behind (`backends/`, found by name in its registry) and their numba kernels trust what
they get. A back-end takes its own config sub-section (`config`: `[mapper.octree]` for the
octrees, `[mapper.tsdf]` for the TSDF), as it is; left out, that section's defaults.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from smana.common.classes import ClassTable
from smana.common.config.mapper import MapperConfig
from smana.services.mapper import mapfile, voxel_ply
from smana.services.mapper.backends import backend_class
from smana.services.mapper.block_grid import KEY_LIMIT
from smana.services.mapper.delta import Delta
from smana.services.mapper.mapfile import FORMAT_VERSION, LAYER

_DEFAULT = MapperConfig()  # the library's defaults are the config's, declared once there


def smana_version() -> str:
    """The installed smana's version, written into every saved map ("" when not installed)."""
    try:
        return version("smana")
    except PackageNotFoundError:
        return ""


@dataclass
class QueryResult:
    """Per query point: `known` (observed voxel), `occupied`, fused `labels`, `confidences`, and
    `values` (octree: log-odds; tsdf: signed distance in metres; NaN where unknown)."""

    known: np.ndarray
    occupied: np.ndarray
    labels: np.ndarray
    confidences: np.ndarray
    values: np.ndarray


def _semantic_ids(table: ClassTable) -> np.ndarray:
    """Classes that carry a label worth fusing: not `unknown`, not `ignored`."""
    fused = ("traversable", "obstacle", "forbidden")
    return np.array([c.id for c in table.classes.values() if c.kind in fused], np.int64)


class SemanticMap:
    """A semantic 3D voxel map fed with labelled point clouds (world frame)."""

    def __init__(
        self,
        backend: str = _DEFAULT.backend,
        resolution_m: float = _DEFAULT.resolution_m,
        max_range_m: float = _DEFAULT.max_range_m,
        raycast_range_m: float = _DEFAULT.raycast_range_m,
        class_table: ClassTable | str | Path = "garden3drms",
        config: Any = None,
        block_bits: int = 3,
    ):
        """A map from the `[mapper]` section's own fields (`raycast_range_m`: 0 carves the whole
        ray); they are checked by that section, so the library and the config share one set of
        limits (a `ConfigError`, a ValueError, naming the key). `config` is the back-end's own
        section (`[mapper.<config_key>]`); left out, its defaults."""
        cls = backend_class(backend)  # a ValueError naming the known back-ends
        tables = {}
        if config is not None and cls.config_class is not None:
            if not isinstance(config, cls.config_class):
                want, got = cls.config_class.__name__, type(config).__name__
                raise ValueError(f"back-end {backend} takes a {want}, got {got}")
            tables[cls.config_key] = config
        section = MapperConfig(
            backend=backend,
            resolution_m=resolution_m,
            max_range_m=max_range_m,
            raycast_range_m=raycast_range_m,
            **tables,
        )
        self._setup(section, class_table, block_bits)

    @classmethod
    def from_config(
        cls,
        config: MapperConfig,
        class_table: ClassTable | str | Path = "garden3drms",
        block_bits: int = 3,
    ) -> SemanticMap:
        """The map a [mapper] section asks for, given the section as it is (its back-end's
        sub-section included): nothing renamed, nothing checked twice."""
        m = cls.__new__(cls)
        m._setup(config, class_table, block_bits)
        return m

    def _setup(self, section: MapperConfig, class_table, block_bits: int) -> None:
        cls = backend_class(section.backend)
        self.section = section  # the [mapper] section the map was made from
        self.backend = section.backend
        self.values_kind = cls.values_kind  # what the deltas' values hold (MapDelta.values_kind)
        self.resolution_m = section.resolution_m
        self.max_range_m = section.max_range_m
        self.raycast_range_m = section.raycast_range_m  # 0: the whole ray
        self.class_table = (
            class_table if isinstance(class_table, ClassTable) else ClassTable.load(class_table)
        )
        # the back-end's own section ([mapper.<config_key>]), None for one without parameters
        self.config = section.variant(cls.config_key) if cls.config_key else None
        if self.config is None and cls.config_class is not None:
            self.config = cls.default_config()
        self.block_bits = block_bits
        self.class_ids = _semantic_ids(self.class_table)
        # ignored classes (sky, ...) never reach the map; unknown ids update geometry only
        self._ignored = np.zeros(65536, bool)
        self._ignored[: self.class_table.size] = self.class_table.ignored_lut
        self._clip = cls.clip_to_extent
        self._core = cls(
            self.config,
            resolution_m=self.resolution_m,
            max_range_m=self.max_range_m,
            raycast_range_m=self.raycast_range_m,
            class_ids=self.class_ids,
            block_bits=block_bits,
        )
        self.n_integrations = 0
        self.n_points = 0

    # -- integration -----------------------------------------------------------------------

    def integrate(
        self,
        points: np.ndarray,
        labels: np.ndarray,
        confidences: np.ndarray | None = None,
        origin: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> Delta:
        """Integrate one cloud (world-frame points, sensor origin); returns the changed voxels."""
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be N x 3, got shape {pts.shape}")
        n = pts.shape[0]
        if not np.issubdtype(pts.dtype, np.floating):
            raise ValueError(f"points must be floating point, got {pts.dtype}")
        # writable and contiguous: decoded messages are read-only views, and numba would compile
        # (and cache) a second copy of every kernel for read-only arrays
        pts = np.require(pts, np.float32, ["C", "W"])
        if not np.isfinite(pts).all():
            raise ValueError("points contain NaN or inf (drop them first)")
        lab = np.asarray(labels)
        if lab.shape != (n,):
            raise ValueError(f"labels must have shape ({n},), got {lab.shape}")
        if n and not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(f"labels must be integers, got {lab.dtype}")
        if n and (lab.min() < 0 or lab.max() > 65535):
            raise ValueError("labels must be in 0..65535")
        lab = np.require(lab, np.uint16, ["C", "W"])
        if confidences is None:
            conf = np.ones(n, np.float32)
        else:
            conf = np.require(confidences, np.float32, ["C", "W"])
            if conf.shape != (n,):
                raise ValueError(f"confidences must have shape ({n},), got {conf.shape}")
            if n and not (np.isfinite(conf).all() and conf.min() >= 0 and conf.max() <= 1):
                raise ValueError("confidences must be finite and in [0, 1]")
        org = np.asarray(origin, np.float64)
        if org.shape != (3,) or not np.isfinite(org).all():
            raise ValueError(f"origin must be 3 finite numbers, got {origin!r}")
        limit = KEY_LIMIT * self.resolution_m  # OctoMap's 16-bit key range, the map's extent
        if (np.abs(org) >= limit).any():
            raise ValueError(f"origin {org.tolist()} outside the map extent +-{limit:g} m")
        keep = ~self._ignored[lab]
        if self._clip:
            # octrees skip such rays inside the kernel as OctoMap does (a far point beyond the
            # range still carves up to it); other back-ends' keys are only safe inside the extent
            keep &= (np.abs(pts) < limit).all(axis=1)
        if not keep.all():
            pts, lab, conf = pts[keep], lab[keep], conf[keep]
        self.n_integrations += 1
        self.n_points += int(pts.shape[0])
        if pts.shape[0] == 0:
            return Delta.empty()
        return self._core.integrate(pts, lab, conf, org.astype(np.float32))

    # -- queries ---------------------------------------------------------------------------

    def occupied_voxels(self, box=None) -> Delta:
        """Occupied (octree) or surface (tsdf) voxels with labels, optionally inside a box
        ((xmin, ymin, zmin), (xmax, ymax, zmax)) that contains their centres."""
        return self._in_box(self._core.rows(self._core.occupied_index()), box)

    def observed_voxels(self, box=None) -> Delta:
        """Every observed voxel (free ones too) with its value and label, optionally in a box
        (as `occupied_voxels`): the whole map, as a consumer that replaces its copy needs it."""
        return self._in_box(self._core.rows(self._core.observed_index()), box)

    @staticmethod
    def _in_box(rows: Delta, box) -> Delta:
        if box is None:
            return rows
        lo, hi = (np.asarray(b, np.float64) for b in box)
        if lo.shape != (3,) or hi.shape != (3,) or not np.isfinite([lo, hi]).all():
            raise ValueError("box must be ((xmin, ymin, zmin), (xmax, ymax, zmax))")
        inside = ((rows.centres >= lo) & (rows.centres <= hi)).all(axis=1)
        return rows.subset(inside)

    def query(self, points: np.ndarray) -> QueryResult:
        """State of the voxels holding each point."""
        pts = np.asarray(points, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or not np.isfinite(pts).all():
            raise ValueError("query points must be a finite N x 3 array")
        keys = np.floor(pts / self.resolution_m).astype(np.int64)
        g = self._core.grid.lookup(keys)
        n = pts.shape[0]
        known = np.zeros(n, bool)
        hit = g >= 0
        known[hit] = self._core.known(g[hit])
        rows = self._core.rows(g[known])
        out = QueryResult(
            known,
            np.zeros(n, bool),
            np.zeros(n, np.uint16),
            np.zeros(n, np.float32),
            np.full(n, np.nan, np.float32),
        )
        out.occupied[known] = rows.occupied.astype(bool)
        out.labels[known] = rows.labels
        out.confidences[known] = rows.confidences
        out.values[known] = rows.values
        return out

    def stats(self) -> dict:
        grid = self._core.grid
        allocated = grid.n_blocks * grid.voxels_per_block
        observed = self._core.n_observed
        used, reserved = grid.nbytes()
        return {
            "backend": self.backend,
            "resolution_m": self.resolution_m,
            "integrations": self.n_integrations,
            "points": self.n_points,
            "blocks": grid.n_blocks,
            "voxels_allocated": allocated,
            "voxels_observed": observed,
            "voxels_occupied": self._core.n_occupied,
            "bytes_per_voxel_field": self._core.bytes_per_voxel(),
            "bytes_used": used,
            "bytes_reserved": reserved,
            "bytes_per_allocated_voxel": used / allocated if allocated else 0.0,
            # with the growth headroom (columns grow by 1.5x, so at most a third is spare)
            "bytes_reserved_per_allocated_voxel": reserved / allocated if allocated else 0.0,
            "bytes_per_observed_voxel": used / observed if observed else 0.0,
        }

    # -- voxel states (the journal's, services/mapper/journal.py) -----------------------------

    def column_names(self) -> list[str]:
        """The back-end's per-voxel columns (what a saved map and a journal record hold)."""
        return list(self._core.grid.cols)

    def voxel_state(self, keys: np.ndarray) -> dict[str, np.ndarray]:
        """Every column of the voxels at integer keys (N x 3) as the back-end holds them (label
        distributions, weights, flags): what `set_voxel_state` needs to set them again exactly,
        which a `Delta` row is not. Each key must be in an allocated block."""
        keys = np.asarray(keys)
        if keys.ndim != 2 or keys.shape[1] != 3:
            raise ValueError(f"keys must be N x 3, got shape {keys.shape}")
        g = self._core.grid.lookup(keys)
        if (g < 0).any():
            raise ValueError(f"{int((g < 0).sum())} keys are in no allocated block")
        return {k: c[g] for k, c in self._core.grid.cols.items()}

    def set_voxel_state(self, keys: np.ndarray, cols: dict[str, np.ndarray]) -> None:
        """Set every column of the voxels at `keys` (blocks allocated as needed). The map's
        figures (observed, occupied) are stale until `recount()`: call it after a batch."""
        keys = np.asarray(keys)
        if keys.ndim != 2 or keys.shape[1] != 3:
            raise ValueError(f"keys must be N x 3, got shape {keys.shape}")
        if keys.size and (keys.min() < -KEY_LIMIT or keys.max() >= KEY_LIMIT):
            raise ValueError(f"keys must lie in [-{KEY_LIMIT}, {KEY_LIMIT})")
        grid = self._core.grid
        if set(cols) != set(grid.cols):
            raise ValueError(f"columns {sorted(cols)} do not fit back-end {self.backend}")
        for k, v in cols.items():
            col = grid.cols[k]
            if v.dtype != col.dtype or v.shape != (keys.shape[0], *col.shape[1:]):
                raise ValueError(f"column {k}: {v.dtype} {v.shape} does not fit {col.dtype}")
        g = grid.insert(keys)  # may grow the columns: read them after
        for k, v in cols.items():
            grid.cols[k][g] = v

    def recount(self) -> None:
        """Recompute the observed and occupied counts from the columns."""
        self._core.recount()

    # -- persistence -----------------------------------------------------------------------

    def _meta(self) -> dict:
        return {
            "format": FORMAT_VERSION,
            "backend": self.backend,
            "resolution_m": self.resolution_m,
            "max_range_m": self.max_range_m,
            "ray_length_m": self.raycast_range_m or None,  # the file's spelling: None, whole ray
            "class_table": self.class_table.name,
            "class_ids": self.class_ids.tolist(),
            "config": dataclasses.asdict(self.config) if self.config is not None else None,
            "block_bits": self.block_bits,
            "integrations": self.n_integrations,
            "points": self.n_points,
            "smana_version": smana_version(),
        }

    def save(self, path: str | Path, meta: dict | None = None, **extra: np.ndarray) -> Path:
        """Write the map to an .npz file atomically (a crash mid-save keeps the old file).
        `meta` replaces the map's own metadata and `extra` adds arrays (the fleet map's layers);
        `load` reads such a file as a plain map."""
        path = Path(path)
        grid = self._core.grid
        arrays = {f"col_{k}": grid.used(k) for k in grid.cols}
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                meta=np.frombuffer(json.dumps(meta or self._meta()).encode(), np.uint8),
                block_keys=grid.block_keys[: grid.n_blocks],
                **arrays,
                **extra,
            )
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        return path

    @classmethod
    def load(
        cls,
        path: str | Path,
        class_table: ClassTable | str | Path | None = None,
        backend: str | None = None,
        max_bytes: int = mapfile.MAX_MAP_BYTES,
    ) -> SemanticMap:
        """Read a map written by `save`; `class_table` defaults to the bundled one it names.
        Everything in the file is checked before use (`mapfile`); a file that cannot be used is a
        one-line `MapFileError` (a ValueError). The back-end it names must be a registered one,
        or `backend` (a module:Class spec the caller trusts, e.g. its `mapper.backend`)."""
        with mapfile.MapFile(path, max_bytes) as f:
            meta, m = cls._checked(f, class_table, backend)
            grid = m._core.grid
            block_keys, cols = mapfile.read_grid(
                f, "block_keys", "col_", grid.fields, grid.bits, set(grid.loaders)
            )
            # a fleet map's layers are not this map's, but the file is checked whole
            for i in range(len(meta.get("fleet", {}).get("members", ()))):
                mapfile.read_grid(f, f"layer{i}_block_keys", f"layer{i}_", LAYER, grid.bits)
        grid.restore(block_keys, cols)
        m._core.recount()
        m.n_integrations = meta["integrations"]
        m.n_points = meta["points"]
        return m

    @classmethod
    def check_file(
        cls,
        path: str | Path,
        class_table: ClassTable | str | Path | None = None,
        backend: str | None = None,
    ) -> None:
        """Everything `load` checks but the arrays' values (the container, the metadata, every
        array's dtype and shape), without reading more than the metadata: a quick check before
        a service starts. A `MapFileError` (one line) when the file cannot be used."""
        with mapfile.MapFile(path) as f:
            meta, m = cls._checked(f, class_table, backend)
            grid = m._core.grid
            mapfile.check_grid(f, "block_keys", "col_", grid.fields, grid.bits, set(grid.loaders))
            for i in range(len(meta.get("fleet", {}).get("members", ()))):
                mapfile.check_grid(f, f"layer{i}_block_keys", f"layer{i}_", LAYER, grid.bits)

    @classmethod
    def _checked(cls, f: mapfile.MapFile, class_table, backend) -> tuple[dict, SemanticMap]:
        """The checked metadata of an open file and the empty map it describes; the file holds
        exactly the arrays that map needs (and a fleet map's layers)."""
        meta = mapfile.check_meta(f.meta(), f.path, backend)
        m = cls.from_meta(meta, class_table, f.path)
        expected = {"meta", "block_keys", *(f"col_{k}" for k in m._core.grid.fields)}
        if "fleet" in meta:
            expected |= mapfile.layer_names(len(meta["fleet"]["members"]))
        mapfile.check_members(f, expected)
        return meta, m

    @classmethod
    def from_meta(cls, meta: dict, class_table, path) -> SemanticMap:
        """The empty map a checked `meta` describes."""
        backend = backend_class(meta["backend"])
        saved = meta["config"]
        if backend.config_key == "octree" and "max_fusion" not in saved:
            saved = {**saved, "max_fusion": "gain"}  # saved before the rule was a choice
        try:
            m = cls(
                backend=meta["backend"],
                resolution_m=meta["resolution_m"],
                max_range_m=meta["max_range_m"],
                raycast_range_m=meta["ray_length_m"] or 0.0,
                class_table=class_table if class_table is not None else meta["class_table"],
                config=backend.config_class(**saved) if backend.config_class is not None else None,
                block_bits=meta["block_bits"],
            )
        except ValueError as exc:
            raise mapfile.MapFileError(f"{path}: {exc}") from None
        if m.class_ids.tolist() != meta["class_ids"]:
            raise mapfile.MapFileError(
                f"{path}: class table does not match the one the map was built with"
            )
        return m

    def export_ply(self, path: str | Path, class_table: ClassTable | None = None) -> int:
        """Occupied voxel centres with colour, label and confidence; returns the vertex count."""
        table = class_table or self.class_table
        rows = self.occupied_voxels()
        lut = table.colour_lut
        labels = rows.labels.astype(np.int64)
        colours = np.full((len(rows), 3), 255, np.uint8)
        inside = labels < lut.shape[0]
        colours[inside] = lut[labels[inside]]
        voxel_ply.write_ply(path, rows.centres, colours, rows.labels, rows.confidences)
        return len(rows)
