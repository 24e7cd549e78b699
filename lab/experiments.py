"""The paper's experiments (sections 4.2.2 and 4.3), reproduced in smana's simulated garden.

    smana experiment noise [--quick] [--out DIR]
    smana experiment exploration [--quick] [--seeds 3] [--out DIR]

**noise** (paper Figures 6 and 7): the camera follows one fixed trajectory of about 44 m through
the garden; its frames are rendered once (PyBullet TinyRenderer, the simulator's camera), then
degraded and integrated into every back-end (octree-max, octree-bayes, tsdf) at 5 cm:
- four localisation noise levels (Gaussian noise on the x, y and yaw of every frame's pose, label
  noise "none"), scored by reconstruction error (mean and std) and classification ratio;
- four label noise levels (SLIC superpixels redrawn from Table 2's confusion matrix,
  p = 1.0 / 0.9 / 0.8 / 0.7, confidences uniform in [0.33, 1]), scored by classification ratio.
It runs in-process on the simulator's and the mapper's cores (no Zenoh), so each configuration
sees exactly the same frames, noise draws and trajectory.

**exploration** (paper 4.3): the whole stack (`smana up`) explores the garden with the grass
traversability cost at x1 (costs ignored: grass costs what terrain costs), x2 (the class table)
and x4, over several world seeds; the share of travelled graph nodes on terrain (vs grass),
explored area and distance are read from each run's metrics.json.

Both write raw results (CSV and JSON), PNG plots and a markdown summary into `--out`.
`--quick` runs a small version (fewer frames, smaller images, 10 cm voxels; a small world and a
short budget) that the test suite runs.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from smana.common import progress
from smana.common.zenoh_config import free_loopback_port
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
PAPER_TERRAIN_SHARE = {1.0: 0.60, 2.0: 0.70, 4.0: 0.88}  # grass cost factor -> terrain share


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


# -- exploration experiment ----------------------------------------------------------------------


@dataclass
class ExplorationExperimentConfig:
    """What `smana experiment exploration` runs: one `smana up` per seed and grass cost factor."""

    seeds: tuple[int, ...] = (3, 4, 5)
    cost_factors: tuple[float, ...] = (1.0, 2.0, 4.0)
    size_m: float = 12.0
    budget_s: float = 480.0
    extra: tuple[str, ...] = ()  # more --set overrides for every run

    @classmethod
    def quick(cls) -> ExplorationExperimentConfig:
        # a 6 m garden, a small camera and a 10 cm map: two short closed loops for the test suite
        small = (
            "sim.camera.width=160",
            "sim.camera.height=160",
            "mapper.resolution_m=0.1",
            "navgraph.bounds_min_xy=[-4.0, -4.0]",
            "navgraph.bounds_max_xy=[4.0, 4.0]",
            # no hot spares: a 20 s run would start five only to stop them
            "deploy.standby_delay_s=3600",
        )
        return cls(seeds=(3,), cost_factors=(1.0, 4.0), size_m=6.0, budget_s=20.0, extra=small)


def exploration_run(
    out: Path, seed: int, factor: float, s: ExplorationExperimentConfig, log=progress.say
):
    """One `smana up` run with grass at `factor` times terrain's cost; returns its metrics."""
    from smana.common.classes import ClassTable

    table = ClassTable.load("garden3drms")
    terrain = table.by_name("terrain").cost
    # absolute: the supervisor starts each service inside the run directory
    run_dir = (out / f"seed{seed}_grass_x{factor:g}").resolve()
    # a robot name of its own: stray processes of another stack that reach this router (a reused
    # port) then talk on other keys
    robot = f"exp{os.getpid()}-s{seed}-x{factor:g}".replace(".", "_")
    sets = [
        f'general.robot="{robot}"',
        f"sim.seed={seed}",
        f"sim.garden.size_m={s.size_m}",
        f"explorer.time_budget_s={s.budget_s}",
        f'explorer.class_costs=["grass={factor * terrain}"]',
        *s.extra,
    ]
    port = free_loopback_port()
    argv = [
        sys.executable,
        "-m",
        "smana.deploy.cli",
        "up",
        "--run-dir",
        str(run_dir),
        "--set",
        f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
    ]
    for item in sets:
        argv += ["--set", item]
    t0 = time.perf_counter()
    run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "up.log", "w") as f:
        code = subprocess.call(
            argv, stdout=f, stderr=subprocess.STDOUT, timeout=s.budget_s * 3 + 180
        )
    metrics = None
    if (run_dir / "metrics.json").is_file():
        metrics = json.loads((run_dir / "metrics.json").read_text())
    log(f"seed {seed} grass x{factor:g}: exit {code}, {time.perf_counter() - t0:.0f} s")
    return code, metrics or {}


