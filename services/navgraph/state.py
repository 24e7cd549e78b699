"""The state the navigation graph's kernels take (kernels.py), as named tuples of arrays:
numba unpacks them at no cost, so no kernel takes more than eight arguments (`GridGeometry`,
`NodeLayers`, `ColumnStore`, `NodeChanges`, `Voxels`, `Flips`, ...), and the constants they share
with graph.py (voxel kinds, class kind bits, the empty column floor)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

NO_FLOOR = int(np.iinfo(np.int32).min)  # col_floor of a column that never overflowed

# Voxel kinds after `prepare_voxels`.
CLEARED, SURFACE, UNUSABLE = 0, 1, 2


class GridGeometry(NamedTuple):
    """Where the nodes are: the NavGrid's layout as the kernels read it (build it after allocating
    tiles: `tile_coords` is replaced when the tile pool grows)."""

    origin_x: float
    origin_y: float
    resolution_m: float
    nx: int
    ny: int
    tile_size: int
    tile_map: np.ndarray  # (ntx, nty) int32: slot of each tile, < 0 where not allocated
    tile_coords: np.ndarray  # (capacity, 2) int32: tile (tx, ty) of each slot


class NodeLayers(NamedTuple):
    """The graph grid's per-node state, each layer flat by node index (`NavGrid.flat`)."""

    labels: np.ndarray  # u2, as published
    heights: np.ndarray  # f4, as published (NaN where unknown)
    flags: np.ndarray  # u1, as published: FLAG_KNOWN | FLAG_OBSTACLE | FLAG_SAFETY_ZONE
    col_head: np.ndarray  # i4: the column's highest entry, -1 when empty
    col_len: np.ndarray  # i4: entries in the column
    col_floor: np.ndarray  # i4: highest level forgotten on overflow, NO_FLOOR if none
    obstacle_count: np.ndarray  # i4: zone centres (obstacles; forbidden with the margin) within
    # the robot radius, itself included
    epoch: np.ndarray  # u4: the integration that last touched the node (see NodeChanges)
    # the label distribution of the voxel that sets the label (NavGrid RISK_LAYERS), as published
    alt_labels: np.ndarray  # u2: the second most likely class, 0 for none
    p_label: np.ndarray  # u1: probability of `labels` x 255
    p_alt: np.ndarray  # u1: probability of `alt_labels` x 255
    # i1: the node's evidence for an obstacle class (NodeRule): +1 per update whose top level
    # votes for one, -miss_weight per update whose does not, within +/- cap
    obstacle_evidence: np.ndarray


class ColumnStore(NamedTuple):
    """The entry pool every column lives in: one linked list per node, highest level first; freed
    entries form a free list through `next`."""

    level: np.ndarray  # i4: the voxel's map z index
    sub: np.ndarray  # u2: sub-column id, (gx mod 256) << 8 | (gy mod 256)
    label: np.ndarray  # u2
    z: np.ndarray  # f4: the voxel centre's height
    next: np.ndarray  # i4: the next entry down the column (or the free list), -1 at the end
    alt_label: np.ndarray  # u2: the voxel's second class (0: none)
    p_label: np.ndarray  # u1: probability of `label` x 255
    p_alt: np.ndarray  # u1: probability of `alt_label` x 255
    solid: np.ndarray  # u1: the voxel may support a geometric obstacle (Voxels.solid)
    state: np.ndarray  # i8[3]: free-list head, high-water mark, entries in use
    column_capacity: int  # entries a column keeps before it forgets its lowest level


class NodeChanges(NamedTuple):
    """The nodes one integration touched, each once (stamped with the epoch), with their state
    from before, so that only the nodes that really differ are reported."""

    node: np.ndarray  # i8 flat node index
    label: np.ndarray  # u2
    height: np.ndarray  # f4
    flags: np.ndarray  # u1
    alt_label: np.ndarray  # u2
    p_label: np.ndarray  # u1
    p_alt: np.ndarray  # u1

    @classmethod
    def empty(cls, n: int) -> NodeChanges:
        return cls(
            np.empty(n, np.int64),
            np.empty(n, np.uint16),
            np.empty(n, np.float32),
            np.empty(n, np.uint8),
            np.empty(n, np.uint16),
            np.empty(n, np.uint8),
            np.empty(n, np.uint8),
        )

    def head(self, n: int) -> NodeChanges:
        return NodeChanges(*(a[:n] for a in self))


class Voxels(NamedTuple):
    """One map update as the kernels read it: `prepare_voxels` fills the clean labels and kinds."""

    centres: np.ndarray  # (M, 3) float: voxel centres, as the delta holds them
    labels: np.ndarray  # u2 (M,): class ids, those outside the table read as 0
    kinds: np.ndarray  # u1 (M,): CLEARED, SURFACE or UNUSABLE
    map_resolution_m: float
    alt_labels: np.ndarray  # u2 (M,): the second class (`prepare_voxels` fills it: Distribution)
    p_label: np.ndarray  # u1 (M,): probability of `labels` x 255
    p_alt: np.ndarray  # u1 (M,): probability of `alt_labels` x 255
    solid: np.ndarray  # u1 (M,): 1 where the voxel may support a geometric obstacle (graph.py)


class Distribution(NamedTuple):
    """The label distribution a map update carries per voxel (MapDelta v2), as sent; empty
    arrays where it carries none (the voxels are then certain)."""

    confidences: np.ndarray  # f4 (M,) or (0,): probability of the label
    alt_labels: np.ndarray  # u2 (M,) or (0,): the second class, 0 for none
    alt_confidences: np.ndarray  # f4 (M,) or (0,): its probability


class NodeRule(NamedTuple):
    """When a node blocks (the [navgraph] obstacle_step_m / semantic_* fields): its class's kind
    bits, the column height over its lowest voxel that blocks whatever the label, and the evidence
    an uncertain obstacle label needs."""

    kind: np.ndarray  # u1 per label id: LUT_OBSTACLE | LUT_ZONE bits (ClassLuts.kind)
    step_m: float
    confirm: int  # evidence at which an uncertain obstacle label blocks (0: never alone)
    miss_weight: int
    cap: int  # evidence is kept within [-cap, cap]
    # labels of probability 1 are certain (they vote at once, and an obstacle class blocks):
    # only when the map sends no distribution. A map's own probability of 1 is not certainty.
    certain: bool = True


class ClassLuts(NamedTuple):
    """What the class table says about a label id, as look-up tables."""

    valid: np.ndarray  # bool: the id is in the table
    ignored: np.ndarray  # bool: not ground (sky, ...): its voxels count as cleared
    kind: np.ndarray  # u1: LUT_OBSTACLE | LUT_ZONE bits


# The bits of ClassLuts.kind: an obstacle class, and a class whose nodes the safety zone surrounds
# by their label alone (with `navgraph.forbidden_margin`, every forbidden one); an obstacle node
# (FLAG_OBSTACLE: confirmed, not doubtful) is always a centre of the zone.
LUT_OBSTACLE = 1
LUT_ZONE = 2


class Flips(NamedTuple):
    """Nodes that became (+1) or stopped being (-1) a centre of the safety zone (an obstacle, or a
    forbidden class with `navgraph.forbidden_margin`): the safety zone's input."""

    node: np.ndarray  # i8 flat node index
    sign: np.ndarray  # i4 +1 or -1

    def head(self, n: int) -> Flips:
        return Flips(self.node[:n], self.sign[:n])


class DiscStencil(NamedTuple):
    """The cell offsets within the robot radius of a node (itself included)."""

    dx: np.ndarray  # i8
    dy: np.ndarray  # i8
