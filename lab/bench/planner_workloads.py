"""The workloads of `smana bench planner` (planner.py runs and times them): cluttered and flat
graphs, the risk layers a label distribution gives them, the doubt of a map's labels along a
drive, and far-apart pairs of free nodes to plan between.

Risk rows (`--risk`, column "risk": the mode and the doubt share): the cluttered graph again with
a class distribution on a share of its free nodes drawn at random (`--doubt`, default 0.5; the
graph's risk layers: a doubtful label, a second class, some unnamed mass), planned under each
`planner.risk` mode on a new Planner, built in the timed call (window, risk
enter costs, A*) and built just before (it prepares the window and the risk enter costs ahead:
the A* alone), and once with the layers there but every node certain ("certain": the costs of the
graph without them); their Dijkstra runs on the enter costs that mode gave (the kernels themselves
are held to a per-node reference by tests/test_planner_risk.py). Rows without risk ("-") are on
the graph without the layers, as before.

`--map-doubt SEED ...` measures instead what share of a real map's free nodes is doubtful: the
wet garden (10 m, water 10 %, class table garden3drms_wet) seen along the noise experiment's fixed
trajectory (44 m, 640 px; `--quick`: 6 m, 160 px), label noise p = 0.7 (SLIC + Table 2 with water,
as the simulator degrades the wet garden) and the highest pose noise, integrated in-process into
the TSDF back-end and the navigation graph (their default sections): per seed, the share of known
free graph nodes whose p_label < 255 and the spread of their p_label."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

from smana.common.classes import ClassTable
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid

RES = 0.2
ROBOT_RADIUS = 0.4
GRASS, TERRAIN = 1, 2
OBSTACLES = (4, 5, 6, 8)  # hedge, topiary, rose, tree


def make_graph(
    n: int, seed: int = 0, classes: ClassTable | None = None, obstacle_share: float = 0.12
):
    """A deterministic cluttered N x N garden: labels, heights, flags (dense arrays)."""
    classes = classes or ClassTable.load("garden3drms")
    rng = np.random.default_rng(seed)
    labels = _grass_patches(rng, n)
    # Obstacles: discs of 0.3 to 1.5 m radius covering about `obstacle_share` of the area
    # (less where they overlap).
    obstacle = np.zeros((n, n), bool)
    yy, xx = np.mgrid[0:n, 0:n]
    n_discs = int(obstacle_share * n * n / (np.pi * (0.8 / RES) ** 2))
    centres = rng.integers(0, n, size=(n_discs, 2))
    radii = rng.uniform(0.3, 1.5, n_discs) / RES
    kinds = rng.choice(OBSTACLES, n_discs)
    for (cx, cy), r, k in zip(centres, radii, kinds, strict=True):
        ri = int(np.ceil(r))
        x0, x1, y0, y1 = max(0, cx - ri), min(n, cx + ri + 1), max(0, cy - ri), min(n, cy + ri + 1)
        disc = (xx[x0:x1, y0:y1] - cx) ** 2 + (yy[x0:x1, y0:y1] - cy) ** 2 <= r * r
        labels[x0:x1, y0:y1][disc] = k
        obstacle[x0:x1, y0:y1] |= disc
    # Hills: a few metres high over tens of metres, steep flanks in places.
    hills = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=40, mode="wrap")
    heights = (hills / np.abs(hills).max() * 0.03 * n).astype(np.float32)
    dist = ndimage.distance_transform_edt(~obstacle) * RES
    safety = (dist <= ROBOT_RADIUS + 1e-9) & ~obstacle
    flags = (FLAG_KNOWN | obstacle * FLAG_OBSTACLE | safety * FLAG_SAFETY_ZONE).astype(np.uint8)
    assert not (classes.obstacle_lut[labels] != obstacle).any()
    return labels, heights, flags


def _grass_patches(rng, n: int) -> np.ndarray:
    """Grass where smooth noise is high: patches of a few metres, about 40 % of the ground."""
    noise = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma=12, mode="wrap")
    return np.where(noise > np.quantile(noise, 0.6), GRASS, TERRAIN).astype(np.uint16)


def make_flat_graph(n: int, seed: int = 0):
    """The cluttered graph's grass patches on flat, open ground: labels, heights, flags."""
    labels = _grass_patches(np.random.default_rng(seed), n)
    return labels, np.zeros((n, n), np.float32), np.full((n, n), FLAG_KNOWN, np.uint8)


def grid_from_dense(labels, heights, flags, risk=None) -> NavGrid:
    n = labels.shape[0]
    grid = NavGrid((0.0, 0.0), labels.shape, RES, tile_size=32)
    cells = np.argwhere(np.ones((n, n), bool))
    risk = None if risk is None else [r.ravel() for r in risk]
    grid.apply_patch(cells, labels.ravel(), heights.ravel(), flags.ravel(), risk=risk)
    return grid


