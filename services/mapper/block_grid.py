"""Hashed block grid and ray traversal shared by the mapper back-ends (numba, no zenoh).

Storage is a voxblox-style block hash: voxels are grouped in cubes of `2**bits` voxels a side;
an open-addressing table maps a packed block key to a block index, and every per-voxel field is
a flat struct-of-arrays column indexed by `block * voxels_per_block + local`. Walking a ray then
costs one hash probe per block crossed instead of one per voxel, which is where the speed over a
pointer octree comes from.

Kernels take the block hash as one structure, `Grid` (a named tuple of arrays: numba passes it
at the cost of its fields, see docs/benchmarks.md), and find a voxel's block through `voxel_slot`,
the one copy of the look-up with its last-block cache that every back-end kernel uses.

Kernels here never allocate map storage: when a block or table slot is missing they return a
status code and the Python owner (`BlockGrid`) grows the arrays and calls them again, resuming at
the point where they stopped. Every step a kernel takes before such a return is idempotent.

Note for editors: numba's on-disk cache (`cache=True`) keys a kernel on its own file only, so the
kernels of `backends/*.py` do not notice a change here. After editing this file, delete
`services/mapper/backends/__pycache__/*.nbi` and `*.nbc` (or touch those files).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numba import njit

from smana.common.config.mapper import KEY_LIMIT as _KEY_LIMIT

# -- status codes returned by the integration kernels ----------------------------------------------
DONE = 0
GROW_BLOCKS = 1
GROW_TABLE = 2
GROW_TOUCHED = 3

# -- per-voxel flag bits ---------------------------------------------------------------------------
OBSERVED = np.uint8(1)  # the voxel received at least one update (unknown otherwise)
MARK_FREE = np.uint8(2)  # this cloud: a ray passed through (cleared after the cloud)
MARK_HIT = np.uint8(4)  # this cloud: a point ended in it (cleared after the cloud)
MARK_SEM = np.uint8(8)  # this cloud: its label or confidence moved (cleared after the cloud)
MARK_ANY = np.uint8(14)

# Block coordinates are packed in 21 bits per axis; OctoMap's key range (+-32768 voxels) is the
# map's extent anyway, so the packing never overflows.
PACK_OFF = 1 << 20
PACK_MASK = (1 << 21) - 1
# voxel indices must lie in [-KEY_LIMIT, KEY_LIMIT), as OctoMap's 16-bit keys (declared with the
# map's other limits in the config section, common/config/mapper.py)
KEY_LIMIT = _KEY_LIMIT
EMPTY = np.int64(-1)
_FIB = np.uint64(0x9E3779B97F4A7C15)


class Grid(NamedTuple):
    """The block hash as kernels see it (rebuilt by `BlockGrid.state()` after every growth)."""

    h_keys: np.ndarray  # int64 [2**k]: packed block key per slot, EMPTY where free
    h_vals: np.ndarray  # int32 [2**k]: block index per slot
    block_keys: np.ndarray  # int64 [capacity]: packed key of each allocated block
    n_blocks: np.ndarray  # int64 [1]: blocks in use; kernels append
    hshift: int  # 64 - log2(table size), for Fibonacci hashing
    bits: int  # log2 of the block side


@njit(cache=True, error_model="numpy", inline="always")
def pack_block(bx, by, bz):
    return ((bx + PACK_OFF) << 42) | ((by + PACK_OFF) << 21) | (bz + PACK_OFF)


@njit(cache=True, error_model="numpy")
def unpack_block(key):
    return (
        ((key >> 42) & PACK_MASK) - PACK_OFF,
        ((key >> 21) & PACK_MASK) - PACK_OFF,
        (key & PACK_MASK) - PACK_OFF,
    )


@njit(cache=True, error_model="numpy", inline="always")
def voxel_key(grid, g):
    """(ix, iy, iz) of global voxel index g (block slot << 3 * bits | index in the block)."""
    bits = grid.bits
    vb = 3 * bits
    bm = (1 << bits) - 1
    bx, by, bz = unpack_block(grid.block_keys[g >> vb])
    local = g & ((1 << vb) - 1)
    return (
        (bx << bits) | (local & bm),
        (by << bits) | ((local >> bits) & bm),
        (bz << bits) | ((local >> (2 * bits)) & bm),
    )


@njit(cache=True, error_model="numpy", inline="always")
def put_key_centre(grid, g, res, keys, centres, i):
    """Row i of a Delta's keys and centres: voxel g's integer key and its centre in metres."""
    kx, ky, kz = voxel_key(grid, g)
    keys[i, 0] = kx
    keys[i, 1] = ky
    keys[i, 2] = kz
    centres[i, 0] = (kx + 0.5) * res
    centres[i, 1] = (ky + 0.5) * res
    centres[i, 2] = (kz + 0.5) * res


@njit(cache=True, error_model="numpy", inline="always")
def hash_slot(key, hshift):
    # Fibonacci hashing: the high bits of key * golden ratio spread neighbouring blocks.
    return np.int64((np.uint64(key) * _FIB) >> np.uint64(hshift))


@njit(cache=True, error_model="numpy", inline="always")
def table_find(grid, key):
    """Block index of `key`, or -1."""
    h_keys = grid.h_keys
    mask = h_keys.shape[0] - 1
    s = hash_slot(key, grid.hshift)
    while True:
        k = h_keys[s]
        if k == key:
            return np.int64(grid.h_vals[s])
        if k == EMPTY:
            return np.int64(-1)
        s = (s + 1) & mask


@njit(cache=True, error_model="numpy", inline="always")
def table_find_or_insert(grid, key):
    """Block index of `key`, allocated when missing; -GROW_BLOCKS / -GROW_TABLE when storage is
    full (nothing was changed then)."""
    h_keys = grid.h_keys
    mask = h_keys.shape[0] - 1
    s = hash_slot(key, grid.hshift)
    while True:
        k = h_keys[s]
        if k == key:
            return np.int64(grid.h_vals[s])
        if k == EMPTY:
            break
        s = (s + 1) & mask
    n_blocks = grid.n_blocks[0]
    if n_blocks >= grid.block_keys.shape[0]:
        return np.int64(-GROW_BLOCKS)
    if 2 * (n_blocks + 1) > h_keys.shape[0]:  # keep the load factor <= 1/2
        return np.int64(-GROW_TABLE)
    h_keys[s] = key
    grid.h_vals[s] = n_blocks
    grid.block_keys[n_blocks] = key
    grid.n_blocks[0] = n_blocks + 1
    return np.int64(n_blocks)


@njit(cache=True, error_model="numpy", inline="always")
def voxel_slot(grid, ix, iy, iz, last_key, last_b):
    """Global voxel index of voxel (ix, iy, iz), its block allocated when missing, through a
    one-entry cache of the last block: a ray's voxels come in order, so most share the previous
    one's block and skip the hash probe. Returns (index, last_key, last_b) to carry to the next
    call (start with -1, -1); a negative index is -GROW_BLOCKS / -GROW_TABLE."""
    bkey, local = voxel_index(ix, iy, iz, grid.bits)
    if bkey != last_key:
        b = table_find_or_insert(grid, bkey)
        if b < 0:
            return b, last_key, last_b
        last_key = bkey
        last_b = b
    return (last_b << (3 * grid.bits)) | local, last_key, last_b


@njit(cache=True, error_model="numpy")
def rebuild_table(grid):
    h_keys = grid.h_keys
    h_keys[:] = EMPTY
    mask = h_keys.shape[0] - 1
    for b in range(grid.n_blocks[0]):
        key = grid.block_keys[b]
        s = hash_slot(key, grid.hshift)
        while h_keys[s] != EMPTY:
            s = (s + 1) & mask
        h_keys[s] = key
        grid.h_vals[s] = b


@njit(cache=True, error_model="numpy", inline="always")
def voxel_index(ix, iy, iz, bits):
    """(packed block key, local index inside the block) of voxel (ix, iy, iz)."""
    bm = (1 << bits) - 1
    key = pack_block(ix >> bits, iy >> bits, iz >> bits)
    local = (ix & bm) | ((iy & bm) << bits) | ((iz & bm) << (2 * bits))
    return key, local


@njit(cache=True, error_model="numpy")
def lookup_voxels(keys, grid):
    """Global voxel index of each (ix, iy, iz) row of `keys`, -1 where no block holds it."""
    out = np.empty(keys.shape[0], np.int64)
    bits = grid.bits
    vb = 3 * bits
    for i in range(keys.shape[0]):
        bkey, local = voxel_index(keys[i, 0], keys[i, 1], keys[i, 2], bits)
        b = table_find(grid, bkey)
        out[i] = -1 if b < 0 else (b << vb) | local
    return out


@njit(cache=True, error_model="numpy")
def insert_voxels(keys, grid, out, i0):
    """Global voxel index of each (ix, iy, iz) row of `keys` from row i0 on, allocating blocks;
    returns (status, row to resume at)."""
    last_key = np.int64(-1)
    last_b = np.int64(-1)
    for i in range(i0, keys.shape[0]):
        g, last_key, last_b = voxel_slot(grid, keys[i, 0], keys[i, 1], keys[i, 2], last_key, last_b)
        if g < 0:
            return -g, i
        out[i] = g
    return DONE, keys.shape[0]


@njit(cache=True, error_model="numpy")
def voxel_coords(gidx, grid):
    """(ix, iy, iz) int64 rows of global voxel indices."""
    out = np.empty((gidx.shape[0], 3), np.int64)
    bits = grid.bits
    vb = 3 * bits
    bm = (1 << bits) - 1
    for i in range(gidx.shape[0]):
        g = gidx[i]
        bx, by, bz = unpack_block(grid.block_keys[g >> vb])
        local = g & ((1 << vb) - 1)
        out[i, 0] = (bx << bits) | (local & bm)
        out[i, 1] = (by << bits) | ((local >> bits) & bm)
        out[i, 2] = (bz << bits) | ((local >> (2 * bits)) & bm)
    return out


@njit(cache=True, error_model="numpy", inline="always")
def coord_to_key(c, inv_res):
    """OctoMap's coordToKey without the 2**15 offset: floor(coord / res), in double."""
    return np.int64(np.floor(np.float64(c) * inv_res))


