"""The plotting module: it refuses a figure without a legend, every figure smana writes goes
through it (recorded while the report, the experiments, the replay benchmark and the world preview
write theirs), maps take the class table's own colours and names, and equal series stay visible."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.lab import paper_figures
from smana.lab.experiments import exploration_report as exr

TABLE = ClassTable.from_dict(
    {
        "name": "plot-test",
        "class": [
            {"id": 0, "name": "unknown", "kind": "unknown", "colour": [0, 0, 0]},
            {"id": 1, "name": "moss", "kind": "traversable", "cost": 1.0, "colour": [10, 20, 200]},
            {"id": 3, "name": "boulder", "kind": "obstacle", "colour": [250, 240, 5]},
        ],
    }
)


@pytest.fixture
def saved(monkeypatch):
    """Every figure handed to `paper_figures.save` (the lab's or the product's,
    common/plotting.py): (path, figure), in order."""
    from smana.common import plotting

    record: list[tuple[Path, object]] = []
    real = paper_figures.save

    def recording(fig, path, *args, **kwargs):
        out = real(fig, path, *args, **kwargs)  # refuses first, records only what was written
        record.append((Path(out), fig))
        return out

    monkeypatch.setattr(paper_figures, "save", recording)
    monkeypatch.setattr(plotting, "save", recording)
    return record


def _legend_texts(fig) -> list[str]:
    return [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]


def test_save_refuses_a_figure_without_a_legend(tmp_path):
    fig = paper_figures.new_figure()
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], label="a line")
    ax.set_title("no key")
    with pytest.raises(paper_figures.PlotError, match="no legend"):
        paper_figures.save(fig, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
    ax.legend()
    assert paper_figures.save(fig, tmp_path / "x.png").stat().st_size > 1000
    with pytest.raises(paper_figures.PlotError, match="not an image type"):
        paper_figures.save(fig, tmp_path / "x.nope")


def test_importing_the_module_does_not_load_matplotlib():
    import subprocess
    import sys

    code = (
        "import sys, smana.lab.paper_figures, smana.deploy.report; "
        "print('matplotlib' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_world_map_uses_the_class_tables_colours_and_names(tmp_path):
    ids = np.zeros((40, 30), np.uint16)
    ids[:, :] = 1
    ids[5:15, 5:15] = 3  # a boulder in the south-west
    traj = np.array([[0.5, 0.5], [2.0, 1.0], [3.0, 2.5]])
    fig = paper_figures.world_map(
        TABLE, ids, (0.05, 0.05), 0.1, "toy", trajectory=traj, goals=traj[1:]
    )
    texts = _legend_texts(fig)
    assert {"moss", "boulder", "trajectory", "start", "goals (n = 2)"} <= set(texts)
    assert "unknown" not in texts  # only the classes the map shows
    handles = fig.axes[0].get_legend().legend_handles
    face = {t: h.get_facecolor()[:3] for t, h in zip(texts, handles) if t in ("moss", "boulder")}
    assert np.allclose(face["moss"], np.array([10, 20, 200]) / 255)
    assert np.allclose(face["boulder"], np.array([250, 240, 5]) / 255)
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"
    assert ax.get_aspect() == 1.0
    assert ax.get_xlim() == pytest.approx((0.0, 4.0)) and ax.get_ylim() == pytest.approx((0.0, 3.0))
    # the pixels are the table's colours too (BGR as OpenCV reads them)
    img = cv2.imread(str(paper_figures.save(fig, tmp_path / "m.png")))
    for rgb in ((10, 20, 200), (250, 240, 5)):
        assert np.any(np.all(img == rgb[::-1], axis=2)), rgb


def test_graph_map_labels_unknown_obstacle_safety_zone_and_frontier():
    labels = np.ones((20, 20), np.uint16)
    flags = np.zeros((20, 20), np.uint8)
    flags[:12] = 1  # known for x < 12 cells
    flags[4, 4] = 1 | 2
    flags[3:6, 3:6] |= 4
    flags[4, 4] = 1 | 2
    fig = paper_figures.graph_map(TABLE, labels, flags, (0.0, 0.0), 0.2, "graph")
    texts = _legend_texts(fig)
    assert {"moss", "unknown", "obstacle", "safety zone", "frontier"} <= set(texts)
    assert "doubtful" not in texts  # none in this graph


def test_graph_map_shows_doubtful_nodes_in_their_own_colour():
    labels = np.ones((20, 20), np.uint16)
    flags = np.ones((20, 20), np.uint8)  # all known: no frontier
    flags[8, 8] = 1 | 8  # a doubtful node in the middle of the lawn
    fig = paper_figures.graph_map(TABLE, labels, flags, (0.0, 0.0), 0.2, "graph")
    assert "doubtful" in _legend_texts(fig)
    img = fig.axes[0].get_images()[0].get_array()
    want = paper_figures.OVERLAY["doubtful"]
    np.testing.assert_allclose(np.asarray(img[8, 8])[:3], want, atol=0.02)
    assert not np.allclose(np.asarray(img[2, 2])[:3], want, atol=0.02)


def test_equal_series_stay_visible():
    same = [0.1, 0.2, 0.3]
    fig = paper_figures.line_plot(
        [
            paper_figures.Series("octree-bayes", [0, 1, 2], same),
            paper_figures.Series("octree-max", [0, 1, 2], same),
        ],
        "t",
        "level",
        "ratio",
    )
    a, b = fig.axes[0].get_lines()[:2]
    assert a.get_marker() != b.get_marker() and a.get_linestyle() != b.get_linestyle()
    assert not np.allclose(a.get_xdata(), b.get_xdata())  # side by side, not on top


def test_progress_has_two_panels_in_robot_time():
    fig = paper_figures.progress_plot(
        np.array([0.0, 5, 9]), np.array([1.0, 9, 18]), np.array([0, 2, 4.0])
    )
    top, bottom = fig.axes
    assert top.get_ylabel() == "explored area (m²)" and bottom.get_ylabel() == "distance (m)"
    assert "robot time (s)" in bottom.get_xlabel()
    assert "explorer's graph: known free nodes" in _legend_texts(fig)


def test_the_reports_pngs_all_go_through_the_module(tmp_path, saved):
    from smana.common.config import SmanaConfig
    from smana.deploy.report.ground_truth import world_from_config
    from smana.deploy.report.run_plots import run_plots

    cfg = SmanaConfig.load(None, ["sim.garden.size_m=5.0", "sim.seed=3"])
    world = world_from_config(cfg)
    x0, y0, _ = world.spawn_pose(0.4)
    t = np.arange(0.0, 3.0, 0.1)
    traj = np.column_stack([t, x0 + 0.2 * t, y0 + 0 * t, 0 * t])
    flags = np.zeros((25, 25), np.uint8)
    flags[:12] = 1
    graph = {
        "origin_xy": np.array([-2.5, -2.5]),
        "resolution_m": 0.2,
        "labels": np.full((25, 25), 2, np.uint16),
        "flags": flags,
    }
    state = {"plans": [{"goal": [1.0, 1.0]}], "history": [[0, 1, 5, 0], [2, 4, 3, 0.6]]}
    replay = {"per_scan": [[i, i, f"s{i}", 0.1 * i, 100, 5.0 + i] for i in range(4)]}
    exploration = {"usable_area_m2": 4.5}
    classes = ClassTable.load("garden3drms")
    files = run_plots(tmp_path, classes, world, graph, traj, state, replay, exploration)
    assert set(files) == {"map", "graph", "progress", "replay_latency"}
    written = sorted(p.relative_to(tmp_path) for p in (tmp_path / "plots").glob("*.png"))
    assert written == sorted(p.relative_to(tmp_path) for p, _ in saved)
    assert sorted(Path(f) for f in files.values()) == written
    by_name = {p.name: fig for p, fig in saved}
    # the world's classes in their table colours, the start and goals labelled
    texts = _legend_texts(by_name["world_trajectory.png"])
    assert {"grass", "terrain", "start", "trajectory", "goals (n = 1)"} <= set(texts)
    assert "report: usable ∩ reachable ground truth (4.5 m²)" in _legend_texts(
        by_name["progress.png"]
    )
    assert "wall time" in by_name["replay_latency.png"].axes[0].get_ylabel()


def test_the_experiments_figures_say_n_and_draw_spread_only_with_several_runs(tmp_path, saved):
    from smana.lab import experiments as exp

    rows = []
    for b in exp.BACKENDS:
        for sweep, level in (("label", "none"), ("label", "high"), ("pose", "high")):
            rows.append(
                {
                    "backend": b,
                    "sweep": sweep,
                    "level": level,
                    "label_p": 1.0,
                    "pose_sigma_xy_m": 0.0,
                    "pose_sigma_yaw_rad": 0.0,
                    "n_points": 1000,
                    "error_mean_m": 0.02,  # every back-end equal: none may hide another
                    "error_std_m": 0.01,
                    "classification_ratio": 0.9,
                    "integrate_ms_per_frame": 1.0,
                    "per_class_ratio": {},
                }
            )
    meta = {
        "settings": asdict(exp.NoiseExperimentConfig()),
        "trajectory_length_m": 44.0,
        "frames": 10,
        "pose_noise": exp.POSE_NOISE,
        "seconds": 1.0,
    }
    exp.write_noise_outputs(rows, meta, tmp_path / "noise")
    names = {p.name for p, _ in saved}
    assert {
        "fig6_pose_noise_error.png",
        "fig6_pose_noise_ratio.png",
        "fig7_label_noise_ratio.png",
    } <= names
    for _, fig in saved:
        lines = [c.lines[0] for c in fig.axes[0].containers]  # each series' data line
        styles = {(ln.get_marker(), ln.get_linestyle()) for ln in lines}
        assert len(styles) == len(exp.BACKENDS)
        assert "n = 1" in fig.axes[0].get_legend().get_title().get_text()
        assert not fig.axes[0].collections  # one run: no interval bars

    # three seeds: each point a mean with its 95 % interval over them
    saved.clear()
    rows3 = [{**r, "seed": s, "error_mean_m": 0.02 + 0.001 * s} for s in (3, 4, 5) for r in rows]
    exp.write_noise_outputs(rows3, meta, tmp_path / "noise3")
    assert len(saved) == 3
    for _, fig in saved:
        title = fig.axes[0].get_legend().get_title().get_text()
        assert "95 % t-interval (n = 3 seeds)" in title
        assert fig.axes[0].collections  # the interval bars

    def exploration(seeds):
        from smana.lab.experiments import exploration as ex

        saved.clear()
        runs = []
        for seed in seeds:
            for f in (1.0, 4.0):
                hist = [(10.0 * k, 4.0 * k, 3, 3.0 * k) for k in range(11)]
                m = {
                    "exploration": {
                        "terrain_share": 0.5 + 0.05 * f + 0.01 * seed,
                        "coverage": 0.9,
                        "known_reachable_share": 0.9,  # what the curves end at
                        "distance_m": 30.0,
                    },
                    "explorer": {"explored_m2": 40.0},
                }
                runs.append(ex.make_row(seed, ex.nbv(f), 0, m, {"history": hist}, 1.0, 1.0))
        out = tmp_path / f"exploration{len(seeds)}"
        exr.write_exploration_outputs(runs, ex.ExplorationExperimentConfig(seeds=seeds), out)
        by_name = {p.name: fig for p, fig in saved}
        assert set(by_name) == {
            "exploration_terrain_share.png",
            "exploration_coverage_distance.png",
            "exploration_coverage_time.png",
        }
        return by_name

    figs = exploration((3, 4, 5))
    fig = figs["exploration_terrain_share.png"]
    assert "n = 3 seeds" in fig.axes[0].get_title()
    assert any("95 % CI (n = 3 seeds)" in t for t in _legend_texts(fig))
    assert fig.axes[0].collections  # the error bars
    band = figs["exploration_coverage_distance.png"].axes[0]
    assert band.collections  # the interval bands
    assert any("n = 3" in t for t in _legend_texts(figs["exploration_coverage_time.png"]))
    fig = exploration((3,))["exploration_terrain_share.png"]
    assert "n = 1 seed" in fig.axes[0].get_title()
    assert not any("CI" in t for t in _legend_texts(fig))
    # no error bars: only the paper's line and smana's, no bar collections
    assert not fig.axes[0].collections


def test_replay_bench_figures_and_world_preview(tmp_path, saved):
    from smana.lab.bench.replay import RunResult, aggregate
    from smana.services.sim.world_cli import cli as world_cli

    runs = []
    for b in ("octree-max", "tsdf"):
        r = RunResult(b, 0.1, 0.2, 0, scans=3, points_per_scan=1000.0)
        r.map_ms, r.map_us_per_point = [10.0, 12.0], [10.0, 12.0]
        r.graph_ms, r.graph_us_per_point = [5.0, 5.0], [5.0, 5.0]
        r.cpu_map, r.cpu_graph = [100.0, 90.0], [10.0, 20.0]
        r.rss_map_mb, r.rss_graph_mb = 300.0, 50.0
        runs.append(r)
    rows = aggregate(runs)
    paper_figures.figure_11(rows, tmp_path / "f11.png")
    paper_figures.figure_12(rows, tmp_path / "f12.png")
    assert (
        world_cli(["preview", "--seed", "2", "--size", "5", "--out", str(tmp_path / "w.png")]) == 0
    )
    assert [p.name for p, _ in saved] == ["f11.png", "f12.png", "w.png"]
    f11, f12, preview = (fig for _, fig in saved)
    assert "n = 1 run" in f11.axes[0].get_legend().get_title().get_text()
    assert f12.axes[0].get_yscale() == "log" and "µs" in f12.axes[0].get_ylabel()
    ax = preview.axes[0]
    assert ax.get_xlabel() == "x (m)" and ax.get_aspect() == 1.0
    names = set(_legend_texts(preview))
    assert {"grass", "obstacle"} <= names  # the lawn and the garden's walls
    assert names <= {c.name for c in ClassTable.load("garden3drms").classes.values()} | {
        "object outline (seen from above)"
    }


def test_a_shares_band_is_cut_to_0_1_and_the_legend_says_so():
    """Issue 26: an interval of a share is clipped to [0, 1] in a figure."""
    x = np.arange(3.0)
    mean = np.array([0.5, 0.9, 0.98])
    lo, hi = mean - 0.2, mean + 0.2  # 1.18 at the end: no share is above 1
    fig = paper_figures.band_plot(
        [("1 robot (n = 3)", x, mean, lo, hi)], "t", "x", "y", "mean", clip=(0, 1)
    )
    ax = fig.axes[0]
    band = ax.collections[0].get_paths()[0].vertices
    assert band[:, 1].max() <= 1.0 and band[:, 1].min() >= 0.0
    assert ax.get_legend().get_title().get_text() == "mean, cut to [0, 1]"
    unclipped = paper_figures.band_plot([("a", x, mean, lo, hi)], "t", "x", "y", "mean").axes[0]
    assert unclipped.collections[0].get_paths()[0].vertices[:, 1].max() > 1.1
