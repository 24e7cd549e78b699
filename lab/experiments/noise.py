"""`smana experiment noise` (paper Figures 6 and 7): map precision under localisation and label
noise, in-process on the simulator's and the mapper's cores (no Zenoh).

The camera follows one fixed trajectory through the garden; its frames are rendered once
(PyBullet TinyRenderer, the simulator's camera), then degraded and integrated into every back-end
(octree-max, octree-bayes, tsdf):
- localisation noise levels (Gaussian noise on the x, y and yaw of every frame's pose, label
  noise "none"), scored by reconstruction error (mean and std) and classification ratio;
- label noise levels (SLIC superpixels redrawn from Table 2's confusion matrix,
  p = 1.0 / 0.9 / 0.8 / 0.7, confidences uniform in [0.33, 1]), scored by classification ratio.
Each configuration sees exactly the same frames, noise draws and trajectory.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from smana.common import progress
from smana.lab import evaluation as ev
from smana.lab import plots
from smana.services.mapper.backends import BACKENDS as _REGISTRY

BACKENDS = tuple(_REGISTRY)  # the mapper's registry: every back-end it knows
LEVELS = ("none", "low", "medium", "high")
# Localisation noise per level: standard deviation of x and y (m) and of yaw (rad), drawn afresh
# for every frame. The paper's values are not legible in its Figure 6; these span "a good
# odometry" to "a poor one" at the 5 cm map resolution.
POSE_NOISE = {
    "none": (0.0, 0.0),
    "low": (0.02, 0.005),
    "medium": (0.05, 0.01),
    "high": (0.10, 0.02),
}
PAPER_LABEL_LOSS = {"tsdf": 0.11, "octree-max": 0.30}  # classification loss, lowest -> highest


# -- the fixed trajectory ------------------------------------------------------------------------


def fixed_trajectory(
    world,
    length_m: float = 44.0,
    spacing_m: float = 0.25,
    clearance_m: float = 0.45,
    n_waypoints: int = 8,
) -> np.ndarray:
    """(K, 3) poses (x, y, yaw) every `spacing_m` along a collision-free tour of the garden.

    Waypoints are spread over the free space reachable from the spawn point (farthest-point
    sampling), visited nearest-first along shortest paths on the ground-truth traversability
    raster, smoothed, and cut at `length_m` (the tour repeats if it is shorter)."""
    trav = world.traversability(clearance_m)
    res = trav.resolution_m
    sx, sy, _ = world.spawn_pose(clearance_m)
    si, sj = (int(v) for v in trav.index_of(sx, sy))
    reach = ev.reachable_traversable(trav.data, (si, sj))
    cells = np.argwhere(reach)
    if len(cells) < 2:
        raise ValueError("the world has no free space to drive through")
    idx = -np.ones(reach.shape, np.int64)
    idx[reach] = np.arange(len(cells))
    rows, cols, wts = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = cells
        b = cells + (di, dj)
        ok = (
            (b[:, 0] >= 0)
            & (b[:, 1] >= 0)
            & (b[:, 0] < reach.shape[0])
            & (b[:, 1] < reach.shape[1])
        )
        a, b = a[ok], b[ok]
        ok = reach[b[:, 0], b[:, 1]]
        rows.append(idx[a[ok, 0], a[ok, 1]])
        cols.append(idx[b[ok, 0], b[ok, 1]])
        wts.append(np.full(ok.sum(), math.hypot(di, dj) * res))
    n = len(cells)
    graph = coo_matrix(
        (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    start = int(idx[si, sj])
    # farthest-point sampling of waypoints, by path distance
    dist = dijkstra(graph, directed=False, indices=start)
    way = [start]
    d_min = dist.copy()
    for _ in range(n_waypoints):
        k = int(np.argmax(np.where(np.isfinite(d_min), d_min, -1)))
        way.append(k)
        d_min = np.minimum(d_min, dijkstra(graph, directed=False, indices=k))
    # visit them nearest-first
    order, left = [way[0]], set(way[1:])
    path_cells: list[int] = [way[0]]
    total = 0.0
    while total < length_m * 1.2:
        if not left:
            left = set(way) - {order[-1]}
        d, pred = dijkstra(graph, directed=False, indices=order[-1], return_predecessors=True)
        nxt = min(left, key=lambda k: d[k])
        left.discard(nxt)
        seg = [nxt]
        while seg[-1] != order[-1]:
            seg.append(int(pred[seg[-1]]))
        path_cells += seg[::-1][1:]
        order.append(nxt)
        total += float(d[nxt])
    xs, ys = trav.cell_centres()
    pts = np.column_stack([xs[cells[path_cells, 0]], ys[cells[path_cells, 1]]])
    # smooth the staircase of the raster path, then resample evenly
    pts = ndimage.uniform_filter1d(pts, size=5, axis=0, mode="nearest")
    seg_len = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg_len)])
    stations = np.arange(0.0, min(length_m, s[-1]), spacing_m)
    x = np.interp(stations, s, pts[:, 0])
    y = np.interp(stations, s, pts[:, 1])
    ahead = np.minimum(np.searchsorted(s, stations + 0.5), len(pts) - 1)
    yaw = np.arctan2(pts[ahead, 1] - y, pts[ahead, 0] - x)
    # a millimetre off the ground raster's vertices: TinyRenderer slows down on exact alignments
    return np.column_stack([x + 1e-3, y + 1.3e-3, yaw])


# -- noise experiment ------------------------------------------------------------------------------


@dataclass
class NoiseExperimentConfig:
    """What `smana experiment noise` renders and sweeps: world, trajectory, camera, map."""

    world_seed: int = 3
    size_m: float = 12.0
    length_m: float = 44.0
    spacing_m: float = 0.25
    image_px: int = 640
    pixel_stride: int = 1
    resolution_m: float = 0.05
    gt_spacing_m: float = 0.02
    ray_length_m: float = 1.0
    noise_seed: int = 0
    backends: tuple[str, ...] = BACKENDS
    levels: tuple[str, ...] = LEVELS

    @classmethod
    def quick(cls) -> NoiseExperimentConfig:
        return cls(
            size_m=12.0,
            length_m=6.0,
            spacing_m=0.6,
            image_px=160,
            resolution_m=0.1,
            gt_spacing_m=0.04,
            levels=("none", "high"),
        )


def render_frames(world, poses: np.ndarray, image_px: int, bar=None):
    """Render the camera along the trajectory once: [(world_from_sensor, CameraCapture)].
    `bar` (a `progress.bar`) advances by one per frame."""
    from smana.common.config.sim import CameraConfig, RobotConfig
    from smana.services.sim.camera import SemanticCamera
    from smana.services.sim.scene import BulletScene

    camera = CameraConfig(width=image_px, height=image_px)
    base_h = RobotConfig().base_height_m
    frames = []
    with BulletScene(world) as scene:
        cam = SemanticCamera(scene, camera)
        for x, y, yaw in poses:
            base = np.eye(4)
            c, s = math.cos(yaw), math.sin(yaw)
            base[:2, :2] = [[c, -s], [s, c]]
            base[:3, 3] = [x, y, float(world.ground.height_at(x, y)) + base_h]
            frames.append((base, cam.capture(base @ camera.mount_matrix()), camera.mount_matrix()))
            if bar is not None:
                bar.update()
    return frames


def _cloud(frame, labels_img, base_used, stride):
    """World points of a frame's valid pixels, placed with the (possibly noisy) base pose."""
    from smana.services.sim.scene import transform_points

    _, cap, mount = frame
    valid = (labels_img >= 0) & cap.valid
    if stride > 1:
        keep = np.zeros_like(valid)
        keep[::stride, ::stride] = True
        valid &= keep
    rows, cols = np.nonzero(valid)
    sensor = base_used @ mount
    pts = transform_points(cap.points_sensor(rows, cols), sensor)
    return pts, labels_img[rows, cols].astype(np.uint16), sensor[:3, 3]