@njit(cache=True, error_model="numpy", inline="always")
def key_in_range(kx, ky, kz):
    lim = KEY_LIMIT
    return -lim <= kx < lim and -lim <= ky < lim and -lim <= kz < lim


class RayOrigin(NamedTuple):
    """The part of OctoMap's DDA set-up that depends on a ray's start only (`octomap_ray_origin`),
    with the voxel size it was computed at."""

    kx: int  # the start's keys
    ky: int
    kz: int
    in_range: bool  # the start's keys lie in the key range
    npx: float  # per axis, the tMax numerator for a positive and for a negative step
    nnx: float
    npy: float
    nny: float
    npz: float
    nnz: float
    res: float
    inv_res: float


@njit(cache=True, error_model="numpy", inline="always")
def octomap_ray_origin(ox, oy, oz, res, inv_res):
    """The set-up of the rays from (ox, oy, oz), a `RayOrigin`, computed once for all the rays of
    a scan (they all start at the sensor): the start's keys, whether they are in the key range,
    and per axis the tMax numerator for a positive and for a negative step,
    `(key + 0.5) * res +- res / 2 - start`, in double, in OctoMap's order of operations.
    Coordinates must be float32."""
    kox = coord_to_key(ox, inv_res)
    koy = coord_to_key(oy, inv_res)
    koz = coord_to_key(oz, inv_res)
    half = np.float64(np.float32(res * 0.5))
    cx = (np.float64(kox) + 0.5) * res
    cy = (np.float64(koy) + 0.5) * res
    cz = (np.float64(koz) + 0.5) * res
    fx = np.float64(ox)
    fy = np.float64(oy)
    fz = np.float64(oz)
    # OctoMap adds step * half with step = +-1: exactly +half or -half
    return RayOrigin(
        kox,
        koy,
        koz,
        key_in_range(kox, koy, koz),
        cx + half - fx,
        cx - half - fx,
        cy + half - fy,
        cy - half - fy,
        cz + half - fz,
        cz - half - fz,
        res,
        inv_res,
    )