def run_exploration(s: ExplorationExperimentConfig, out: Path, log=progress.say) -> list[dict]:
    rows = []
    # one step per `smana up`: each runs to its time budget or to the end of the frontiers
    runs = progress.bar(len(s.seeds) * len(s.cost_factors), "exploration", unit="run")
    for seed in s.seeds:
        for factor in s.cost_factors:
            runs.set_postfix_str(f"seed {seed} grass x{factor:g}")
            code, m = exploration_run(out, seed, factor, s, log)
            runs.update()
            ex = m.get("exploration") or {}
            ee = m.get("explorer") or {}
            rows.append(
                {
                    "seed": seed,
                    "grass_cost_factor": factor,
                    "exit_code": code,
                    "terrain_share": ex.get("terrain_share"),
                    "coverage": ex.get("coverage"),
                    "explored_area_m2": ex.get("explored_reachable_area_m2"),
                    "distance_m": ex.get("distance_m"),
                    "min_clearance_m": ex.get("min_clearance_m"),
                    "done_reason": ee.get("done_reason"),
                    "wall_time_s": ee.get("wall_time_s"),
                }
            )
            log(f"  terrain share {rows[-1]['terrain_share']}, coverage {rows[-1]['coverage']}")
    runs.close()
    write_exploration_outputs(rows, s, out)
    return rows


def summarise_exploration(rows: list[dict]) -> list[dict]:
    out = []
    for f in sorted({r["grass_cost_factor"] for r in rows}):
        sel = [r for r in rows if r["grass_cost_factor"] == f]

        def stat(key, sel=sel):
            v = np.array([r[key] for r in sel if r[key] is not None], float)
            return (float(v.mean()), float(v.std())) if len(v) else (None, None)

        ts, cov, dist = stat("terrain_share"), stat("coverage"), stat("distance_m")
        out.append(
            {
                "grass_cost_factor": f,
                "runs": len(sel),
                "terrain_share_mean": ts[0],
                "terrain_share_std": ts[1],
                "coverage_mean": cov[0],
                "coverage_std": cov[1],
                "distance_mean_m": dist[0],
                "distance_std_m": dist[1],
                "paper_terrain_share": PAPER_TERRAIN_SHARE.get(f),
            }
        )
    return out


