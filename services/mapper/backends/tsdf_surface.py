"""The TSDF's surface (tsdf.py's docstring: one voxel per sign change, of weight >= min_weight):
a voxel's status from its 6 face neighbours (`surface_kernel`), and the statuses a cloud changed,
around every voxel it updated (`extract_kernel`), kept in the SURFACE flag bits."""

from __future__ import annotations

import numpy as np
from numba import njit

from smana.services.mapper.block_grid import OBSERVED, table_find, voxel_index, voxel_key

# A flag bit of this back-end: the voxel was a surface voxel after the last cloud. Only the
# incremental surface count reads it; the surface itself is always recomputed from distances.
SURFACE = np.uint8(16)
_SEEN = np.uint8(32)  # scratch mark of the extraction, cleared before it returns
_FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.int64)


@njit(cache=True, error_model="numpy", inline="always")
def _near_voxel(grid, g, own_key, ix, iy, iz):
    """Global index of voxel (ix, iy, iz), -1 when its block was never allocated; `own_key` is
    the block key of voxel g, a neighbour: most neighbours share its block, with no hash probe."""
    bkey, local = voxel_index(ix, iy, iz, grid.bits)
    vb = 3 * grid.bits
    if bkey == own_key:
        return ((g >> vb) << vb) | local
    b = table_find(grid, bkey)
    return np.int64(-1) if b < 0 else (b << vb) | local


@njit(cache=True, error_model="numpy", inline="always")
def _is_surface(grid, distance, weight, min_weight, g, ix, iy, iz):
    """Voxel g at (ix, iy, iz) is a surface voxel (module docstring)."""
    if not weight[g] >= min_weight:
        return False
    d = distance[g]
    neg = d < 0
    ad = abs(d)
    own_key, _ = voxel_index(ix, iy, iz, grid.bits)
    for f in range(6):
        n = _near_voxel(grid, g, own_key, ix + _FACES[f, 0], iy + _FACES[f, 1], iz + _FACES[f, 2])
        if n < 0 or not weight[n] >= min_weight:
            continue
        dn = distance[n]
        if (dn < 0) == neg:
            continue
        adn = abs(dn)
        # the voxel nearer the crossing; on a tie the one in front (d >= 0), so exactly one
        if ad < adn or (ad == adn and not neg):
            return True
    return False


@njit(cache=True, error_model="numpy")
def surface_kernel(g, grid, distance, weight, min_weight, out):
    """out[i]: voxel g[i] is a surface voxel."""
    for i in range(g.shape[0]):
        ix, iy, iz = voxel_key(grid, g[i])
        out[i] = _is_surface(grid, distance, weight, min_weight, g[i], ix, iy, iz)


@njit(cache=True, error_model="numpy")
def extract_kernel(changed, st, min_weight, seen, out_g, out_surf):
    """Surface status after a cloud: of every updated voxel (listed whatever its status does) and
    of their observed face neighbours (listed only when their status flipped: an unchanged
    neighbour tells a consumer nothing). Sets the SURFACE bits; returns (listed, change in the
    surface count). `seen` (7 per updated voxel) holds the voxels examined, marked _SEEN meanwhile
    so that a voxel shared by several updated ones is looked at once."""
    grid = st.grid
    flags = st.flags
    distance = st.distance
    weight = st.weight
    n_seen = 0
    n_out = 0
    dcount = 0
    for i in range(changed.shape[0]):
        g = changed[i]
        flags[g] |= _SEEN
        seen[n_seen] = g
        n_seen += 1
    for i in range(changed.shape[0]):
        g = changed[i]
        ix, iy, iz = voxel_key(grid, g)
        own_key, _ = voxel_index(ix, iy, iz, grid.bits)
        s = _is_surface(grid, distance, weight, min_weight, g, ix, iy, iz)
        was = (flags[g] & SURFACE) != 0
        dcount += np.int64(s) - np.int64(was)
        flags[g] = (flags[g] | SURFACE) if s else (flags[g] & ~SURFACE)
        out_g[n_out] = g
        out_surf[n_out] = s
        n_out += 1
        for f in range(6):
            jx = ix + _FACES[f, 0]
            jy = iy + _FACES[f, 1]
            jz = iz + _FACES[f, 2]
            nb = _near_voxel(grid, g, own_key, jx, jy, jz)
            if nb < 0 or flags[nb] & _SEEN or not flags[nb] & OBSERVED:
                continue
            flags[nb] |= _SEEN
            seen[n_seen] = nb
            n_seen += 1
            s = _is_surface(grid, distance, weight, min_weight, nb, jx, jy, jz)
            was = (flags[nb] & SURFACE) != 0
            if s != was:
                dcount += 1 if s else -1
                flags[nb] = (flags[nb] | SURFACE) if s else (flags[nb] & ~SURFACE)
                out_g[n_out] = nb
                out_surf[n_out] = s
                n_out += 1
    for i in range(n_seen):
        flags[seen[i]] &= ~_SEEN
    return n_out, dcount