@njit(cache=True, error_model="numpy", inline="always")
def octomap_ray_from(origin, ex, ey, ez, dx, dy, dz, length):
    """`octomap_ray_start` from a start's `RayOrigin`, the end, and the ray's float32 difference
    end - start and its float32 length, as `octomap_ray_start` computes them (a caller that has
    them already saves a square root)."""
    kox, koy, koz, o_in, npx, nnx, npy, nny, npz, nnz, res, inv_res = origin
    kex = coord_to_key(ex, inv_res)
    key_ = coord_to_key(ey, inv_res)
    kez = coord_to_key(ez, inv_res)
    big = np.finfo(np.float64).max
    first = 1
    if not (o_in and key_in_range(kex, key_, kez)):
        first = -1
    elif kox == kex and koy == key_ and koz == kez:
        first = 0
    if first <= 0:
        z = np.int64(0)
        return first, (z, z, z, z, z, z, z, z, z, big, big, big, big, big, big, big)
    dx = np.float32(dx / length)
    dy = np.float32(dy / length)
    dz = np.float32(dz / length)
    sx = np.int64(1 if dx > 0 else (-1 if dx < 0 else 0))
    sy = np.int64(1 if dy > 0 else (-1 if dy < 0 else 0))
    sz = np.int64(1 if dz > 0 else (-1 if dz < 0 else 0))
    tmx = tmy = tmz = big
    tdx = tdy = tdz = big
    if sx != 0:
        tmx = (npx if sx > 0 else nnx) / np.float64(dx)
        tdx = res / abs(np.float64(dx))
    if sy != 0:
        tmy = (npy if sy > 0 else nny) / np.float64(dy)
        tdy = res / abs(np.float64(dy))
    if sz != 0:
        tmz = (npz if sz > 0 else nnz) / np.float64(dz)
        tdz = res / abs(np.float64(dz))
    walk = (kox, koy, koz, kex, key_, kez, sx, sy, sz, tmx, tmy, tmz, tdx, tdy, tdz)
    return first, (*walk, np.float64(length))


