"""`FleetMap`: one semantic map merged from the map deltas of several robots (no zenoh).

    fm = FleetMap(config.mapper, ["r1", "r2"], fleet=config.fleet)
    delta = fm.apply("r1", centres, labels, confidences, values)   # one member's MapDelta rows
    delta = fm.replace("r2", centres, labels, confidences, values) # its whole map (a resync)
    fm.occupied_voxels(); fm.query(points); fm.stats(); fm.save(path); FleetMap.load(path, ...)

Each member has a layer: the latest state it reported of every voxel, in its own frame (a
MapDelta carries absolute voxel states, not increments, so a later row replaces an earlier one).
The merged voxel is a pure function of the layers, recomputed for the voxels a delta touched, so
the merged map does not depend on the order in which the members' deltas arrive:

- occupancy: the sum of the members' log-odds, clamped to [clamp_min, clamp_max] as the back-end
  clamps. Integrating robot B's clouds into robot A's map adds B's hit and miss log-odds to A's,
  so this is the back-end's own rule; it is exact as long as no member's value was clamped (a
  clamped member lost updates that the sum cannot recover). Occupied = merged log-odds > 0.
- labels: the back-end's own fusion rule (`OccupancyBackend.fuse_labels`, the kernels the cloud
  path uses), fed each member's (label, confidence) as one observation, starting from an
  unlabelled voxel, in a canonical order: by confidence (ascending: the most confident comes
  last), ties by member index. A member whose voxel has label 0 (none) adds occupancy only.
- frame: `fleet.frame = "world"` takes the centres as they are; "start_pose" moves each member's
  centres by its `fleet.start_poses` entry [x, y, yaw] (SE(2), z unchanged) and re-voxelises them
  in the fleet grid; source voxels of one member that fall into one fleet voxel are fused by the
  same rules (their log-odds add up).

A voxel that no member reports any more (a layer replaced by a snapshot without it) becomes
unknown again; its delta row says free (log-odds 0, label 0).

Only occupancy back-ends (values "log_odds") can be merged: a MapDelta carries no TSDF weights.
The merged map lives in the back-end's own core (a `SemanticMap`), so queries, snapshots and
stats are the mapper's; `save` writes a map file that `SemanticMap.load` reads as the merged map
and that `FleetMap.load` reads with its layers, so a restarted fleet mapper resumes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from smana.common.classes import ClassTable
from smana.common.config import ConfigError
from smana.common.config.fleet import FleetConfig
from smana.common.config.mapper import MapperConfig
from smana.services.mapper import mapfile
from smana.services.mapper.backends import backend_class
from smana.services.mapper.backends.occupancy import sensor_model
from smana.services.mapper.block_grid import KEY_LIMIT, OBSERVED, BlockGrid
from smana.services.mapper.delta import Delta
from smana.services.mapper.semantic_map import QueryResult, SemanticMap

HAS = np.uint8(1)  # a layer's flag: the member reported this voxel
_LAYER_FIELDS = mapfile.LAYER  # a layer's columns, as the map file stores them
# A source voxel whose centre lands in a fleet voxel has its centre within res / sqrt(2) of that
# voxel's back-projected centre on each axis: an interval shorter than 2 voxels, so 2 x 2
# candidate source voxels from the first key it may hold (the margin covers rounding)
_REACH = np.sqrt(0.5) + 1e-6
_AROUND = np.array([[dx, dy, 0] for dx in (0, 1) for dy in (0, 1)], np.int64)


def _unique_keys(keys: np.ndarray) -> np.ndarray:
    """The distinct rows of int64 voxel keys inside the key range, sorted (packed in 16 bits an
    axis: one 1-D sort, many times faster than `np.unique(axis=0)`)."""
    packed = ((keys[:, 0] + KEY_LIMIT) << 32) | ((keys[:, 1] + KEY_LIMIT) << 16)
    packed |= keys[:, 2] + KEY_LIMIT
    packed.sort()
    first = np.ones(packed.shape[0], bool)
    np.not_equal(packed[1:], packed[:-1], out=first[1:])
    u = packed[first]
    out = np.empty((u.shape[0], 3), np.int64)
    out[:, 0] = (u >> 32) - KEY_LIMIT
    out[:, 1] = ((u >> 16) & 0xFFFF) - KEY_LIMIT
    out[:, 2] = (u & 0xFFFF) - KEY_LIMIT
    return out


def check_fleet_source(config: MapperConfig, fleet: FleetConfig) -> None:
    """Refuse, in one line, a fleet mapper that cannot run: no members, or a back-end whose
    deltas cannot be merged."""
    kind = backend_class(config.backend).values_kind
    if kind != "log_odds":
        raise ConfigError(
            f'mapper.source = "fleet": back-end {config.backend!r} cannot be merged (its deltas '
            f"hold {kind}, without weights); use octree-max or octree-bayes"
        )
    if not fleet.robots:
        raise ConfigError('mapper.source = "fleet" needs the members in fleet.robots')


class _Layer:
    """One member's reported voxels, keyed by its own voxel keys."""

    def __init__(self, block_bits: int):
        self.grid = BlockGrid(block_bits, _LAYER_FIELDS)
        self.n_voxels = 0

    def index(self) -> np.ndarray:
        return np.flatnonzero(self.grid.used("flags") & HAS)

    def put(self, keys, logodds, labels, confs) -> None:
        g = self.grid.insert(keys)
        c = self.grid.cols
        self.n_voxels += int((c["flags"][g] & HAS == 0).sum())
        c["logodds"][g] = logodds
        c["label"][g] = labels
        c["conf"][g] = confs
        c["flags"][g] = HAS

    def clear(self) -> np.ndarray:
        """Forget every voxel; returns their keys."""
        g = self.index()
        keys = self.grid.coords(g)
        self.grid.cols["flags"][g] = 0
        self.n_voxels = 0
        return keys

    def get(self, keys) -> tuple[np.ndarray, np.ndarray]:
        """(reported?, global index) of each key."""
        g = self.grid.lookup(keys)
        ok = g >= 0
        ok[ok] = (self.grid.cols["flags"][g[ok]] & HAS).astype(bool)
        return ok, g