def write_exploration_outputs(rows: list[dict], s: ExplorationExperimentConfig, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "exploration_results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = summarise_exploration(rows)
    (out / "exploration_results.json").write_text(
        json.dumps({"settings": asdict(s), "runs": rows, "summary": summary}, indent=2)
    )
    xs = [d["grass_cost_factor"] for d in summary]
    ok = [d for d in summary if d["terrain_share_mean"] is not None]
    shares = {
        d["grass_cost_factor"]: [
            r["terrain_share"]
            for r in rows
            if r["grass_cost_factor"] == d["grass_cost_factor"] and r["terrain_share"] is not None
        ]
        for d in ok
    }
    ns = sorted({len(v) for v in shares.values()})
    n_text = f"n = {ns[0]}" if len(ns) == 1 else f"n = {ns[0]}-{ns[-1]}"
    n_text += " seed" if ns == [1] else " seeds"
    mean = [d["terrain_share_mean"] for d in ok]
    spread = None  # with one seed there is no spread to draw
    if ns and ns[-1] > 1:
        spread = (
            [m - min(shares[d["grass_cost_factor"]]) for m, d in zip(mean, ok)],
            [max(shares[d["grass_cost_factor"]]) - m for m, d in zip(mean, ok)],
        )
    label = f"smana, mean and min-max ({n_text})" if spread else f"smana ({n_text})"
    series = [plots.Series(label, [d["grass_cost_factor"] for d in ok], mean, spread)]
    paper = [(f, v) for f, v in PAPER_TERRAIN_SHARE.items() if f in xs]
    if paper:
        series.append(
            plots.Series("paper", [f for f, _ in paper], [v for _, v in paper], dashed=True)
        )
    plots.save(
        plots.line_plot(
            series,
            f"Travelled nodes on terrain vs grass cost ({n_text})",
            "grass cost factor (x terrain's cost)",
            "terrain share of travelled nodes",
            {f: f"x{f:g}" for f in xs},
        ),
        out / "exploration_terrain_share.png",
    )
    lines = [
        "# Exploration experiment (paper 4.3)",
        "",
        f"Seeds {list(s.seeds)}, garden {s.size_m} m, budget {s.budget_s:.0f} s per run.",
        "",
        "| grass cost | runs | terrain share | paper | coverage | distance (m) |",
        "|---|---|---|---|---|---|",
    ]

    def pm(m, sd, scale=1.0, fmt=".1f"):
        return "-" if m is None else f"{format(m * scale, fmt)} +- {format(sd * scale, fmt)}"

    for d in summary:
        paper_v = d["paper_terrain_share"]
        lines.append(
            f"| x{d['grass_cost_factor']:g} | {d['runs']} | "
            f"{pm(d['terrain_share_mean'], d['terrain_share_std'], 100)} % | "
            f"{'-' if paper_v is None else f'{100 * paper_v:.0f} %'} | "
            f"{pm(d['coverage_mean'], d['coverage_std'], 100)} % | "
            f"{pm(d['distance_mean_m'], d['distance_std_m'])} |"
        )
    shares = [d["terrain_share_mean"] for d in summary if d["terrain_share_mean"] is not None]
    if len(shares) >= 2:
        rising = all(b >= a for a, b in zip(shares[:-1], shares[1:], strict=True))
        lines += [
            "",
            "Direction of the paper's effect (terrain share rises with the grass cost): "
            + ("reproduced" if rising else "NOT reproduced")
            + ".",
        ]
    lines += ["", "![terrain share](exploration_terrain_share.png)", ""]
    (out / "exploration_summary.md").write_text("\n".join(lines))


# -- command line --------------------------------------------------------------------------------


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, output_dir, positive_float, positive_int
    from smana.common.config import SmanaConfig

    p = ArgumentParser(prog="smana experiment", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="which", required=True)
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
    e = sub.add_parser(
        "exploration",
        help="terrain share vs grass traversability cost (about 30 min; --quick 1.5 min)",
        description="Paper 4.3: one `smana up` per world seed and grass cost factor (x1, x2, "
        "x4); the share of travelled nodes on terrain.",
        epilog="Duration on a 2-core machine: about 30 minutes (3 seeds x 3 grass costs = 9 "
        "runs of smana up, each up to --budget seconds); --quick about 1.5 minutes (2 runs of "
        "20 s in a 6 m garden). A progress bar with an ETA shows on a terminal "
        "(SMANA_PROGRESS=1 forces it, 0 hides it).",
    )
    e.add_argument(
        "--quick", action="store_true", help="2 runs of 20 s in a 6 m garden (about 1.5 min)"
    )
    e.add_argument("--out", type=Path)
    e.add_argument("--seeds", type=positive_int, help="number of world seeds (3, 4, ...)")
    e.add_argument("--budget", type=positive_float, help="time budget per run, seconds")
    e.add_argument(
        "--set",
        dest="extra",
        action="append",
        default=[],
        help="extra config override for every run",
    )
    args = p.parse_args(argv)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = args.out or Path("runs") / f"experiment-{args.which}-{stamp}"
    if args.which == "exploration":
        SmanaConfig.load(overrides=args.extra)  # a bad --set: ConfigError now, not in every run
    output_dir(out, "output directory", "--out")
    if args.which == "noise":
        s = NoiseExperimentConfig.quick() if args.quick else NoiseExperimentConfig()
        if args.backends:
            s.backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
            bad = [b for b in s.backends if b not in BACKENDS]
            if bad:
                p.error(f"unknown back-end(s) {bad}")
        if args.seed is not None:
            s.world_seed = args.seed
        run_noise(s, out)
        print(f"results in {out} (noise_summary.md)")
    else:
        s = ExplorationExperimentConfig.quick() if args.quick else ExplorationExperimentConfig()
        if args.seeds:
            s.seeds = tuple(range(3, 3 + args.seeds))
        if args.budget:
            s.budget_s = args.budget
        s.extra = (*s.extra, *args.extra)
        run_exploration(s, out)
        print(f"results in {out} (exploration_summary.md)")
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(run_command("experiment", cli))
