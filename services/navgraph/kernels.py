"""The navigation graph's numba kernels (graph.py drives them): a map update's voxels prepared
(`prepare_voxels`), integrated into the node columns (`integrate_kernel`), and the safety zone
kept round the obstacles that changed (`safety_zone_kernel`). They take their state as the named
tuples of state.py; a helper (the node under a point, a column look-up, the safety-zone bit) is
written once for every kernel that needs it.
"""

from __future__ import annotations

import numba
import numpy as np

from smana.common.navgrid import FLAG_DOUBTFUL, FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE

from .state import CLEARED, LUT_OBSTACLE, LUT_ZONE, NO_FLOOR, SURFACE, UNUSABLE

# What one voxel did to its column (`_column_update`).
COLUMN_UNCHANGED, COLUMN_CHANGED, COLUMN_BELOW_FLOOR = 0, 1, 2


# -- kernels ---------------------------------------------------------------------------------
# Each kernel is a loop over voxels or nodes; the steps of the paper's update are the helpers
# below it, each written once and inlined (inline="always") into the kernels that use it.
#
# The kernels are compiled without numba's reference counting (`_nrt=False`): every array they
# touch is owned by the caller, and with the state passed as named tuples, counted references
# cost an atomic increment and decrement per helper call and tuple field read in the hot loops
# (numba cannot prune them across branches, numba/numba#2350), which made the column update four
# times slower. Without it the structures are free; a kernel that tried to allocate an array
# would fail to compile, so the callers allocate every output.


@numba.njit(cache=True, inline="always")
def _cell_of(geo, x, y):
    """The graph cell (ix, iy) under a world point (may be out of bounds)."""
    ix = int(np.floor((x - geo.origin_x) / geo.resolution_m))
    iy = int(np.floor((y - geo.origin_y) / geo.resolution_m))
    return ix, iy


@numba.njit(cache=True, inline="always")
def _in_bounds(geo, ix, iy):
    return 0 <= ix < geo.nx and 0 <= iy < geo.ny