@njit(cache=True, error_model="numpy", inline="always")
def octomap_ray_start(ox, oy, oz, ex, ey, ez, res, inv_res):
    """OctoMap's computeRayKeys, as a walk: (first, walk). `first` is -1 when an end lies outside
    the key range (OctoMap skips the ray), 0 when both ends share a voxel (no key), else 1: the
    walk's cell (walk[0:3]) is the origin's voxel, the first key; `octomap_ray_next` gives the
    others, up to, not including, the end's voxel.

    A transcription of OcTreeBaseImpl::computeRayKeys (Amanatides-Woo 3D DDA) keeping its mix of
    float (point3d) and double (tMax, tDelta) arithmetic, so that both walk the same voxels even
    when a ray grazes a voxel corner. Coordinates must be float32. A kernel walking the keys as
    they come (no buffer) saves a store and a load per voxel and keeps the walk in registers.
    Split in two (`octomap_ray_origin`, `octomap_ray_from`) so that a scan's rays, which share
    their start, compute its part once.
    """
    # float32 direction and length, exactly as point3d computes them
    dx = np.float32(ex - ox)
    dy = np.float32(ey - oy)
    dz = np.float32(ez - oz)
    nsq = np.float32(np.float32(dx * dx + dy * dy) + dz * dz)
    length = np.float32(np.sqrt(np.float64(nsq)))
    origin = octomap_ray_origin(ox, oy, oz, res, inv_res)
    return octomap_ray_from(origin, ex, ey, ez, dx, dy, dz, length)


@njit(cache=True, error_model="numpy", inline="always")
def octomap_ray_next(walk):
    """One DDA step: (done, walk); when not done, walk[0:3] is the next key."""
    cx, cy, cz, kex, key_, kez, sx, sy, sz, tmx, tmy, tmz, tdx, tdy, tdz, flen = walk
    if tmx < tmy:
        dim = 0 if tmx < tmz else 2
    else:
        dim = 1 if tmy < tmz else 2
    if dim == 0:
        cx += sx
        tmx += tdx
    elif dim == 1:
        cy += sy
        tmy += tdy
    else:
        cz += sz
        tmz += tdz
    done = (cx == kex and cy == key_ and cz == kez) or min(tmx, tmy, tmz) > flen
    return done, (cx, cy, cz, kex, key_, kez, sx, sy, sz, tmx, tmy, tmz, tdx, tdy, tdz, flen)


