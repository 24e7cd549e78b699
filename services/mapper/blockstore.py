"""An unloaded-block store: a map's blocks far from the robot live on disk, not in memory.

A long drive maps an area that grows with the distance; the blocks the sensor can still reach
are the ones around it. This store keeps a `SemanticMap`'s blocks resident within
`keep_radius_m` (xy) of the sensor and moves the others to disk, grouped in square regions of
`region_m`, one `.npz` file per region (block keys and every voxel column, as `SemanticMap.save`
writes them). A region is read back, whole, before an integration whose sensor origin comes
within `load_radius_m` of it: the mapper's rays end within `max_range_m` of the origin, so with
`load_radius_m = max_range_m + one block` every voxel an integration reads or writes is resident,
and the map (resident and stored blocks together) is the map an unbounded run makes, voxel for
voxel. Nothing is dropped: the bound is on memory, not on the map.

What was chosen and why: voxblox and nvblox both keep a block hash (as `block_grid.BlockGrid` does)
and bound memory by deleting blocks (nvblox's `clearOutsideRadius`, voxblox's block removal by
distance), which loses the far map. Keeping whole regions on disk instead costs one file write
per region left behind and one read per region come back to, and keeps the map exact. Regions
(not single blocks) keep the file count and the look-up per scan small: the store looks only at
the regions within reach of the origin.

Moving blocks out or in rebuilds the resident block arrays (`BlockGrid.restore`), a copy of the
resident part only, which the radius bounds. The core's counters (observed, occupied voxels)
then count the resident blocks; `stats()` adds the stored ones.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from smana.services.mapper import mapfile
from smana.services.mapper.block_grid import PACK_MASK, PACK_OFF


def _block_xy(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block (bx, by) of packed block keys (`block_grid.pack_block`)."""
    keys = np.asarray(keys, np.int64)
    return ((keys >> 42) & PACK_MASK) - PACK_OFF, ((keys >> 21) & PACK_MASK) - PACK_OFF