@numba.njit(cache=True, inline="always")
def _node_index(geo, ix, iy):
    """The flat node index of an in-bounds cell, -1 where its tile is not allocated."""
    t = geo.tile_size
    slot = geo.tile_map[ix // t, iy // t]
    if slot < 0:
        return -1
    return slot * t * t + (ix % t) * t + (iy % t)


@numba.njit(cache=True, inline="always")
def _cell_of_node(geo, n):
    """The cell (ix, iy) of a flat node index (`NavGrid.cells_of_flat`)."""
    t = geo.tile_size
    slot = n // (t * t)
    local = n % (t * t)
    return geo.tile_coords[slot, 0] * t + local // t, geo.tile_coords[slot, 1] * t + local % t


@numba.njit(cache=True, inline="always")
def _voxel_key(geo, map_res, x, y, z):
    """A map voxel's place in its column: level (map z index) and sub-column id."""
    gz = np.int32(np.floor(z / map_res))
    gx = int(np.floor((x - geo.origin_x) / map_res))
    gy = int(np.floor((y - geo.origin_y) / map_res))
    return gz, np.uint16(((gx & 255) << 8) | (gy & 255))


@numba.njit(cache=True, inline="always")
def _with_safety_zone(flags, obstacle_count):
    """A node is in the safety zone when a zone centre (an obstacle, or a forbidden class with
    `forbidden_margin`) is within the robot radius (its count is positive) and it is not an
    obstacle itself (a forbidden node is in its own zone: never entered either way). A doubtful
    node is no centre, but may lie within a real obstacle's zone."""
    if obstacle_count > 0 and not (flags & FLAG_OBSTACLE):
        return flags | np.uint8(FLAG_SAFETY_ZONE)
    return flags & ~np.uint8(FLAG_SAFETY_ZONE)


@numba.njit(cache=True, inline="always")
def _touch(nodes, epoch, changes, nd, n):
    """Record node n's state before this integration changes it, once per integration."""
    if nodes.epoch[n] != epoch:
        nodes.epoch[n] = epoch
        changes.node[nd] = n
        changes.label[nd] = nodes.labels[n]
        changes.height[nd] = nodes.heights[n]
        changes.flags[nd] = nodes.flags[n]
        changes.alt_label[nd] = nodes.alt_labels[n]
        changes.p_label[nd] = nodes.p_label[n]
        changes.p_alt[nd] = nodes.p_alt[n]
        return nd + 1
    return nd


@numba.njit(cache=True, inline="always")
def _probability_step(c, nan_as):
    """A probability as the graph keeps it: x 255 rounded half up, clipped to 0..255 (NaN:
    nan_as). (Half up, not Python's half to even: a floor is a tenth of its cost here.)"""
    if c != c:
        c = nan_as
    c = min(max(np.float64(c), 0.0), 1.0)
    return np.uint8(np.floor(c * 255.0 + 0.5))


@numba.njit(cache=True, _nrt=False)
def prepare_voxels(labels, occupied, luts, geo, vox, missing, dist):
    """Per voxel of `vox.centres`: the clean label `vox.labels` (ids outside the table -> 0), its
    `vox.kinds` (CLEARED, SURFACE, or UNUSABLE: a non-finite coordinate), a surface voxel's
    distribution in steps of 1/255 (`vox.alt_labels`, `vox.p_label`, `vox.p_alt` from `dist`:
    p_alt capped so the two never pass 255; a second class 0, outside the table or of
    probability 0 is none; other voxels' are never read and stay unset),
    and the ids (tx * nty + ty) of unallocated tiles under in-bounds surface voxels, each once,
    in `missing`. Returns the counts (missing tiles, non-finite rows, unknown labels, surface
    voxels)."""
    cen = vox.centres
    lab = vox.labels
    kind = vox.kinds
    valid_lut = luts.valid
    ignored_lut = luts.ignored
    m = len(cen)
    tile_map = geo.tile_map
    t = geo.tile_size
    nty = tile_map.shape[1]
    n_lut = len(valid_lut)
    n_missing = 0
    n_nonfinite = 0
    n_unknown = 0
    n_surface = 0
    has_p = dist.confidences.shape[0] == m
    has_alt = has_p and dist.alt_labels.shape[0] == m and dist.alt_confidences.shape[0] == m
    for i in range(m):
        x = cen[i, 0]
        y = cen[i, 1]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(cen[i, 2])):
            kind[i] = UNUSABLE
            lab[i] = 0
            n_nonfinite += 1
            continue
        lb = labels[i]
        if lb >= n_lut or not valid_lut[lb]:
            lb = 0
            n_unknown += 1
        lab[i] = lb
        surface = occupied[i] != 0
        # An ignored class (sky, ...) is not ground: treat it as a cleared voxel.
        if ignored_lut[lb]:
            surface = False
        kind[i] = SURFACE if surface else CLEARED
        if not surface:
            continue
        n_surface += 1
        p = np.uint8(255)
        alt = np.uint16(0)
        pa = np.uint8(0)
        if has_p:
            p = _probability_step(dist.confidences[i], 1.0)
            if has_alt:
                alt = dist.alt_labels[i]
                pa = min(_probability_step(dist.alt_confidences[i], 0.0), np.uint8(255 - p))
                if alt == 0 or alt >= n_lut or not valid_lut[alt] or pa == 0:
                    alt = np.uint16(0)  # not counted: the label is what a node shows
                    pa = np.uint8(0)
        vox.p_label[i] = p
        vox.alt_labels[i] = alt
        vox.p_alt[i] = pa
        ix, iy = _cell_of(geo, x, y)
        if not _in_bounds(geo, ix, iy):
            continue
        tx = ix // t
        ty = iy // t
        if tile_map[tx, ty] == -1:
            tile_map[tx, ty] = -2  # mark so each tile is reported once
            missing[n_missing] = tx * nty + ty
            n_missing += 1
    for k in range(n_missing):
        tile_map[missing[k] // nty, missing[k] % nty] = -1
    return n_missing, n_nonfinite, n_unknown, n_surface


@numba.njit(cache=True, _nrt=False)
def integrate_kernel(vox, geo, nodes, cols, rule, epoch, changes, flips):
    """Column update for every usable voxel, then node head recompute for every touched node.
    Returns the counts (touched nodes, zone flips, out of bounds, below floor, columns lost);
    the flips (node, +1 became a zone centre / -1 stopped) are for the safety-zone kernel."""
    cen = vox.centres
    kind = vox.kinds
    map_res = vox.map_resolution_m
    nd = 0
    n_oob = 0
    n_below = 0
    for i in range(len(cen)):
        if kind[i] == UNUSABLE:
            continue
        x = cen[i, 0]
        y = cen[i, 1]
        ix, iy = _cell_of(geo, x, y)
        if not _in_bounds(geo, ix, iy):
            n_oob += 1
            continue
        n = _node_index(geo, ix, iy)
        if n < 0:
            continue  # a cleared voxel over a region never seen: nothing to recompute
        gz, sub = _voxel_key(geo, map_res, x, y, cen[i, 2])
        done = _column_update(cols, nodes, n, gz, sub, vox, i)
        if done == COLUMN_BELOW_FLOOR:
            n_below += 1
        elif done == COLUMN_CHANGED:
            nd = _touch(nodes, epoch, changes, nd, n)

    nf = 0
    n_lost = 0
    for k in range(nd):
        n = changes.node[k]
        was_known = (changes.flags[k] & FLAG_KNOWN) != 0
        if nodes.col_head[n] < 0 and nodes.col_floor[n] != NO_FLOOR and was_known:
            n_lost += 1
        centre = _node_head_recompute(cols, nodes, rule, n)
        was_centre = _zone_centre(rule.kind, changes.label[k], changes.flags[k])
        if centre != was_centre:
            flips.node[nf] = n
            flips.sign[nf] = 1 if centre else -1
            nf += 1
    return nd, nf, n_oob, n_below, n_lost


@numba.njit(cache=True, inline="always")
def _column_update(cols, nodes, n, gz, sub, vox, i):
    """Apply voxel i of `vox` to node n's column: a surface voxel is added or relabelled (its
    label distribution with it), a cleared one removed. Returns COLUMN_CHANGED,
    COLUMN_UNCHANGED or COLUMN_BELOW_FLOOR."""
    label = vox.labels[i]
    z = vox.centres[i, 2]
    prev, found, found_prev = _column_find(cols, nodes.col_head[n], gz, sub)
    if vox.kinds[i] == SURFACE:
        if found >= 0:
            if (
                cols.label[found] == label
                and cols.p_label[found] == vox.p_label[i]
                and cols.alt_label[found] == vox.alt_labels[i]
                and cols.p_alt[found] == vox.p_alt[i]
                and cols.solid[found] == vox.solid[i]
            ):
                return COLUMN_UNCHANGED  # same voxel, same distribution: the node cannot change
            cols.label[found] = label
            cols.z[found] = z
            _entry_distribution(cols, found, vox, i)
        else:
            if gz <= nodes.col_floor[n]:
                return COLUMN_BELOW_FLOOR
            e = _column_insert(cols, nodes, n, prev, gz, sub, label, z)
            _entry_distribution(cols, e, vox, i)
            if nodes.col_len[n] > cols.column_capacity:
                _column_forget_lowest(cols, nodes, n)
    else:
        if found < 0:
            return COLUMN_UNCHANGED  # free voxel that was never in the column
        _column_unlink(cols, nodes, n, found, found_prev)
        _entry_free(cols, found)
        nodes.col_len[n] -= 1
    return COLUMN_CHANGED


@numba.njit(cache=True, inline="always")
def _entry_distribution(cols, e, vox, i):
    cols.alt_label[e] = vox.alt_labels[i]
    cols.p_label[e] = vox.p_label[i]
    cols.p_alt[e] = vox.p_alt[i]
    cols.solid[e] = vox.solid[i]


@numba.njit(cache=True, inline="always")
def _column_find(cols, head, gz, sub):
    """Walk a column (highest level first) to level gz: returns the last entry above it (-1 for
    none: insert at the head), and the entry of sub-column `sub` at that level with the entry
    before it (-1, -1 when the voxel is not in the column)."""
    prev = -1
    e = head
    while e >= 0 and cols.level[e] > gz:
        prev = e
        e = cols.next[e]
    before = prev
    while e >= 0 and cols.level[e] == gz:
        if cols.sub[e] == sub:
            return prev, e, before
        before = e
        e = cols.next[e]
    return prev, -1, -1


@numba.njit(cache=True, inline="always")
def _entry_new(cols):
    """An entry from the free list, or past the high-water mark."""
    state = cols.state
    if state[0] >= 0:
        e = state[0]
        state[0] = cols.next[e]
    else:
        e = state[1]
        state[1] += 1
    state[2] += 1
    return e


@numba.njit(cache=True, inline="always")
def _entry_free(cols, e):
    cols.next[e] = cols.state[0]
    cols.state[0] = e
    cols.state[2] -= 1


@numba.njit(cache=True, inline="always")
def _column_insert(cols, nodes, n, prev, gz, sub, label, z):
    """A new entry after `prev` (before the first entry of a lower level)."""
    e = _entry_new(cols)
    cols.level[e] = gz
    cols.sub[e] = sub
    cols.label[e] = label
    cols.z[e] = z
    if prev < 0:
        cols.next[e] = nodes.col_head[n]
        nodes.col_head[n] = e
    else:
        cols.next[e] = cols.next[prev]
        cols.next[prev] = e
    nodes.col_len[n] += 1
    return e


@numba.njit(cache=True, inline="always")
def _column_unlink(cols, nodes, n, e, before):
    if before < 0:
        nodes.col_head[n] = cols.next[e]
    else:
        cols.next[before] = cols.next[e]


@numba.njit(cache=True, inline="always")
def _column_forget_lowest(cols, nodes, n):
    """An overflowing column forgets its lowest level whole, so that the list stays exact above
    the floor it now remembers."""
    cur = nodes.col_head[n]
    lowest = cols.level[cur]
    while cur >= 0:
        lowest = cols.level[cur]
        cur = cols.next[cur]
    cut = -1
    cur = nodes.col_head[n]
    while cur >= 0 and cols.level[cur] > lowest:
        cut = cur
        cur = cols.next[cur]
    if cut < 0:
        nodes.col_head[n] = -1
    else:
        cols.next[cut] = -1
    while cur >= 0:
        after = cols.next[cur]
        _entry_free(cols, cur)
        nodes.col_len[n] -= 1
        cur = after
    nodes.col_floor[n] = lowest


@numba.njit(cache=True, inline="always")
def _zone_centre(kind_lut, label, flags):
    """Whether a node with this label and flags is a centre of the safety zone: an obstacle (a
    doubtful one is not), or known and of a forbidden class with `forbidden_margin`."""
    if flags & FLAG_OBSTACLE:
        return True
    return (flags & FLAG_KNOWN) != 0 and (kind_lut[label] & LUT_ZONE) != 0


@numba.njit(cache=True, inline="always")
def _node_head_recompute(cols, nodes, rule, n):
    """Node n shows its column's head: label, height and flags from the highest level, with
    that voxel's label distribution; an empty column is unknown (and certain: nothing to be
    unsure of). Called once per node an update changed, so it also counts the node's evidence.
    Returns whether the node is a centre of the safety zone now. Its height is the highest
    solid voxel's (the top's while none is solid).

    The top level votes for an obstacle class when every label there is certain (probability 1
    from a map that sends no distribution: `rule.certain`) and one has it
    (the paper's conservative rule), or when at least half of its voxels have one (one wrong
    label among four lawn voxels is no vote). The vote moves the evidence (+1, or
    -`rule.miss_weight` against; a certain vote sets it to the cap). The node shows an obstacle
    voxel when the vote says so and the label is certain, the evidence is positive, or no other
    voxel is there; otherwise the level's other voxel: a lawn that the map mislabels now and
    then stays a lawn. Among voxels of one kind the larger sub-column id wins, so the result
    does not depend on arrival order. `_blocks` then sets the flags."""
    kind_lut = rule.kind
    e = nodes.col_head[n]
    flags = np.uint8(0)
    if e < 0:
        nodes.labels[n] = 0
        nodes.heights[n] = np.nan
        nodes.alt_labels[n] = 0
        nodes.p_label[n] = 255
        nodes.p_alt[n] = 0
        nodes.obstacle_evidence[n] = 0
    else:
        best_ob = -1  # the top level's obstacle voxel and other voxel of largest sub-column id
        best_other = -1
        n_top = 0
        n_ob = 0
        certain = True
        # one walk down the column, sorted from the highest level: the top level's voxels, the
        # first solid entry (the highest solid voxel) and the last one (the lowest voxel)
        solid_z = np.nan
        low_z = cols.z[e]
        cur = e
        while cur >= 0:
            if cols.level[cur] == cols.level[e]:
                n_top += 1
                certain = certain and rule.certain and cols.p_label[cur] == 255
                if (kind_lut[cols.label[cur]] & LUT_OBSTACLE) != 0:
                    n_ob += 1
                    if best_ob < 0 or cols.sub[cur] > cols.sub[best_ob]:
                        best_ob = cur
                elif best_other < 0 or cols.sub[cur] > cols.sub[best_other]:
                    best_other = cur
            if solid_z != solid_z and cols.solid[cur]:
                solid_z = cols.z[cur]
            low_z = cols.z[cur]
            cur = cols.next[cur]
        vote = n_ob > 0 and (certain or 2 * n_ob >= n_top)
        ev = np.int64(nodes.obstacle_evidence[n])
        if vote:
            ev = rule.cap if certain else min(ev + 1, rule.cap)
        else:
            ev = max(ev - rule.miss_weight, -rule.cap)
        nodes.obstacle_evidence[n] = ev
        best = best_ob if vote and (certain or ev > 0 or best_other < 0) else best_other
        nodes.labels[n] = cols.label[best]
        # the height the robot drives at: the highest solid voxel's, not a voxel above it that
        # noisy poses smeared there and views since saw through (its step would cut the
        # planner's edges where the ground is flat); the top's when nothing is solid yet
        nodes.heights[n] = solid_z if solid_z == solid_z else cols.z[best]
        nodes.alt_labels[n] = cols.alt_label[best]
        nodes.p_label[n] = cols.p_label[best]
        nodes.p_alt[n] = cols.p_alt[best]
        flags |= np.uint8(FLAG_KNOWN)
        rise = solid_z - low_z if solid_z == solid_z else 0.0
        flags |= _blocks(rule, cols.label[best], cols.p_label[best], ev, rise)
    nodes.flags[n] = _with_safety_zone(flags, nodes.obstacle_count[n])
    return _zone_centre(kind_lut, nodes.labels[n], flags)


@numba.njit(cache=True, inline="always")
def _blocks(rule, label, p_label, evidence, rise_m):
    """FLAG_OBSTACLE, FLAG_DOUBTFUL or 0 for a known node showing `label` (its probability x
    255 `p_label`) whose highest solid voxel rises `rise_m` over its lowest. Geometry blocks
    whatever the label (a step the robot cannot climb); an obstacle class blocks when its label is
    certain (`rule.certain`: no distribution came with it), or when `rule.confirm` > 0 and the
    node's evidence reached it; it is doubtful otherwise (with `rule.confirm` 0, the default, an
    uncertain label never blocks alone)."""
    if rise_m > rule.step_m:
        return np.uint8(FLAG_OBSTACLE)
    if (rule.kind[label] & LUT_OBSTACLE) == 0:
        return np.uint8(0)
    if (rule.certain and p_label == 255) or (rule.confirm > 0 and evidence >= rule.confirm):
        return np.uint8(FLAG_OBSTACLE)
    return np.uint8(FLAG_DOUBTFUL)


@numba.njit(cache=True, _nrt=False)
def safety_zone_kernel(flips, stencil, geo, nodes, epoch, changes):
    """Safety-zone update: each zone-centre flip changes the count of the nodes of its disc by
    one, and their safety-zone bit with it. Returns how many nodes it touched."""
    stencil_dx = stencil.dx
    stencil_dy = stencil.dy
    sign = flips.sign
    nd = 0
    for k in range(len(flips.node)):
        ix, iy = _cell_of_node(geo, flips.node[k])
        for j in range(len(stencil_dx)):
            jx = ix + stencil_dx[j]
            jy = iy + stencil_dy[j]
            if not _in_bounds(geo, jx, jy):
                continue
            m = _node_index(geo, jx, jy)
            if m < 0:
                continue  # only when removing an obstacle whose disc was never allocated
            nd = _touch(nodes, epoch, changes, nd, m)
            nodes.obstacle_count[m] += sign[k]
            nodes.flags[m] = _with_safety_zone(nodes.flags[m], nodes.obstacle_count[m])
    return nd