@njit(cache=True, error_model="numpy")
def octomap_ray_keys(ox, oy, oz, ex, ey, ez, res, out):
    """OctoMap's computeRayKeys (`octomap_ray_start`) into `out` (n x 3): returns how many keys,
    or -1 when an end lies outside the key range."""
    first, walk = octomap_ray_start(ox, oy, oz, ex, ey, ez, res, 1.0 / res)
    if first <= 0:
        return first
    n_max = out.shape[0]
    n = 0
    while True:
        out[n, 0] = walk[0]
        out[n, 1] = walk[1]
        out[n, 2] = walk[2]
        n += 1
        done, walk = octomap_ray_next(walk)
        if done or n >= n_max:  # n_max: cannot happen for rays within the buffer's length
            break
    return n


@njit(cache=True, error_model="numpy")
def voxblox_ray_keys(sx, sy, sz, ex, ey, ez, inv_res, out):
    """voxblox's RayCaster: voxels from the start's to the end's, both included.

    Works in voxel-scaled coordinates like voxblox; the number of voxels is one more than the
    Manhattan distance between the end voxels. Axis-parallel components never step (voxblox
    intends this; its `abs(x) < 0` guard does not achieve it).
    """
    ax = sx * inv_res
    ay = sy * inv_res
    az = sz * inv_res
    bx = ex * inv_res
    by = ey * inv_res
    bz = ez * inv_res
    cx = np.int64(np.floor(ax))
    cy = np.int64(np.floor(ay))
    cz = np.int64(np.floor(az))
    n_steps = (
        abs(np.int64(np.floor(bx)) - cx)
        + abs(np.int64(np.floor(by)) - cy)
        + abs(np.int64(np.floor(bz)) - cz)
    )
    rx = bx - ax
    ry = by - ay
    rz = bz - az
    sgx = 1 if rx > 0 else (-1 if rx < 0 else 0)
    sgy = 1 if ry > 0 else (-1 if ry < 0 else 0)
    sgz = 1 if rz > 0 else (-1 if rz < 0 else 0)
    inf = np.inf
    tx = ((max(0, sgx) - (ax - cx)) / rx) if sgx != 0 else inf
    ty = ((max(0, sgy) - (ay - cy)) / ry) if sgy != 0 else inf
    tz = ((max(0, sgz) - (az - cz)) / rz) if sgz != 0 else inf
    stx = (sgx / rx) if sgx != 0 else inf
    sty = (sgy / ry) if sgy != 0 else inf
    stz = (sgz / rz) if sgz != 0 else inf
    n = 0
    n_max = out.shape[0]
    for _ in range(n_steps + 1):
        if n >= n_max:
            break
        out[n, 0] = cx
        out[n, 1] = cy
        out[n, 2] = cz
        n += 1
        if tx <= ty and tx <= tz:
            cx += sgx
            tx += stx
        elif ty <= tz:
            cy += sgy
            ty += sty
        else:
            cz += sgz
            tz += stz
    return n


