"""The navigation graph builder (paper 3.3.1): map deltas in, changed nodes out. No zenoh here.

Each map voxel is projected to the 2.5D node under it. A node shows the highest occupied voxel of
its column (the first voxel sets label and height, afterwards the highest wins), and the safety
zone marks nodes within `robot_radius_m` of an obstacle (and, with `forbidden_margin`, the default,
of a node whose label is a forbidden class: water).

A node doubts before it blocks (STYLE: a single observation sets a cost, not a wall). It is an
obstacle when geometry says so: its highest solid voxel (`solid_log_odds` for an occupancy map)
rises more than `obstacle_step_m` over its lowest voxel, whatever the label; or when it shows an
obstacle class of the class table whose label is certain (a map that sends no distribution: a
map's own probability of 1 is not certainty, since Bayesian fusion reaches it after two views
that agree and pose noise smears noise-free labels), or, with `semantic_confirm` > 0, confirmed
by the node's evidence. What it
shows is weighed over updates: the top level votes, the vote moves the evidence (the
`obstacle_evidence` layer: +1, or -`semantic_miss_weight`), and an obstacle voxel is shown only
while the evidence is positive. An uncertain obstacle class short of blocking is FLAG_DOUBTFUL:
passable at the planner's `doubtful_cost`, and no centre of the safety zone, so a few wrong
labels on the ground no longer wall the robot in; a wrong label fades when later views disagree,
as Nav2's obstacle layer clears what its rays see through.

A voxel is a surface voxel when the map says it is occupied. A map that carries signed distances
(`MapDelta.values_kind == "signed_distance"`) marks its extracted surface in `occupied` (the zero
crossing between neighbouring voxels, one voxel thick, as voxblox and Kimera mesh it), so the graph
reads it the same way; widening it to every voxel with |distance| below the graph resolution (the
paper's rule) was dropped: under pose noise that band thickens and lifts node heights. The graph
reads what a delta holds, never which back-end made it.

To recompute a node when the map clears a voxel (an obstacle that moved away) the node must know
what remains below, so every node keeps its column: a linked list of the occupied voxels projected
to it, sorted from the highest down, in a shared entry pool (`ColumnStore`). The list is bounded by
`column_capacity`: when a column overflows, its lowest level is forgotten and the node remembers
that level as its `floor`; voxels at or below the floor are then ignored. The list is therefore
always exactly "every occupied voxel above the floor", and a column that loses all its tracked
voxels while it has a floor becomes unknown rather than showing a ghost or a guess.

The safety zone is kept current incrementally: every node counts the zone centres (obstacle nodes,
and forbidden ones with `forbidden_margin`) within the robot radius (itself included); when a node
becomes or stops being a centre, the counts of the nodes of a disc stencil around it change by
one. A node is in the safety zone when its count is positive and it is not an obstacle itself.
Tiles within the radius of a centre are allocated so that the zone also covers nodes not seen
yet.

Each node also keeps the label distribution of the voxel that sets its label (the NavGrid's
RISK_LAYERS: the second class and both probabilities x 255), as the map delta carried it; a delta
without one (version 1) gives certain voxels. A node changes, and is published, when its
distribution moves by at least one step of 1/255.

The numba kernels are in `kernels.py`, the named tuples of arrays they take as state in
`state.py`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from smana.common.classes import ClassTable
from smana.common.config.navgraph import NavgraphConfig
from smana.common.navgrid import (
    FLAG_DOUBTFUL,
    FLAG_KNOWN,
    FLAG_OBSTACLE,
    FLAG_SAFETY_ZONE,
    P_SCALE,
    RISK_LAYER_NAMES,
    NavGrid,
)

from .kernels import integrate_kernel, prepare_voxels, safety_zone_kernel
from .state import (
    LUT_OBSTACLE,
    LUT_ZONE,
    NO_FLOOR,
    ClassLuts,
    ColumnStore,
    DiscStencil,
    Distribution,
    Flips,
    GridGeometry,
    NodeChanges,
    NodeLayers,
    NodeRule,
    Voxels,
)

# The least bound of a node's evidence (+/-): enough memory that a lawn mislabelled for a few
# updates stays a lawn, short enough that a real change shows within a few more.
EVIDENCE_CAP = 8

# What `integrate_delta` reads from each kind of MapDelta.values (common/messages.py VALUES_KINDS),
# given the [navgraph] section: both say where the surface is with `occupied` (a signed-distance
# map's extracted surface); an occupancy map's log-odds also say which surface voxels are solid
# enough to make a geometric obstacle (`solid_log_odds`); a future kind names its inputs here.
SURFACE_INPUTS = {
    "log_odds": lambda delta, config: {"solid": np.asarray(delta.values) >= config.solid_log_odds},
    "signed_distance": lambda delta, config: {},
}


@dataclass
class GraphUpdate:
    """What one integration changed: the nodes whose label, height or flags differ afterwards."""

    cells: np.ndarray  # (K, 2) int32 grid indices from the grid origin
    labels: np.ndarray  # (K,) u2
    heights: np.ndarray  # (K,) f4, NaN where the node is not known
    flags: np.ndarray  # (K,) u1
    # their label distributions (NavGrid RISK_LAYERS): alt_labels u2, p_label u1, p_alt u1
    alt_labels: np.ndarray | None = None
    p_label: np.ndarray | None = None
    p_alt: np.ndarray | None = None
    n_voxels: int = 0
    n_surface: int = 0  # voxels that add to or update a column
    n_out_of_bounds: int = 0
    n_nonfinite: int = 0
    n_unknown_labels: int = 0  # labels outside the class table, read as unknown (id 0)
    n_below_floor: int = 0  # surface voxels ignored because their column overflowed below them
    n_columns_lost: int = 0  # columns emptied above their floor (became unknown)
    n_new_tiles: int = 0
    time_ms: float = 0.0


def same_nodes(label_a, height_a, flags_a, label_b, height_b, flags_b) -> np.ndarray:
    """Where two node states are equal (two unknown heights, NaN, are equal)."""
    same_h = (height_a == height_b) | (np.isnan(height_a) & np.isnan(height_b))
    return (label_a == label_b) & (flags_a == flags_b) & same_h


# what an update without a distribution passes (read-only, as a decoded delta's arrays are, so
# that both kinds of update use the kernel compiled for decoded deltas)
_NO_F4 = np.zeros(0, np.float32)
_NO_U2 = np.zeros(0, np.uint16)
_NO_F4.flags.writeable = False
_NO_U2.flags.writeable = False


class NavGraph:
    """A 2.5D semantic navigation graph inside fixed bounds, built from map deltas.

    `config` is the `[navgraph]` section as it is (bounds, resolution, robot radius, tile size,
    column capacity); it is validated when it is made."""

    def __init__(self, classes: ClassTable, config: NavgraphConfig | None = None):
        self.config = config = NavgraphConfig() if config is None else config
        self.classes = classes
        self.grid = NavGrid.from_bounds(
            config.bounds_min_xy, config.bounds_max_xy, config.resolution_m, config.tile_size
        )
        g = self.grid
        g.add_layer("col_head", np.int32, -1)
        g.add_layer("col_len", np.int32, 0)
        g.add_layer("col_floor", np.int32, NO_FLOOR)
        g.add_layer("obstacle_count", np.int32, 0)
        g.add_layer("epoch", np.uint32, 0)
        g.add_layer("obstacle_evidence", np.int8, 0)
        g.add_risk_layers()
        self._epoch = 0
        cap = 1024
        self.columns = ColumnStore(
            level=np.zeros(cap, np.int32),
            sub=np.zeros(cap, np.uint16),
            label=np.zeros(cap, np.uint16),
            z=np.zeros(cap, np.float32),
            next=np.full(cap, -1, np.int32),
            alt_label=np.zeros(cap, np.uint16),
            p_label=np.full(cap, P_SCALE, np.uint8),
            p_alt=np.zeros(cap, np.uint8),
            solid=np.ones(cap, np.uint8),
            state=np.array([-1, 0, 0], np.int64),
            column_capacity=config.column_capacity,
        )
        kind = classes.obstacle_lut * np.uint8(LUT_OBSTACLE)
        if config.forbidden_margin:
            kind |= classes.forbidden_lut * np.uint8(LUT_ZONE)
        self._luts = ClassLuts(classes.valid_lut, classes.ignored_lut.copy(), kind.astype(np.uint8))
        self._rule = NodeRule(
            self._luts.kind,
            float(config.obstacle_step_m),
            int(config.semantic_confirm),
            int(config.semantic_miss_weight),
            max(2 * int(config.semantic_confirm), EVIDENCE_CAP),
        )
        res, radius = self.resolution_m, config.robot_radius_m
        r_cells = int(np.floor(radius / res + 1e-9))
        dx, dy = np.meshgrid(np.arange(-r_cells, r_cells + 1), np.arange(-r_cells, r_cells + 1))
        # Centre-to-centre distance; the small slack keeps nodes at exactly the radius inside.
        inside = np.hypot(dx, dy) * res <= radius + 1e-9
        self._stencil = DiscStencil(dx[inside].astype(np.int64), dy[inside].astype(np.int64))
        self._stencil_reach = r_cells
        self.n_integrations = 0
        self._kernel_view: tuple[int, GridGeometry, NodeLayers] | None = None

    @property
    def resolution_m(self) -> float:
        return self.grid.resolution_m

    # -- memory --------------------------------------------------------------------------------

    @property
    def nbytes(self) -> int:
        c = self.columns
        arrays = (c.level, c.sub, c.label, c.z, c.next, c.alt_label, c.p_label, c.p_alt, c.solid)
        return self.grid.nbytes + sum(a.nbytes for a in arrays)

    @property
    def n_column_voxels(self) -> int:
        return int(self.columns.state[2])

    def _reserve_entries(self, n: int) -> None:
        c = self.columns
        need = int(c.state[1]) + n
        cap = len(c.level)
        if need <= cap:
            return
        while cap < need:
            cap *= 2

        def grown(a, fill):
            out = np.full(cap, fill, a.dtype)
            out[: len(a)] = a
            return out

        self.columns = c._replace(
            level=grown(c.level, 0),
            sub=grown(c.sub, 0),
            label=grown(c.label, 0),
            z=grown(c.z, 0),
            next=grown(c.next, -1),
            alt_label=grown(c.alt_label, 0),
            p_label=grown(c.p_label, P_SCALE),
            p_alt=grown(c.p_alt, 0),
            solid=grown(c.solid, 1),
        )

    def _kernel_state(self) -> tuple[GridGeometry, NodeLayers]:
        """The grid as the kernels see it. Growing the tile pool replaces the layer arrays and
        `tile_coords`, so the tuples are re-made when the pool's capacity has changed."""
        g = self.grid
        if self._kernel_view is None or self._kernel_view[0] != g.capacity:
            geometry = GridGeometry(
                float(g.origin_xy[0]),
                float(g.origin_xy[1]),
                float(g.resolution_m),
                int(g.shape[0]),
                int(g.shape[1]),
                int(g.tile_size),
                g.tile_map,
                g.tile_coords,
            )
            layers = NodeLayers(*(g.flat(name) for name in NodeLayers._fields))
            self._kernel_view = (g.capacity, geometry, layers)
        return self._kernel_view[1], self._kernel_view[2]

    # -- integration ---------------------------------------------------------------------------

    def integrate_delta(self, delta) -> GraphUpdate:
        """Integrate a MapDelta (or anything with the same attributes), read by its
        `values_kind`; a kind this graph cannot read is refused with a ValueError."""
        read = SURFACE_INPUTS.get(delta.values_kind)
        if read is None:
            raise ValueError(
                f"values_kind must be one of {list(SURFACE_INPUTS)}, got {delta.values_kind!r}"
            )
        # a delta without a distribution (version 1) reads as certain
        has = getattr(delta, "has_distribution", False)
        return self.integrate(
            delta.centres,
            delta.labels,
            delta.occupied,
            map_resolution_m=delta.resolution_m,
            confidences=delta.confidences if has else None,
            alt_labels=delta.alt_labels if has else None,
            alt_confidences=delta.alt_confidences if has else None,
            **read(delta, self.config),
        )

    def integrate(
        self,
        centres,
        labels,
        occupied,
        *,
        map_resolution_m: float = 0.1,
        confidences=None,
        alt_labels=None,
        alt_confidences=None,
        solid=None,
    ) -> GraphUpdate:
        """Integrate the voxels of one map update and return the nodes that changed.

        A voxel with `occupied` set is added to (or relabels) its column, one without is removed
        from it. Rows with non-finite centres are dropped and counted. `confidences` is the
        probability of each voxel's label, `alt_labels` / `alt_confidences` its second class;
        left out, the voxels are certain (a version-1 delta: an obstacle class blocks at once);
        given, no label is, not even at probability 1 (Bayesian fusion reaches 1 after two views
        that agree; noise-free labels come at 1 and noisy poses smear them). `solid`: where a
        surface voxel may make a geometric obstacle (left out: everywhere).
        """
        t0 = time.perf_counter()
        if not (np.isfinite(map_resolution_m) and map_resolution_m > 0):
            raise ValueError(f"map_resolution_m must be > 0, got {map_resolution_m}")
        if self.resolution_m / map_resolution_m > 255:
            # Sub-column ids pack (gx, gy) modulo 256 each: a node may span at most 255 voxels.
            raise ValueError("graph resolution spans more than 255 map voxels per axis")
        centres = np.asarray(centres)
        if centres.ndim != 2 or centres.shape[1] != 3 or centres.dtype.kind != "f":
            raise ValueError(f"centres must be a float (M, 3) array, got {centres.shape}")
        m = len(centres)
        labels = np.asarray(labels)
        occupied = np.asarray(occupied)
        if labels.shape != (m,) or labels.dtype.kind not in "iu":
            raise ValueError(f"labels must be an integer array of length {m}")
        if occupied.shape != (m,):
            raise ValueError(f"occupied must have length {m}")
        for name, a in (
            ("confidences", confidences),
            ("alt_labels", alt_labels),
            ("alt_confidences", alt_confidences),
            ("solid", solid),
        ):
            if a is not None and np.shape(a) != (m,):
                raise ValueError(f"{name} must have length {m}")
        if (alt_labels is None) != (alt_confidences is None):
            raise ValueError("alt_labels and alt_confidences go together")
        if alt_labels is not None and np.asarray(alt_labels).dtype.kind not in "iu":
            raise ValueError("alt_labels must be integers")

        if labels.dtype != np.uint16:
            if labels.dtype.kind == "i" and m and labels.min() < 0:
                raise ValueError("labels must be >= 0")
            labels = labels.astype(np.int64)
        if occupied.dtype != np.uint8:
            occupied = (occupied != 0).view(np.uint8)

        g = self.grid
        # 1. classify voxels (surface / cleared / unusable row), clean labels, and allocate the
        # tiles of every in-bounds surface voxel, all in one pass.
        vox = Voxels(
            centres,
            np.empty(m, np.uint16),
            np.empty(m, np.uint8),
            float(map_resolution_m),
            np.empty(m, np.uint16),
            np.empty(m, np.uint8),
            np.empty(m, np.uint8),
            np.ones(m, np.uint8) if solid is None else (np.asarray(solid) != 0).view(np.uint8),
        )
        dist = Distribution(
            _NO_F4 if confidences is None else _readonly(confidences, np.float32),
            _NO_U2 if alt_labels is None else _readonly(alt_labels, np.uint16),
            _NO_F4 if alt_confidences is None else _readonly(alt_confidences, np.float32),
        )
        missing = np.empty(m, np.int64)
        n_missing, n_nonfinite, n_unknown, n_surface = prepare_voxels(
            labels, occupied, self._luts, self._kernel_state()[0], vox, missing, dist
        )
        missing = missing[:n_missing]
        n_new = g.allocate_tiles(missing // g.tiles_shape[1], missing % g.tiles_shape[1])
        self._reserve_entries(int(n_surface))

        # 2. columns and node heads.
        self._epoch += 1
        if self._epoch >= np.iinfo(np.uint32).max:  # wrap: clear stamps so none looks current
            g.flat("epoch")[:] = 0
            self._epoch = 1
        epoch = np.uint32(self._epoch)
        changes = NodeChanges.empty(m)
        flips = Flips(np.empty(m, np.int64), np.empty(m, np.int32))
        geometry, layers = self._kernel_state()  # after allocating: the pool may have grown
        # a label is certain only when the map sends no distribution (see NodeRule.certain)
        rule = self._rule._replace(certain=confidences is None)
        counts = integrate_kernel(vox, geometry, layers, self.columns, rule, epoch, changes, flips)
        n_touched, n_flips, n_oob, n_below, n_lost = (int(c) for c in counts)
        changes = changes.head(n_touched)
        flips = flips.head(n_flips)

        # 3. safety zone: allocate the tiles a new centre's disc reaches, then update counts.
        if n_flips:
            n_new += self._allocate_discs(flips.node[flips.sign > 0])
            zone_changes = NodeChanges.empty(n_flips * len(self._stencil.dx))
            geometry, layers = self._kernel_state()
            n_zone = safety_zone_kernel(flips, self._stencil, geometry, layers, epoch, zone_changes)
            changes = NodeChanges(
                *(np.concatenate([a, b]) for a, b in zip(changes, zone_changes.head(n_zone)))
            )

        # 4. the nodes that actually differ now.
        touched = changes.node
        n_lab = g.flat("labels")[touched]
        n_h = g.flat("heights")[touched]
        n_f = g.flat("flags")[touched]
        n_risk = [g.flat(name)[touched] for name in RISK_LAYER_NAMES]
        changed = ~same_nodes(n_lab, n_h, n_f, changes.label, changes.height, changes.flags)
        for now, before in zip(n_risk, (changes.alt_label, changes.p_label, changes.p_alt)):
            changed |= now != before
        sel = touched[changed]
        ix, iy = g.cells_of_flat(sel)
        cells = np.stack([ix, iy], axis=1).astype(np.int32)
        if len(sel):
            g.changed(cells)
        self.n_integrations += 1
        return GraphUpdate(
            cells=cells,
            labels=n_lab[changed],
            heights=n_h[changed],
            flags=n_f[changed],
            alt_labels=n_risk[0][changed],
            p_label=n_risk[1][changed],
            p_alt=n_risk[2][changed],
            n_voxels=m,
            n_surface=int(n_surface),
            n_out_of_bounds=n_oob,
            n_nonfinite=int(n_nonfinite),
            n_unknown_labels=int(n_unknown),
            n_below_floor=n_below,
            n_columns_lost=n_lost,
            n_new_tiles=n_new,
            time_ms=(time.perf_counter() - t0) * 1e3,
        )

    def _allocate_discs(self, new_centres: np.ndarray) -> int:
        """Allocate every tile the safety-zone disc of a new zone centre reaches."""
        if not len(new_centres):
            return 0
        g = self.grid
        nx, ny = g.shape
        t = g.tile_size
        ix, iy = g.cells_of_flat(new_centres)
        r = self._stencil_reach
        if 2 * r >= t:
            txs, tys = _tile_ranges(ix, iy, r, t, nx, ny)
        else:
            # While the disc spans at most two tiles per axis its four corners name them all.
            txs, tys = [], []
            for ddx in (-r, r):
                for ddy in (-r, r):
                    txs.append(np.clip(ix + ddx, 0, nx - 1) // t)
                    tys.append(np.clip(iy + ddy, 0, ny - 1) // t)
            txs, tys = np.concatenate(txs), np.concatenate(tys)
        return g.allocate_tiles(txs, tys)

    # -- reading -------------------------------------------------------------------------------

    def node(self, x: float, y: float) -> dict | None:
        """One node's state at world (x, y), or None outside the bounds."""
        ix, iy, ok = self.grid.world_to_cell(np.array([x, y], np.float64))
        if not ok:
            return None
        lab, h, f = self.grid.read_cells(np.array([[ix, iy]]))
        flat = self.grid.flat_index(np.array([ix]), np.array([iy]))[0]
        column = self.column(int(ix), int(iy)) if flat >= 0 else []
        cls = self.classes.classes.get(int(lab[0]))
        return {
            "cell": [int(ix), int(iy)],
            "centre": self.grid.cell_centre(ix, iy).tolist(),
            "label": int(lab[0]),
            "class": cls.name if cls else "?",
            "height": float(h[0]),
            "known": bool(f[0] & FLAG_KNOWN),
            "obstacle": bool(f[0] & FLAG_OBSTACLE),
            "safety_zone": bool(f[0] & FLAG_SAFETY_ZONE),
            "doubtful": bool(f[0] & FLAG_DOUBTFUL),
            "obstacle_evidence": int(self.grid.flat("obstacle_evidence")[flat]) if flat >= 0 else 0,
            **dict(zip(RISK_LAYER_NAMES, (int(a[0]) for a in self.grid.read_risk([[ix, iy]])))),
            "allocated": bool(flat >= 0),
            "column_voxels": len(column),
        }

    def column(self, ix: int, iy: int) -> list[tuple[int, int, int, float]]:
        """The tracked voxels of a node, highest first: (level, sub-column, label, height)."""
        flat = int(self.grid.flat_index(np.array([ix]), np.array([iy]))[0])
        if flat < 0:
            return []
        c = self.columns
        out = []
        e = int(self.grid.flat("col_head")[flat])
        while e >= 0:
            out.append((int(c.level[e]), int(c.sub[e]), int(c.label[e]), float(c.z[e])))
            e = int(c.next[e])
        return out

    def export(self, box_xy: tuple[float, float, float, float] | None = None, known_only=True):
        """cells, labels, heights, flags of the graph, or of a world box (x0, y0, x1, y1)."""
        box = None
        if box_xy is not None:
            x0, y0, x1, y1 = (float(v) for v in box_xy)
            if not all(np.isfinite([x0, y0, x1, y1])) or x1 < x0 or y1 < y0:
                raise ValueError(f"box must be finite x0, y0, x1, y1 with x0<=x1, y0<=y1: {box_xy}")
            res, o = self.resolution_m, self.grid.origin_xy
            # in cells, clipped to the grid: a finite box far outside (1e308 m) overflows an int
            with np.errstate(over="ignore"):
                lo = np.floor((np.array([x0, y0]) - o) / res)
                hi = np.floor((np.array([x1, y1]) - o) / res) + 1
            size = np.array(self.grid.shape, np.float64)
            lo, hi = np.clip(lo, 0, size), np.clip(hi, 0, size)
            box = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
        return self.grid.export(box, known_only)

    def stats(self) -> dict:
        g = self.grid
        return {
            "tiles": g.n_tiles,
            "nodes_allocated": g.n_nodes_allocated,
            "nodes_known": g.n_known(),
            "column_voxels": self.n_column_voxels,
            "bytes": self.nbytes,
            "integrations": self.n_integrations,
        }


def _readonly(a, dtype) -> np.ndarray:
    """A contiguous read-only array of `dtype` (no copy when it is one already): one kernel type."""
    a = np.asarray(a)
    if a.dtype != dtype or not a.flags.c_contiguous:
        a = np.ascontiguousarray(a, dtype)
    if a.flags.writeable:
        a = a.view()
        a.flags.writeable = False
    return a


def warm_up(classes: ClassTable) -> float:
    """Compile (or load from numba's cache) the kernels for the array types a decoded MapDelta
    has (read-only views), so the first real delta is not slow. Returns the seconds it took."""
    t0 = time.perf_counter()
    config = NavgraphConfig(
        bounds_min_xy=[0.0, 0.0], bounds_max_xy=[2.0, 2.0], robot_radius_m=0.2, tile_size=4
    )
    g = NavGraph(classes, config)

    def ro(a):
        a.flags.writeable = False
        return a

    ok = classes.obstacle_lut.nonzero()[0]
    lab = int(ok[0]) if len(ok) else 0
    for occ in (1, 0):
        g.integrate(
            ro(np.array([[0.55, 0.55, 0.05], [0.65, 0.55, 0.15]], np.float32)),
            ro(np.array([lab, 0], np.uint16)),
            ro(np.array([occ, occ], np.uint8)),
            map_resolution_m=0.1,
            confidences=ro(np.array([0.7, 1.0], np.float32)),
            alt_labels=ro(np.array([lab, 0], np.uint16)),
            alt_confidences=ro(np.array([0.2, 0.0], np.float32)),
        )
    return time.perf_counter() - t0


def _tile_ranges(ix, iy, r, t, nx, ny):
    """Every tile a square of half-width r around each cell touches (for radii >= a tile)."""
    txs, tys = [], []
    for x, y in zip(ix.tolist(), iy.tolist(), strict=True):
        tx0, tx1 = max(0, x - r) // t, min(nx - 1, x + r) // t
        ty0, ty1 = max(0, y - r) // t, min(ny - 1, y + r) // t
        gx, gy = np.meshgrid(np.arange(tx0, tx1 + 1), np.arange(ty0, ty1 + 1), indexing="ij")
        txs.append(gx.ravel())
        tys.append(gy.ravel())
    return np.concatenate(txs), np.concatenate(tys)
