"""The semantic voxel map a recorder rebuilds from `mapper/delta`, kept in 2 m blocks so that only
the blocks that changed are logged again."""

from __future__ import annotations

import numpy as np

from smana.common.messages import MapDelta


class VoxelStore:
    """The occupied voxels of the map, kept from MapDelta messages (a voxel at most once).

    `apply` only queues a delta (cost proportional to the delta): merging into the store, newest
    state per voxel, waits for the next read (`blocks`, `keys`, ...). Merging on every delta cost
    the whole store each time: the recorder fell behind the mapper, poses queued behind deltas."""

    MERGE_ROWS = 2_000_000  # queued rows past which a delta merges at once (bounds the memory)

    def __init__(self, block_m: float = 2.0):
        self.block_m = block_m
        self._keys = np.zeros(0, np.int64)
        self._centres = np.zeros((0, 3), np.float32)
        self._labels = np.zeros(0, np.uint16)
        self._queued: list[tuple[np.ndarray, ...]] = []  # (keys, centres, labels, occupied)
        self._queued_rows = 0
        self.dirty_blocks: set[tuple[int, int]] = set()
        self.resolution_m = 0.0

    @staticmethod
    def _keys_of(centres: np.ndarray, res: float) -> np.ndarray:
        q = np.floor(centres / res).astype(np.int64) + (1 << 20)
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]

    def _blocks(self, centres: np.ndarray) -> np.ndarray:
        return np.floor(centres[:, :2] / self.block_m).astype(np.int64)

    @staticmethod
    def _block_codes(blocks: np.ndarray) -> np.ndarray:
        """One int64 per block (x in the high half, y in the low half): sortable, and fast to
        make unique where a row-wise unique of (x, y) pairs is not."""
        return (blocks[:, 0] << 32) + blocks[:, 1]

    def apply(self, delta: MapDelta) -> None:
        if delta.resolution_m != self.resolution_m and (len(self._keys) or self._queued):
            self.__init__(self.block_m)  # the map was restarted at another resolution
        self.resolution_m = delta.resolution_m
        c = np.asarray(delta.centres, np.float32)
        if len(c) == 0:
            return
        labels = np.asarray(delta.labels, np.uint16)
        occupied = np.asarray(delta.occupied).astype(bool)
        self._queued.append((self._keys_of(c, delta.resolution_m), c, labels, occupied))
        self._queued_rows += len(c)
        b = self._blocks(c)
        _, first = np.unique(self._block_codes(b), return_index=True)
        self.dirty_blocks.update(map(tuple, b[first].tolist()))
        if self._queued_rows > self.MERGE_ROWS:
            self._merge()

    def _merge(self) -> None:
        if not self._queued:
            return
        # newest wins: stack the store then the deltas in order, keep each key's last row
        q = self._queued
        all_k = np.concatenate([self._keys, *(d[0] for d in q)])
        all_c = np.concatenate([self._centres, *(d[1] for d in q)])
        all_l = np.concatenate([self._labels, *(d[2] for d in q)])
        all_o = np.concatenate([np.ones(len(self._keys), bool), *(d[3] for d in q)])
        self._queued, self._queued_rows = [], 0
        rev = np.arange(len(all_k))[::-1]
        _, first = np.unique(all_k[rev], return_index=True)
        keep = rev[first]
        keep = keep[all_o[keep]]
        self._keys, self._centres, self._labels = all_k[keep], all_c[keep], all_l[keep]

    @property
    def keys(self) -> np.ndarray:
        self._merge()
        return self._keys

    @property
    def centres(self) -> np.ndarray:
        self._merge()
        return self._centres

    @property
    def labels(self) -> np.ndarray:
        self._merge()
        return self._labels

    def blocks(self, wanted) -> list[tuple[tuple[int, int], np.ndarray, np.ndarray]]:
        """(block, centres, labels) of each block in `wanted`: one sort of the store for all of
        them (a mask per block cost the whole store per block)."""
        self._merge()
        code = self._block_codes(self._blocks(self._centres))
        order = np.argsort(code, kind="stable")
        code = code[order]
        out = []
        for b in sorted(wanted):
            k = (int(b[0]) << 32) + int(b[1])
            lo, hi = np.searchsorted(code, k, "left"), np.searchsorted(code, k, "right")
            sel = order[lo:hi]
            out.append((b, self._centres[sel], self._labels[sel]))
        return out

    def block(self, b: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        _, c, lab = self.blocks([b])[0]
        return c, lab