class BlockGrid:
    """Python owner of the hash table, the block keys and the per-voxel columns.

    `fields` maps a column name to (dtype, trailing shape). Growth multiplies capacity by 1.5,
    so at most a third of the voxel columns is reserve; `stats()` reports used and reserved bytes.
    """

    def __init__(self, bits: int, fields: dict[str, tuple[np.dtype, tuple[int, ...]]]):
        if bits not in (2, 3, 4):
            raise ValueError(f"block_bits must be 2, 3 or 4 (block side 4, 8 or 16), got {bits}")
        self.bits = bits
        self.voxels_per_block = 1 << (3 * bits)
        self.fields = {k: (np.dtype(v[0]), tuple(v[1])) for k, v in fields.items()}
        self._n_blocks = np.zeros(1, np.int64)  # shared with the kernels through state()
        self.block_keys = np.empty(16, np.int64)
        self.cols = {
            k: np.zeros((16 * self.voxels_per_block, *shape), dt)
            for k, (dt, shape) in self.fields.items()
        }
        self._alloc_table(64)
        # name -> function turning a saved column into this layout (a back-end whose column
        # changed its dtype sets one, so that maps saved before still load)
        self.loaders: dict[str, Callable[[np.ndarray], np.ndarray]] = {}

    def _alloc_table(self, size: int) -> None:
        self.h_keys = np.full(size, -1, np.int64)
        self.h_vals = np.zeros(size, np.int32)
        self.hshift = 64 - (size.bit_length() - 1)

    @property
    def n_blocks(self) -> int:
        return int(self._n_blocks[0])

    @n_blocks.setter
    def n_blocks(self, n: int) -> None:
        self._n_blocks[0] = n

    def state(self) -> Grid:
        """The hash for a kernel; valid until the next growth."""
        return Grid(
            self.h_keys, self.h_vals, self.block_keys, self._n_blocks, self.hshift, self.bits
        )

    @property
    def block_capacity(self) -> int:
        return self.block_keys.shape[0]

    def grow_blocks(self, min_blocks: int | None = None) -> None:
        cap = max(int(self.block_capacity * 1.5) + 1, min_blocks or 0)
        keys = np.empty(cap, np.int64)
        keys[: self.n_blocks] = self.block_keys[: self.n_blocks]
        self.block_keys = keys
        n_used = self.n_blocks * self.voxels_per_block
        for k, col in self.cols.items():
            new = np.zeros((cap * self.voxels_per_block, *col.shape[1:]), col.dtype)
            new[:n_used] = col[:n_used]
            self.cols[k] = new

    def grow_table(self) -> None:
        size = self.h_keys.shape[0] * 2
        while size < 4 * (self.n_blocks + 1):
            size *= 2
        self._alloc_table(size)
        rebuild_table(self.state())

    def handle(self, status: int) -> None:
        if status == GROW_BLOCKS:
            self.grow_blocks()
        elif status == GROW_TABLE:
            self.grow_table()
        else:
            raise RuntimeError(f"unexpected kernel status {status}")

    def restore(self, block_keys: np.ndarray, cols: dict[str, np.ndarray]) -> None:
        """Replace the content with saved blocks (keys and used voxel columns)."""
        n = int(block_keys.shape[0])
        self.n_blocks = 0
        self.block_keys = np.empty(max(n, 16), np.int64)
        self.block_keys[:n] = block_keys
        nv = max(n, 16) * self.voxels_per_block
        for k, (dt, shape) in self.fields.items():
            col = np.zeros((nv, *shape), dt)
            load = self.loaders.get(k)
            col[: n * self.voxels_per_block] = cols[k] if load is None else load(cols[k])
            self.cols[k] = col
        self.n_blocks = n
        size = 64
        while size < 4 * max(n, 1):
            size *= 2
        self._alloc_table(size)
        rebuild_table(self.state())

    def used(self, name: str) -> np.ndarray:
        return self.cols[name][: self.n_blocks * self.voxels_per_block]

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Global voxel index of each (ix, iy, iz) row, -1 where no block holds it."""
        return lookup_voxels(np.ascontiguousarray(keys, np.int64), self.state())

    def insert(self, keys: np.ndarray) -> np.ndarray:
        """Global voxel index of each (ix, iy, iz) row (in the key range), allocating blocks."""
        keys = np.ascontiguousarray(keys, np.int64)
        out = np.empty(keys.shape[0], np.int64)
        i = 0
        while True:
            status, i = insert_voxels(keys, self.state(), out, i)
            if status == DONE:
                return out
            self.handle(status)

    def coords(self, gidx: np.ndarray) -> np.ndarray:
        return voxel_coords(np.ascontiguousarray(gidx, np.int64), self.state())

    def nbytes(self) -> tuple[int, int]:
        """(bytes holding allocated blocks, bytes reserved in total), hash table included."""
        per_voxel = sum(c.dtype.itemsize * int(np.prod(c.shape[1:])) for c in self.cols.values())
        table = self.h_keys.nbytes + self.h_vals.nbytes
        used = self.n_blocks * (self.voxels_per_block * per_voxel + 8) + table
        reserved = sum(c.nbytes for c in self.cols.values()) + self.block_keys.nbytes + table
        return used, reserved