class FleetMap:
    """The merged map of a fleet's members (see the module docstring)."""

    def __init__(
        self,
        config: MapperConfig,
        members: list[str],
        fleet: FleetConfig | None = None,
        class_table: ClassTable | str | Path = "garden3drms",
    ):
        fleet = fleet if fleet is not None else FleetConfig(robots=list(members))
        check_fleet_source(config, FleetConfig(robots=list(members)))
        if len(set(members)) != len(members):
            raise ValueError(f"members must be distinct, got {members!r}")
        self.config = config
        self.members = list(members)
        self.map = SemanticMap.from_config(config, class_table)  # the merged voxels
        self._core = self.map._core
        self.resolution_m = self.map.resolution_m
        self.backend = self.map.backend
        self.values_kind = self.map.values_kind
        self.class_ids = self.map.class_ids
        self.class_table = self.map.class_table
        self.frame = fleet.frame
        # per member (cos, sin, tx, ty), None for the identity
        self._poses: list[tuple[float, float, float, float] | None] = []
        for name in self.members:
            if fleet.frame == "start_pose" and name in fleet.robots[: len(fleet.start_poses)]:
                x, y, yaw = (float(v) for v in fleet.start_poses[fleet.robots.index(name)])
                self._poses.append((np.cos(yaw), np.sin(yaw), x, y))
            else:
                self._poses.append(None)
        self.layers = [_Layer(self.map.block_bits) for _ in self.members]
        _, _, c_min, c_max = sensor_model(self.map.config)
        self._clamp = (np.float32(c_min), np.float32(c_max))
        self.deltas_applied = [0] * len(self.members)
        self.replaced = [0] * len(self.members)

    def member_index(self, member: str) -> int:
        try:
            return self.members.index(member)
        except ValueError:
            raise ValueError(f"{member!r} is not a member ({self.members})") from None

    # -- frames ------------------------------------------------------------------------------

    def _to_fleet(self, m: int, keys: np.ndarray) -> np.ndarray:
        """Fleet voxel keys of member m's voxel keys (int64 n x 3)."""
        pose = self._poses[m]
        if pose is None:
            return keys
        c, s, tx, ty = pose
        res = self.resolution_m
        x = (keys[:, 0] + 0.5) * res
        y = (keys[:, 1] + 0.5) * res
        out = keys.copy()
        out[:, 0] = np.floor((c * x - s * y + tx) / res)
        out[:, 1] = np.floor((s * x + c * y + ty) / res)
        return out

    def _candidates(self, m: int, fleet_keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, source key) pairs: member m's voxels that may land in each fleet voxel."""
        pose = self._poses[m]
        n = fleet_keys.shape[0]
        if pose is None:
            return np.arange(n), fleet_keys
        c, s, tx, ty = pose
        res = self.resolution_m
        x = (fleet_keys[:, 0] + 0.5) * res - tx
        y = (fleet_keys[:, 1] + 0.5) * res - ty
        base = fleet_keys.copy()
        base[:, 0] = np.ceil((c * x + s * y) / res - 0.5 - _REACH)
        base[:, 1] = np.ceil((-s * x + c * y) / res - 0.5 - _REACH)
        cand = (base[:, None, :] + _AROUND[None]).reshape(-1, 3)
        return np.repeat(np.arange(n), len(_AROUND)), cand

    @staticmethod
    def _in_range(keys: np.ndarray) -> np.ndarray:
        # one test for both bounds and all three axes: k + LIMIT in [0, 2 LIMIT)
        return ((keys + KEY_LIMIT) >> 16 == 0).all(axis=1)

    # -- updates -----------------------------------------------------------------------------

    def _rows(self, centres, labels, confs, values):
        centres = np.asarray(centres, np.float64)
        n = centres.shape[0]
        if centres.ndim != 2 or centres.shape[1] != 3 or not np.isfinite(centres).all():
            raise ValueError("centres must be a finite N x 3 array")
        labels = np.asarray(labels)
        confs = np.asarray(confs, np.float32)
        values = np.asarray(values, np.float32)
        for name, a in (("labels", labels), ("confidences", confs), ("values", values)):
            if a.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
        if not np.isfinite(values).all():
            raise ValueError("values must be finite log-odds")
        keys = np.floor(centres / self.resolution_m).astype(np.int64)
        ok = self._in_range(keys)
        lo, hi = self._clamp
        return (
            keys[ok],
            np.clip(values[ok], lo, hi),
            labels[ok].astype(np.uint16),
            np.clip(np.nan_to_num(confs[ok]), 0, 1),
        )

    def apply(self, member: str, centres, labels, confidences, values) -> Delta:
        """Member `member` reports these voxel states (a MapDelta's rows, its own frame);
        returns the merged voxels that changed."""
        m = self.member_index(member)
        keys, lo, lab, conf = self._rows(centres, labels, confidences, values)
        self.layers[m].put(keys, lo, lab, conf)
        self.deltas_applied[m] += 1
        return self._recompute(self._to_fleet(m, keys))

    def replace(self, member: str, centres, labels, confidences, values) -> Delta:
        """Member `member`'s whole map (every observed voxel, a snapshot's rows) replaces its
        layer; returns the merged voxels that changed."""
        m = self.member_index(member)
        keys, lo, lab, conf = self._rows(centres, labels, confidences, values)
        old = self.layers[m].clear()
        self.layers[m].put(keys, lo, lab, conf)
        self.replaced[m] += 1
        return self._recompute(self._to_fleet(m, np.concatenate([old, keys])))

    def _recompute(self, fleet_keys: np.ndarray) -> Delta:
        """Derive the merged voxels of `fleet_keys` from the layers; write them; the changed."""
        if any(p is not None for p in self._poses):  # a moved key may leave the range
            fleet_keys = fleet_keys[self._in_range(fleet_keys)]
        if fleet_keys.shape[0] == 0:
            return Delta.empty()
        fleet_keys = _unique_keys(fleet_keys)
        n = fleet_keys.shape[0]
        rows, lo, lab, conf, who = [], [], [], [], []
        for m, layer in enumerate(self.layers):
            r, cand = self._candidates(m, fleet_keys)
            if self._poses[m] is not None:
                ok = self._in_range(cand)
                r, cand = r[ok], cand[ok]
            has, g = layer.get(cand)
            if self._poses[m] is not None:  # only the source voxels that land in this one
                has[has] = (self._to_fleet(m, cand[has]) == fleet_keys[r[has]]).all(axis=1)
            g = g[has]
            cols = layer.grid.cols
            rows.append(r[has])
            lo.append(cols["logodds"][g])
            lab.append(cols["label"][g])
            conf.append(cols["conf"][g])
            who.append(np.full(g.shape[0], m, np.int64))
        rows, lo, lab, conf, who = (np.concatenate(a) for a in (rows, lo, lab, conf, who))
        known = np.bincount(rows, minlength=n) > 0
        total = np.bincount(rows, weights=lo.astype(np.float64), minlength=n)
        c_min, c_max = self._clamp
        merged = np.clip(total.astype(np.float32), c_min, c_max)
        # labels: one observation per (member, source voxel), by confidence then member
        sem_l, sem_p = self._core.fuse_labels(n, rows, lab, conf, who)
        return self._write(fleet_keys, known, merged, sem_l, sem_p)

    def _write(self, keys, known, merged, sem_l, sem_p) -> Delta:
        core = self._core
        grid = core.grid
        g = grid.lookup(keys)
        was = g >= 0
        was[was] = (grid.cols["flags"][g[was]] & OBSERVED).astype(bool)
        keep = known | was
        if not keep.all():
            keys, known, merged, sem_l, sem_p, was = (
                a[keep] for a in (keys, known, merged, sem_l, sem_p, was)
            )
        g = grid.insert(keys)  # after any growth, every column is the grown one
        cols = grid.cols
        old_lo = cols["logodds"][g].copy()
        old_l0 = cols["label"][g, 0].copy()
        old_p0 = cols["prob"][g, 0].copy()
        new_lo = np.where(known, merged, np.float32(0))
        changed = (known != was) | (
            known & ((new_lo != old_lo) | (sem_l[:, 0] != old_l0) | (sem_p[:, 0] != old_p0))
        )
        cols["logodds"][g] = new_lo
        cols["label"][g] = sem_l
        cols["prob"][g] = sem_p
        cols["flags"][g] = np.where(known, OBSERVED, np.uint8(0))
        core.n_observed += int(known.sum()) - int(was.sum())
        core.n_occupied += int((known & (new_lo > 0)).sum()) - int((was & (old_lo > 0)).sum())
        return core.rows(g[changed])

    def rebuild(self) -> None:
        """Derive every merged voxel again from the layers (after a load)."""
        grid = self._core.grid
        grid.cols["flags"][:] = 0
        self._core.recount()
        keys = [
            self._to_fleet(m, layer.grid.coords(layer.index()))
            for m, layer in enumerate(self.layers)
        ]
        self._recompute(np.concatenate(keys) if keys else np.empty((0, 3), np.int64))

    # -- the merged map ----------------------------------------------------------------------

    def occupied_voxels(self, box=None) -> Delta:
        return self.map.occupied_voxels(box)

    def observed_voxels(self, box=None) -> Delta:
        return self.map.observed_voxels(box)

    def query(self, points: np.ndarray) -> QueryResult:
        return self.map.query(points)

    def member_stats(self) -> dict[str, dict[str, int]]:
        return {
            name: {"deltas_applied": self.deltas_applied[m], "voxels": self.layers[m].n_voxels}
            for m, name in enumerate(self.members)
        }

    def stats(self) -> dict:
        return {**self.map.stats(), "members": self.member_stats()}

    # -- persistence -------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """The merged map as `SemanticMap.save` writes it, plus the layers (atomically)."""
        meta = self.map._meta()
        meta["fleet"] = {
            "members": self.members,
            "frame": self.frame,
            "poses": self._poses,
            "deltas_applied": self.deltas_applied,
            "replaced": self.replaced,
        }
        arrays: dict[str, Any] = {}
        for m, layer in enumerate(self.layers):
            lg = layer.grid
            arrays[f"layer{m}_block_keys"] = lg.block_keys[: lg.n_blocks]
            for k in lg.cols:
                arrays[f"layer{m}_{k}"] = lg.used(k)
        return self.map.save(path, meta, **arrays)

    @classmethod
    def load(
        cls,
        path: str | Path,
        config: MapperConfig,
        members: list[str],
        fleet: FleetConfig | None = None,
        class_table: ClassTable | str | Path = "garden3drms",
        max_bytes: int = mapfile.MAX_MAP_BYTES,
    ) -> FleetMap:
        """Resume from a file `save` wrote: the layers of the members named in it that are still
        members (the others start empty); the merged map is derived again from them. The config
        (back-end, resolution, frame) is the one given: a file made with another resolution is
        refused. The file is checked before use as `SemanticMap.load` checks it (`mapfile`)."""
        fm = cls(config, members, fleet, class_table)
        with mapfile.MapFile(path, max_bytes) as f:
            meta = mapfile.check_meta(f.meta(), f.path, config.backend)
            saved = meta.get("fleet")
            if saved is None:
                raise mapfile.MapFileError(f"{path}: a robot's map, not a fleet map (no layers)")
            if meta["resolution_m"] != fm.resolution_m or meta["backend"] != fm.backend:
                raise mapfile.MapFileError(
                    f"{path}: a {meta['backend']} map at {meta['resolution_m']} m; the config "
                    f"asks for {fm.backend} at {fm.resolution_m} m"
                )
            if meta["block_bits"] != fm.map.block_bits:
                raise mapfile.MapFileError(f"{path}: blocks of {meta['block_bits']} bits")
            # the merged map is derived again from the layers; its columns are checked all the
            # same (as the file describes them), so that the file also loads as a plain map
            grid = SemanticMap.from_meta(meta, class_table, f.path)._core.grid
            expected = {"meta", "block_keys", *(f"col_{k}" for k in grid.fields)}
            mapfile.check_members(f, expected | mapfile.layer_names(len(saved["members"])))
            mapfile.read_grid(f, "block_keys", "col_", grid.fields, grid.bits, set(grid.loaders))
            layers = {}
            for m, name in enumerate(saved["members"]):
                block_keys, cols = mapfile.read_grid(
                    f, f"layer{m}_block_keys", f"layer{m}_", _LAYER_FIELDS, grid.bits
                )
                layers[name] = (
                    block_keys,
                    cols,
                    saved["deltas_applied"][m],
                    saved["replaced"][m],
                )
        for m, name in enumerate(fm.members):
            if name in layers:
                block_keys, cols, fm.deltas_applied[m], fm.replaced[m] = layers[name]
                fm.layers[m].grid.restore(block_keys, cols)
                fm.layers[m].n_voxels = int(fm.layers[m].index().shape[0])
        fm.rebuild()
        return fm