def run_noise(settings: NoiseExperimentConfig, out: Path, log=progress.say) -> list[dict]:
    """Both sweeps for every back-end; returns one row per (back-end, sweep, level)."""
    from smana.common.classes import ClassTable
    from smana.services.mapper.semantic_map import SemanticMap
    from smana.services.sim.degrade import NOISE_LEVELS, LabelDegrader, PoseNoise
    from smana.services.sim.worlds.garden import generate

    classes = ClassTable.load("garden3drms")
    names = {i: c.name for i, c in classes.classes.items()}
    world = generate(settings.world_seed, size_m=settings.size_m, classes=classes)
    poses = fixed_trajectory(world, settings.length_m, settings.spacing_m)
    length = float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum())
    t0 = time.perf_counter()
    with progress.bar(len(poses), "noise: rendering", unit="frame") as bar:
        frames = render_frames(world, poses, settings.image_px, bar)
    log(f"rendered {len(frames)} frames along {length:.1f} m in {time.perf_counter() - t0:.1f} s")
    gp, gl = world.gt_cloud(settings.gt_spacing_m)
    tree = cKDTree(np.asarray(gp, np.float64))

    # the inputs of each configuration, shared by every back-end
    def inputs(label_level: str, pose_level: str):
        rng = np.random.default_rng(
            [settings.noise_seed, LEVELS.index(label_level), LEVELS.index(pose_level)]
        )
        deg = LabelDegrader(label_level, rng, classes.colour_lut)
        pn = PoseNoise(*POSE_NOISE[pose_level], rng)
        clouds = []
        for frame in frames:
            base, cap, _ = frame
            lab = deg.degrade(cap.labels).labels
            pts, lab_v, origin = _cloud(frame, lab, pn.apply(base), settings.pixel_stride)
            clouds.append((pts, lab_v, deg.confidences(len(pts)), origin))
        return clouds

    configs = [("label", lv, lv, "none") for lv in settings.levels]
    configs += [("pose", pl, "none", pl) for pl in settings.levels if pl != "none"]
    rows: list[dict] = []
    # one step per map built: every step integrates the same frames, so the ETA holds
    sweep_bar = progress.bar(len(configs) * len(settings.backends), "noise: mapping", unit="map")
    for sweep, level, label_level, pose_level in configs:
        t1 = time.perf_counter()
        clouds = inputs(label_level, pose_level)
        for backend in settings.backends:
            m = SemanticMap(backend, settings.resolution_m, 8.0, settings.ray_length_m, classes)
            t2 = time.perf_counter()
            for pts, lab, conf, origin in clouds:
                m.integrate(pts, lab, conf, origin)
            t_int = time.perf_counter() - t2
            vox = m.occupied_voxels()
            scores = ev.evaluate_map(vox.centres, vox.labels, gp, gl, names, gt_tree=tree)
            row = {
                "backend": backend,
                "sweep": sweep,
                "level": level,
                "label_p": NOISE_LEVELS[label_level],
                "pose_sigma_xy_m": POSE_NOISE[pose_level][0],
                "pose_sigma_yaw_rad": POSE_NOISE[pose_level][1],
                "n_points": scores["n_points"],
                "error_mean_m": scores["reconstruction_error_mean_m"],
                "error_std_m": scores["reconstruction_error_std_m"],
                "classification_ratio": scores["classification_ratio"],
                "integrate_ms_per_frame": 1e3 * t_int / max(1, len(clouds)),
                "per_class_ratio": {
                    k: v["classification_ratio"] for k, v in scores["per_true_class"].items()
                },
            }
            rows.append(row)
            log(
                f"{sweep:5s} {level:6s} {backend:12s} points {row['n_points']:7d} "
                f"error {row['error_mean_m']:.4f} +- {row['error_std_m']:.4f} m "
                f"ratio {row['classification_ratio']:.3f}"
            )
            sweep_bar.update()
        log(f"  ({time.perf_counter() - t1:.1f} s)")
    sweep_bar.close()
    meta = {
        "settings": asdict(settings),
        "trajectory_length_m": length,
        "frames": len(frames),
        "pose_noise": POSE_NOISE,
        "seconds": time.perf_counter() - t0,
    }
    write_noise_outputs(rows, meta, out)
    return rows