def make_risk(labels, flags, seed: int, doubt_share: float = 0.5):
    """Risk layers (alt_labels, p_label, p_alt) for a graph: on `doubt_share` of the free nodes,
    drawn at random, a doubtful label (P 0.7 to 1), a second class (the other ground class, or on
    15 % a tree: forbidden) holding most of the rest, the remainder unnamed."""
    rng = np.random.default_rng(seed)
    shape = labels.shape
    doubt = (rng.random(shape) < doubt_share) & ((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0)
    p_label = np.where(doubt, rng.integers(180, 256, shape), 255).astype(np.uint8)
    other = np.where(labels == GRASS, TERRAIN, GRASS)
    alt = np.where(rng.random(shape) < 0.15, 8, other)  # 8: tree, infinite cost
    alt = np.where(doubt, alt, 0).astype(np.uint16)
    rest = 255 - p_label.astype(np.int64)
    p_alt = np.where(doubt, rest * rng.uniform(0.7, 1.0, shape), 0).astype(np.uint8)
    return alt, p_label, p_alt


def map_doubt(seed: int, length_m: float = 44.0, image_px: int = 640) -> dict:
    """The doubtful share of a real map's known free nodes (see the module's docstring): the
    frames integrated, the known free nodes, and the p_label of the doubtful ones."""
    import types

    from smana.common.config import SmanaConfig
    from smana.lab.experiments.noise import POSE_NOISE, fixed_trajectory, frame_cloud, render_frames
    from smana.services.mapper.semantic_map import SemanticMap
    from smana.services.navgraph.graph import NavGraph
    from smana.services.sim.degrade import WET_CONFUSABLE, WET_IDS, LabelDegrader, PoseNoise
    from smana.services.sim.worlds.garden import generate

    table = "garden3drms_wet"
    config = SmanaConfig.load(overrides=[f'general.class_table="{table}"', 'mapper.backend="tsdf"'])
    classes = ClassTable.load(table)
    world = generate(seed, classes=classes, size_m=10.0, water_share=0.1)
    frames = render_frames(world, fixed_trajectory(world, length_m, 0.25), image_px)
    rng = np.random.default_rng(seed)
    degrade = LabelDegrader("high", rng, classes.colour_lut, ids=WET_IDS, confusable=WET_CONFUSABLE)
    pose_noise = PoseNoise(*POSE_NOISE["high"], rng)
    semantic_map = SemanticMap.from_config(config.mapper, table)
    graph = NavGraph(classes, config.navgraph)
    for base, capture, mount in frames:
        labels = degrade.degrade(capture.labels).labels
        pts, lab, origin = frame_cloud((base, capture, mount), labels, pose_noise.apply(base), 2)
        d = semantic_map.integrate(pts, lab, degrade.confidences(len(pts)), origin)
        # what the mapper publishes (services/mapper/service.py, `_message`)
        graph.integrate_delta(
            types.SimpleNamespace(
                centres=d.centres,
                labels=d.labels,
                confidences=d.confidences,
                occupied=d.occupied,
                values=d.values,
                values_kind=semantic_map.values_kind,
                alt_labels=d.alt_labels,
                alt_confidences=d.alt_confidences,
                has_distribution=True,
                resolution_m=semantic_map.resolution_m,
            )
        )
    grid = graph.grid
    x0, y0, x1, y1 = grid.known_box()
    _, _, flags = grid.box(x0, y0, x1, y1)
    cells = np.argwhere(np.ones((x1 - x0, y1 - y0), bool)) + (x0, y0)
    p_label = grid.read_risk(cells)[1].reshape(flags.shape)
    free = ((flags & FLAG_KNOWN) != 0) & ((flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0)
    doubtful = free & (p_label < 255)
    return {"frames": len(frames), "free": int(free.sum()), "p_label": p_label[doubtful]}


def print_map_doubt(seeds, quick: bool) -> None:
    length_m, image_px = (6.0, 160) if quick else (44.0, 640)
    print(
        f"doubtful share of a real map's known free nodes: wet garden 10 m, TSDF, label noise "
        f"p = 0.7 and pose noise, {length_m:g} m of trajectory, {image_px} px"
    )
    for seed in seeds:
        r = map_doubt(seed, length_m, image_px)
        p = r["p_label"]
        share = len(p) / max(1, r["free"])
        spread = ""
        if len(p):
            q = np.percentile(p, [0, 25, 50, 75, 100]) / 255
            spread = ", their P(label) min / quartiles / max " + " / ".join(f"{v:.2f}" for v in q)
        print(
            f"  seed {seed}: {r['frames']} frames, {r['free']} known free nodes, {len(p)} "
            f"doubtful: share {share:.3f}{spread}"
        )


def anchor_points(n: int, length: float = 1.0):
    """Query ends near opposite corners, then opposite sides; with `length` < 1 both ends are
    drawn towards the centre, so that the query spans that share of the graph."""
    m = n // 50 + 1
    c = (n - 1) / 2
    pairs = [
        ((m, m), (n - 1 - m, n - 1 - m)),
        ((n - 1 - m, m), (m, n - 1 - m)),
        ((m, n // 2), (n - 1 - m, n // 2)),
        ((n // 2, m), (n // 2, n - 1 - m)),
    ]
    return [
        tuple(tuple(int(round(c + (v - c) * length)) for v in end) for end in pair)
        for pair in pairs
    ]


def far_free_pairs(flags, graph_csr, n_queries: int, length: float = 1.0):
    """Start/goal pairs near opposite corners and sides (`anchor_points`), free and connected."""
    n = flags.shape[0]
    free = (flags & (FLAG_OBSTACLE | FLAG_SAFETY_ZONE)) == 0
    anchors = anchor_points(n, length)
    # The largest connected component of the graph, so that every query has an answer.
    _, comp = csgraph.connected_components(graph_csr, directed=True, connection="strong")
    big = np.bincount(comp).argmax()
    ok = free.ravel() & (comp == big)
    idx = np.flatnonzero(ok)
    px, py = idx // n, idx % n
    pairs = []
    for a, b in anchors[:n_queries]:
        ends = []
        for x, y in (a, b):
            j = np.argmin((px - x) ** 2 + (py - y) ** 2)
            ends.append((int(px[j]), int(py[j])))
        pairs.append(tuple(ends))
    return pairs