class BlockStore:
    """Keeps `m`'s blocks within `keep_radius_m` of the sensor in memory, the rest in `directory`.

    Call `before(origin)` before each `m.integrate(..., origin=origin)` (it reads back what the
    integration can touch) and `after(origin)` after it (it moves out what is now far)."""

    def __init__(
        self,
        m,
        directory: str | Path,
        keep_radius_m: float = 40.0,
        region_m: float = 12.8,
        check_every: int = 10,
    ):
        grid = m._core.grid
        self.map = m
        self.block_m = (1 << grid.bits) * m.resolution_m
        self.region_blocks = max(1, int(round(region_m / self.block_m)))
        self.region_m = self.region_blocks * self.block_m
        # a ray ends within max_range_m of the origin; one block more covers the voxel's block
        self.load_radius_m = m.max_range_m + self.block_m
        if not keep_radius_m > self.load_radius_m:
            raise ValueError(
                f"keep_radius_m must exceed max_range_m + one block ({self.load_radius_m:g} m), "
                f"got {keep_radius_m}"
            )
        if int(check_every) < 1:
            raise ValueError(f"check_every must be >= 1, got {check_every}")
        self.keep_radius_m = float(keep_radius_m)
        self.check_every = int(check_every)
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.stored: dict[tuple[int, int], tuple[Path, int, int]] = {}  # region -> file, blocks, B
        self.n_loaded = self.n_evicted = 0  # regions read back, regions written
        self.problems: list[str] = []  # one line per region file that could not be used
        self._calls = 0

    # -- geometry ------------------------------------------------------------------------------

    def _region_distance(self, rx, ry, ox: float, oy: float):
        """xy distance from (ox, oy) to the square of region (rx, ry) (0 inside it)."""
        s = self.region_m
        dx = np.maximum(0.0, np.maximum(rx * s - ox, ox - (rx + 1) * s))
        dy = np.maximum(0.0, np.maximum(ry * s - oy, oy - (ry + 1) * s))
        return np.hypot(dx, dy)

    def _path(self, rx: int, ry: int) -> Path:
        return self.directory / f"region_{rx}_{ry}.npz"

    # -- moving blocks -------------------------------------------------------------------------

    def before(self, origin) -> int:
        """Read back every stored region within `load_radius_m` of the origin; returns how many.
        A region file that cannot be used costs that region only: it leaves the index, its file
        is kept (renamed `.damaged`), the reason goes to `problems`; the others load."""
        if not self.stored:
            return 0
        ox, oy = float(origin[0]), float(origin[1])
        s, r = self.region_m, self.load_radius_m
        want = []
        for rx in range(math.floor((ox - r) / s), math.floor((ox + r) / s) + 1):
            for ry in range(math.floor((oy - r) / s), math.floor((oy + r) / s) + 1):
                if (rx, ry) in self.stored and self._region_distance(rx, ry, ox, oy) <= r:
                    want.append((rx, ry))
        if not want:
            return 0
        grid = self.map._core.grid
        keys = [grid.block_keys[: grid.n_blocks].copy()]
        cols = {k: [grid.used(k)] for k in grid.cols}
        loaded = []
        for region in want:
            got = self._read_region(region, keys[0])
            if got is None:
                continue
            keys.append(got[0])
            for k in cols:
                cols[k].append(got[1][k])
            loaded.append(region)
        if not loaded:
            return 0
        grid.restore(np.concatenate(keys), {k: np.concatenate(v) for k, v in cols.items()})
        self.map._core.recount()
        for region in loaded:  # resident now: only then is the file let go
            self.stored.pop(region)[0].unlink()
        self.n_loaded += len(loaded)
        return len(loaded)

    def _read_region(self, region, resident: np.ndarray):
        """A stored region's block keys and columns, checked as a map file's are (`mapfile`:
        container, dtypes, shapes, values) and against the store (every block in that region,
        none resident); None, and the region dropped, when its file cannot be used."""
        path = self.stored[region][0]
        grid = self.map._core.grid
        try:
            with mapfile.MapFile(path) as f:
                mapfile.check_members(f, {"block_keys", *(f"col_{k}" for k in grid.fields)})
                bk, cols = mapfile.read_grid(f, "block_keys", "col_", grid.fields, grid.bits)
            bx, by = _block_xy(bk)
            rb = self.region_blocks
            if bk.size and ((bx // rb != region[0]).any() or (by // rb != region[1]).any()):
                raise ValueError(f"{path}: blocks outside region {region}")
            if np.isin(bk, resident).any():
                raise ValueError(f"{path}: blocks that are resident already")
        except (ValueError, OSError) as exc:  # MapFileError included: one line, the file
            self.stored.pop(region)
            self.problems.append(" ".join(str(exc).split()))
            try:
                path.rename(path.with_name(path.name + ".damaged"))
            except OSError:
                pass
            return None
        return bk, cols

    def after(self, origin, force: bool = False) -> int:
        """Every `check_every` calls (or when `force`): write out the regions whose square lies
        farther than `keep_radius_m` from the origin; returns how many."""
        self._calls += 1
        if not force and self._calls % self.check_every:
            return 0
        grid = self.map._core.grid
        n = grid.n_blocks
        if n == 0:
            return 0
        keys = grid.block_keys[:n]
        bx, by = _block_xy(keys)
        rb = self.region_blocks
        rx, ry = bx // rb, by // rb
        far = self._region_distance(rx, ry, float(origin[0]), float(origin[1])) > (
            self.keep_radius_m
        )
        if not far.any():
            return 0
        v = grid.voxels_per_block
        per_voxel = np.arange(v)
        far_idx = np.flatnonzero(far)
        rid = rx[far_idx] * (1 << 32) + (ry[far_idx] & 0xFFFFFFFF)
        order = np.argsort(rid, kind="stable")
        far_idx, rid = far_idx[order], rid[order]
        cuts = np.flatnonzero(np.diff(rid)) + 1
        written = 0
        for group in np.split(far_idx, cuts):
            region = (int(rx[group[0]]), int(ry[group[0]]))
            if region in self.stored:  # a region is resident or stored, never both
                raise RuntimeError(f"region {region} is both resident and stored")
            rows = (group[:, None] * v + per_voxel).ravel()
            path = self._path(*region)
            arrays = {f"col_{k}": grid.cols[k][rows] for k in grid.cols}
            with open(path, "wb") as fh:
                np.savez(fh, block_keys=keys[group], **arrays)
            self.stored[region] = (path, len(group), path.stat().st_size)
            written += 1
        kept = np.flatnonzero(~far)
        rows = (kept[:, None] * v + per_voxel).ravel()
        grid.restore(keys[kept].copy(), {k: grid.cols[k][rows] for k in grid.cols})
        self.map._core.recount()
        self.n_evicted += written
        return written

    # -- the whole map -------------------------------------------------------------------------

    def full_map(self):
        """A new SemanticMap holding every block, resident and stored (the store is unchanged)."""
        from smana.services.mapper.semantic_map import SemanticMap

        m = self.map
        grid = m._core.grid
        keys = [grid.block_keys[: grid.n_blocks]]
        cols = {k: [grid.used(k)] for k in grid.cols}
        for region in list(self.stored):
            got = self._read_region(region, keys[0])
            if got is not None:
                keys.append(got[0])
                for k in cols:
                    cols[k].append(got[1][k])
        out = SemanticMap.from_config(m.section, m.class_table, m.block_bits)
        out._core.grid.restore(
            np.concatenate(keys), {k: np.concatenate(c) for k, c in cols.items()}
        )
        out._core.recount()
        out.n_integrations, out.n_points = m.n_integrations, m.n_points
        return out

    def stats(self) -> dict:
        return {
            "resident_blocks": self.map._core.grid.n_blocks,
            "stored_blocks": sum(b for _, b, _ in self.stored.values()),
            "stored_regions": len(self.stored),
            "stored_bytes": sum(n for _, _, n in self.stored.values()),
            "regions_written": self.n_evicted,
            "regions_read": self.n_loaded,
            "regions_damaged": len(self.problems),
        }