def _by(rows, sweep, backend):
    sel = [r for r in rows if r["sweep"] == sweep and r["backend"] == backend]
    if sweep == "pose":  # the pose sweep's "none" is the label sweep's "none"
        sel = [
            r
            for r in rows
            if r["sweep"] == "label" and r["backend"] == backend and r["level"] == "none"
        ] + sel
    return sorted(sel, key=lambda r: LEVELS.index(r["level"]))


def label_losses(rows) -> dict[str, dict]:
    """Classification ratio lost from the lowest to the highest label noise level, per back-end:
    in points of ratio (absolute) and relative to the lowest level."""
    out = {}
    for b in sorted({r["backend"] for r in rows}):
        sel = _by(rows, "label", b)
        if len(sel) >= 2:
            lo, hi = sel[0]["classification_ratio"], sel[-1]["classification_ratio"]
            out[b] = {
                "from": sel[0]["level"],
                "to": sel[-1]["level"],
                "ratio_lowest": lo,
                "ratio_highest": hi,
                "loss_abs": lo - hi,
                "loss_rel": (lo - hi) / lo if lo else None,
                "paper_loss": PAPER_LABEL_LOSS.get(b),
            }
    return out


def write_noise_outputs(rows: list[dict], meta: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    flat = [{k: v for k, v in r.items() if k != "per_class_ratio"} for r in rows]
    with open(out / "noise_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(flat[0]))
        w.writeheader()
        w.writerows(flat)
    losses = label_losses(rows)
    (out / "noise_results.json").write_text(
        json.dumps({"meta": meta, "rows": rows, "label_loss": losses}, indent=2)
    )
    backends = sorted({r["backend"] for r in rows}, key=BACKENDS.index)
    ticks = {i: lv for i, lv in enumerate(LEVELS)}

    def series(sweep, key, err=None):
        out_s = []
        for b in backends:
            sel = _by(rows, sweep, b)
            out_s.append(
                plots.Series(
                    b,
                    [LEVELS.index(r["level"]) for r in sel],
                    [r[key] for r in sel],
                    [r[err] for r in sel] if err else None,
                )
            )
        return out_s

    used = {i: t for i, t in ticks.items() if any(LEVELS.index(r["level"]) == i for r in rows)}
    # one fixed trajectory and one world: each point is one map (n = 1), so a ratio has no spread;
    # the error's bars are its spread over the map's points, not over runs
    one_run = "n = 1 run per level and back-end"
    plots.save(
        plots.line_plot(
            series("pose", "error_mean_m", "error_std_m"),
            "Reconstruction error vs localisation noise (Fig. 6)",
            "localisation noise level",
            "reconstruction error (m)",
            used,
            note=f"mean, bars: std over map points\n{one_run}",
        ),
        out / "fig6_pose_noise_error.png",
    )
    plots.save(
        plots.line_plot(
            series("pose", "classification_ratio"),
            "Classification ratio vs localisation noise (Fig. 6)",
            "localisation noise level",
            "classification ratio (share of map points labelled right)",
            used,
            note=one_run,
        ),
        out / "fig6_pose_noise_ratio.png",
    )
    plots.save(
        plots.line_plot(
            series("label", "classification_ratio"),
            "Classification ratio vs label noise (Fig. 7)",
            "label noise level (p = 1, .9, .8, .7)",
            "classification ratio (share of map points labelled right)",
            used,
            note=one_run,
        ),
        out / "fig7_label_noise_ratio.png",
    )
    lines = [
        "# Noise experiment (paper Figures 6 and 7)",
        "",
        f"Fixed trajectory of {meta['trajectory_length_m']:.1f} m, {meta['frames']} frames of "
        f"{meta['settings']['image_px']} px, map resolution {meta['settings']['resolution_m']} m, "
        f"world seed {meta['settings']['world_seed']}; {meta['seconds']:.0f} s in all.",
        "Localisation noise levels (sigma x/y m, sigma yaw rad): "
        + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in POSE_NOISE.items())
        + ".",
        "",
        "| sweep | level | back-end | map points | error mean (m) | error std (m) | "
        "classification ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['sweep']} | {r['level']} | {r['backend']} | {r['n_points']} | "
            f"{r['error_mean_m']:.4f} | {r['error_std_m']:.4f} | "
            f"{r['classification_ratio']:.3f} |"
        )
    lines += [
        "",
        "## Classification loss from the lowest to the highest label noise",
        "",
        "| back-end | ratio at lowest | ratio at highest | loss (points) | loss (relative) "
        "| paper |",
        "|---|---|---|---|---|---|",
    ]
    for b, d in losses.items():
        paper = f"{100 * d['paper_loss']:.0f} %" if d["paper_loss"] is not None else "-"
        lines.append(
            f"| {b} | {d['ratio_lowest']:.3f} | {d['ratio_highest']:.3f} | "
            f"{100 * d['loss_abs']:.1f} | {100 * (d['loss_rel'] or 0):.1f} % | {paper} |"
        )
    if "tsdf" in losses and "octree-max" in losses:
        more = losses["tsdf"]["loss_abs"] < losses["octree-max"]["loss_abs"]
        lines += [
            "",
            f"Direction of the paper's effect (TSDF loses less than octree-max to label "
            f"noise): {'reproduced' if more else 'NOT reproduced'}.",
        ]
    pose_growth = {}
    for b in backends:
        sel = _by(rows, "pose", b)
        if len(sel) >= 2:
            pose_growth[b] = sel[-1]["error_mean_m"] - sel[0]["error_mean_m"]
    if pose_growth:
        lines += [
            "",
            "Reconstruction error added from the lowest to the highest localisation "
            "noise: " + ", ".join(f"{b} +{1000 * g:.1f} mm" for b, g in pose_growth.items()) + ".",
        ]
        if "tsdf" in pose_growth and "octree-max" in pose_growth:
            ok = pose_growth["tsdf"] < pose_growth["octree-max"]
            lines.append(
                "Direction of the paper's effect (TSDF more robust to localisation "
                f"noise): {'reproduced' if ok else 'NOT reproduced'}."
            )
    lines += [
        "",
        "![fig6 error](fig6_pose_noise_error.png)",
        "![fig6 ratio](fig6_pose_noise_ratio.png)",
        "![fig7](fig7_label_noise_ratio.png)",
        "",
    ]
    (out / "noise_summary.md").write_text("\n".join(lines))


# -- command line --------------------------------------------------------------------------------


def add_parser(sub) -> None:
    """The `noise` subcommand of `smana experiment`."""
    n = sub.add_parser(
        "noise",
        help="map precision under localisation and label noise (about 40 min; --quick 30 s)",
        description="Paper Fig. 6 and 7: every back-end along a fixed 44 m trajectory, under 4 "
        "localisation and 4 label noise levels.",
        epilog="Duration on a 2-core machine: about 40 minutes (176 frames of 640 px, 5 cm "
        "voxels, 3 back-ends x 7 noise settings); --quick about 30 s. A progress bar with an "
        "ETA shows on a terminal (SMANA_PROGRESS=1 forces it, 0 hides it).",
    )
    n.add_argument(
        "--quick",
        action="store_true",
        help="2 noise levels, a 6 m trajectory, 160 px, 10 cm voxels (about 30 s)",
    )
    n.add_argument("--out", type=Path)
    n.add_argument("--backends", help="comma-separated subset of " + ",".join(BACKENDS))
    n.add_argument("--seed", type=int, help="world seed")


def main(args, parser, out: Path) -> int:
    s = NoiseExperimentConfig.quick() if args.quick else NoiseExperimentConfig()
    if args.backends:
        s.backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
        bad = [b for b in s.backends if b not in BACKENDS]
        if bad:
            parser.error(f"unknown back-end(s) {bad}")
    if args.seed is not None:
        s.world_seed = args.seed
    run_noise(s, out)
    print(f"results in {out} (noise_summary.md)")
    return 0
