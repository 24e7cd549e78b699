"""Perception noise beyond the paper's (services/sim/perception.py, confusion_rellis3d.py, the
drift of degrade.py's PoseNoise): each part against a slow, obvious reference, repeatability,
persistence across views, the drift's growth, the paper's levels unchanged, the config."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import ConfigError, SmanaConfig
from smana.common.config.sim import CameraConfig, PerceptionConfig, SimConfig
from smana.services.sim.confusion_rellis3d import garden_matrix, shrub_swap
from smana.services.sim.degrade import GARDEN_IDS, WET_IDS, LabelDegrader, PoseNoise
from smana.services.sim.perception import (
    PersistentErrors,
    bleed,
    cell_uniforms,
    perception_matrix,
    split_matrix,
)
from tests.test_cli_misuse import one_line_misuse, smana

LUT = ClassTable.load("garden3drms").colour_lut


def _image() -> np.ndarray:
    lab = np.full((96, 128), 1, np.int32)
    lab[:, 40:80] = 2
    lab[20:60, 10:30] = 4
    lab[50:90, 90:120] = 8
    lab[5:25, 60:100] = 5
    lab[70:90, 20:50] = 6
    lab[30:45, 85:95] = 7
    lab[:8, :] = -1
    return lab


# sha256 prefixes of the paper's levels computed on main before these options existed (the
# degrader on _image() three times plus 50 confidences; white pose noise five times; and two
# 96 x 96 camera frames of a Simulation with pose noise): the levels must not move a bit.
GOLDEN = {
    "off": "eb25ead4cf0d045f",
    "none": "e753143ff8fd8360",
    "low": "b64d8527f01a277e",
    "medium": "cc761e3bb6d4df08",
    "high": "4a58ddd0c4b4f44a",
    "pose": "11aab7fe8ea70ca3",
}
GOLDEN_SIM = {"medium": "4c0943ae2ab832ae", "high": "e3a0735dcb60234a"}


def test_the_papers_levels_are_unchanged_bit_for_bit():
    for level in ("off", "none", "low", "medium", "high"):
        ss = np.random.SeedSequence([3, 0x51A]).spawn(3)[0]
        d = LabelDegrader(level, np.random.default_rng(ss), LUT)
        h = hashlib.sha256()
        for _ in range(3):
            h.update(d.degrade(_image()).labels.tobytes())
        h.update(d.confidences(50).tobytes())
        assert h.hexdigest()[:16] == GOLDEN[level], level
    pn = PoseNoise(0.1, 0.02, np.random.default_rng(5))
    h = hashlib.sha256()
    for _ in range(5):
        h.update(pn.apply(np.eye(4)).tobytes())
    assert h.hexdigest()[:16] == GOLDEN["pose"]


def test_the_papers_levels_are_unchanged_through_the_simulation():
    from smana.services.sim.simulation import Simulation

    for level, digest in GOLDEN_SIM.items():
        cfg = SimConfig(
            seed=3,
            noise=level,
            pose_noise_xy_m=0.05,
            pose_noise_yaw_rad=0.01,
            camera=CameraConfig(width=96, height=96),
        )
        with Simulation(cfg) as sim:
            assert sim.finisher.noise is None
            h = hashlib.sha256()
            for _ in range(2):
                sim.set_velocity(0.3, 0.4)
                sim.step(0.5)
                f = sim.camera_frame()
                for a in (f.semantic, f.points, f.labels, f.confidences, sim.published_pose()):
                    h.update(np.ascontiguousarray(a).tobytes())
            assert h.hexdigest()[:16] == digest, level


# -- boundary bleed ------------------------------------------------------------------------------


def _bleed_reference(labels: np.ndarray, k: int, ranks: np.ndarray) -> np.ndarray:
    h, w = labels.shape
    out = labels.copy()
    for r in range(h):
        for c in range(w):
            if labels[r, c] < 0:
                continue
            best, best_rank = labels[r, c], ranks[labels[r, c]]
            for rr in range(max(0, r - k), min(h, r + k + 1)):
                for cc in range(max(0, c - k), min(w, c + k + 1)):
                    v = labels[rr, cc]
                    if v >= 0 and ranks[v] > best_rank:
                        best, best_rank = v, ranks[v]
            out[r, c] = best
    return out


@pytest.mark.parametrize("k", [1, 2, 3])
def test_bleed_matches_a_pixel_loop(k):
    rng = np.random.default_rng(k)
    labels = rng.choice([-1, 1, 2, 4, 5, 8], size=(23, 31), p=[0.1, 0.3, 0.3, 0.1, 0.1, 0.1])
    labels = labels.astype(np.int32)
    ranks = rng.permutation(10) + 1
    assert np.array_equal(bleed(labels, k, ranks), _bleed_reference(labels, k, ranks))
    assert np.array_equal(bleed(labels, 0, ranks), labels)


# -- persistent errors ---------------------------------------------------------------------------


def _persistent_reference(errors: PersistentErrors, matrix, ids, true, xy) -> np.ndarray:
    out = []
    for lab, (x, y) in zip(true, xy, strict=True):
        if lab < 0 or lab not in ids:
            out.append(lab)
            continue
        k = ids.index(lab)
        ix = np.array([np.floor(x / errors.cell_m)])
        iy = np.array([np.floor(y / errors.cell_m)])
        u0 = cell_uniforms(errors.key, ix, iy, np.array([lab]), 0)[0]
        off = [matrix[k][j] if j != k else 0.0 for j in range(len(ids))]
        if u0 >= sum(off):
            out.append(lab)
            continue
        u1 = cell_uniforms(errors.key, ix, iy, np.array([lab]), 1)[0] * sum(off)
        acc = 0.0
        for j, share in enumerate(off):
            acc += share
            if u1 < acc:
                out.append(ids[j])
                break
        else:
            out.append(ids[max(j for j, s in enumerate(off) if s > 0)])
    return np.array(out)


def test_persistent_errors_match_a_point_loop():
    ids = GARDEN_IDS
    matrix = garden_matrix(ids, wet=False)
    pers, _ = split_matrix(matrix, 0.8)
    errors = PersistentErrors(pers, ids, 0.5, key=1234)
    rng = np.random.default_rng(0)
    true = rng.choice([-1, 0, 1, 2, 4, 5, 6, 7, 8], 3000)
    xy = rng.uniform(-6, 6, (3000, 2))
    got = errors.labels(true, xy)
    assert np.array_equal(got, _persistent_reference(errors, pers, ids, true, xy))
    assert (got != true).mean() > 0.02  # some are wrong


def test_persistent_errors_are_the_same_from_any_view_of_a_cell():
    """Two views see the same places through different points: every point of a (cell, class)
    gets the one label that cell and class keep, whoever looks."""
    ids = GARDEN_IDS
    table2 = PerceptionConfig(confusion="table2", accuracy=0.7)
    pers, _ = split_matrix(perception_matrix(table2, ids, False), 1)
    errors = PersistentErrors(pers, ids, 0.75, key=99)
    rng = np.random.default_rng(1)
    cells = rng.integers(-8, 8, (400, 2))
    classes = rng.choice([1, 2, 4, 5, 6, 7, 8], 400)
    views = []
    for _ in range(2):  # other points inside the same cells
        xy = (cells + rng.uniform(0.01, 0.99, (400, 2))) * 0.75
        views.append(errors.labels(classes, xy))
    assert np.array_equal(views[0], views[1])
    wrong = views[0] != classes
    assert 0.15 < wrong.mean() < 0.45  # p = 0.7: a share 0.3 of the cells, all persistent
    # another seed's key makes other cells wrong
    other = PersistentErrors(pers, ids, 0.75, key=100).labels(classes, xy)
    assert not np.array_equal(other, views[1])


def test_persistence_holds_across_two_camera_views_in_the_simulation():
    """With every error persistent and no bleed, two frames from different poses give the same
    wrong label to the same (world cell, true class)."""
    from smana.services.sim.simulation import Simulation, _world_xy

    cfg = SmanaConfig.load(
        None,
        [
            "sim.seed=4",
            "sim.noise=realistic",
            "sim.camera.width=128",
            "sim.camera.height=128",
            "sim.perception.confusion=table2",
            "sim.perception.accuracy=0.7",
            "sim.perception.persistent_share=1.0",
            "sim.perception.cell_m=0.5",
            "sim.perception.bleed_px=0",
        ],
    ).sim
    with Simulation(cfg) as sim:
        noise = sim.finisher.noise
        seen = []
        for turn in (0.0, 0.6):
            sim.set_velocity(0.3, turn)
            sim.step(0.6)
            pending = sim.capture_camera()
            frame = sim.finish_camera(pending)
            valid = frame.semantic_true >= 0
            xy = _world_xy(pending.capture)
            true = frame.semantic_true[valid]
            cells = np.floor(xy / 0.5).astype(np.int64)
            pers = noise.persistent.labels(true, xy)
            wrong = pers != true
            # a persistently wrong pixel shows its persistent label, whatever the frame drew
            assert np.array_equal(frame.semantic[valid][wrong], pers[wrong])
            seen.append({(a, b, t): p for (a, b), t, p in zip(cells, true, pers, strict=True)})
        common = seen[0].keys() & seen[1].keys()
        assert len(common) > 20
        assert all(seen[0][k] == seen[1][k] for k in common)
        assert any(seen[0][k] != k[2] for k in common)  # some shared place is wrong in both


# -- the confusion matrices ----------------------------------------------------------------------


def test_the_rellis3d_matrix_follows_the_published_rows_and_mapping():
    dry = garden_matrix(GARDEN_IDS, wet=False)
    wet = garden_matrix(WET_IDS, wet=True)
    for m in (dry, wet):
        assert np.allclose(m.sum(axis=1), 1.0) and (m >= 0).all()
    i = {c: k for k, c in enumerate(GARDEN_IDS)}
    assert dry[i[0], i[0]] == 1.0  # unknown is never confused
    assert dry[i[1], i[1]] == pytest.approx(0.94)  # grass: HRNet+OCR's 0.94
    assert dry[i[1], i[2]] == pytest.approx(0.01)  # grass -> mud: terrain
    # terrain: the mean of concrete, asphalt, mud; its grass share is (0.02 + 0.03 + 0.39) / 3
    assert dry[i[2], i[1]] == pytest.approx(0.44 / 3 / 0.99, rel=0.02)
    assert dry[i[8], i[8]] == pytest.approx(0.88 / 0.96)  # tree, its sky share dropped
    assert 0.04 < shrub_swap() < 0.07
    assert dry[i[4], i[5]] == pytest.approx(dry[i[4], i[6]]) and dry[i[4], i[5]] > 0.04
    w = {c: k for k, c in enumerate(WET_IDS)}
    assert wet[w[9], w[9]] == pytest.approx(0.79)  # water: the puddle row
    assert wet[w[9], w[1]] == pytest.approx(0.13)


def test_pairs_confuse_only_the_listed_pairs():
    pairs = PerceptionConfig(confusion="pairs", accuracy=0.8)
    m = perception_matrix(pairs, GARDEN_IDS, False)
    i = {c: k for k, c in enumerate(GARDEN_IDS)}
    assert m[i[1], i[2]] == pytest.approx(0.2) and m[i[2], i[1]] == pytest.approx(0.2)
    assert m[i[4], i[5]] == pytest.approx(0.1) and m[i[4], i[8]] == pytest.approx(0.1)
    assert m[i[6], i[6]] == 1.0 and m[i[7], i[7]] == 1.0  # rose and obstacle: not in a pair
    wet = perception_matrix(pairs, WET_IDS, True)
    w = {c: k for k, c in enumerate(WET_IDS)}
    assert wet[w[9], w[1]] == pytest.approx(0.2) and wet[w[1], w[9]] == pytest.approx(0.1)


@pytest.mark.parametrize("share", [0.0, 0.3, 0.5, 1.0])
def test_split_keeps_each_classs_total_error_and_its_spread(share):
    m = garden_matrix(WET_IDS, wet=True)
    pers, trans = split_matrix(m, share)
    n = len(m)
    for a in (pers, trans):
        assert np.allclose(a.sum(axis=1), 1.0) and (a >= -1e-12).all()
    # persistently wrong, or persistently right and then redrawn
    combined = pers - np.diag(np.diag(pers)) + np.diag(pers)[:, None] * trans
    assert np.allclose(combined, m)
    assert np.allclose(np.diag(pers), 1 - share * (1 - np.diag(m)))
    assert n == len(WET_IDS)


def test_realistic_labels_repeat_with_the_seed_and_differ_with_another():
    from smana.services.sim.simulation import Simulation

    def labels(seed):
        cfg = SimConfig(seed=seed, noise="realistic", camera=CameraConfig(width=96, height=96))
        with Simulation(cfg) as sim:
            sim.set_velocity(0.2, 0.3)
            sim.step(0.5)
            t = {}
            f = sim.camera_frame(timings=t)
            assert {"persistent_ms", "bleed_ms"} <= t.keys()
            return f.semantic, f.semantic_true, f.confidences

    a, b = labels(3), labels(3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert (a[0] != a[1]).any()  # noisy
    c = labels(5)
    assert not np.array_equal(a[0], c[0])


# -- pose drift ----------------------------------------------------------------------------------


def test_drift_variance_grows_linearly_in_time():
    sigma, sigma_yaw = 0.05, 0.01
    walkers = [
        PoseNoise(0.0, 0.0, np.random.default_rng(0), sigma, sigma_yaw, np.random.default_rng(ss))
        for ss in np.random.SeedSequence(11).spawn(600)
    ]
    times = np.arange(0.0, 20.01, 0.5)
    offsets = np.array([[w.walk_to(t) for t in times] for w in walkers])  # (walker, time, 3)
    for k, t in enumerate(times):
        if t < 2:
            continue
        var_xy = offsets[:, k, :2].var()
        var_yaw = offsets[:, k, 2].var()
        assert var_xy == pytest.approx(sigma**2 * t, rel=0.2), t
        assert var_yaw == pytest.approx(sigma_yaw**2 * t, rel=0.25), t
    # and the published pose carries it
    w = walkers[0]
    m = w.apply(np.eye(4), 25.0)
    assert m[:2, 3] == pytest.approx(w.drift[:2])


def test_drift_leaves_the_white_noise_draws_alone():
    white = PoseNoise(0.1, 0.02, np.random.default_rng(5))
    both = PoseNoise(0.1, 0.02, np.random.default_rng(5), 0.05, 0.01, np.random.default_rng(6))
    for t in (0.0, 1.0, 2.0):
        a, b = white.apply(np.eye(4), t), both.apply(np.eye(4), t)
        assert b[:2, 3] - a[:2, 3] == pytest.approx(both.drift[:2])


# -- config --------------------------------------------------------------------------------------


def test_the_realistic_preset_is_the_sections_defaults_and_keys_override_it():
    r = PerceptionConfig()
    assert (r.confusion, r.persistent_share, r.cell_m, r.bleed_px) == ("rellis3d", 0.5, 0.75, 2)
    cfg = SmanaConfig.load(
        None,
        [
            "sim.noise=realistic",
            "sim.perception.bleed_px=0",
            "sim.pose_drift_xy_m_per_sqrt_s=0.02",
            "sim.pose_drift_yaw_rad_per_sqrt_s=0.005",
        ],
    )
    assert cfg.sim.noise == "realistic" and cfg.sim.perception.bleed_px == 0
    assert cfg.sim.perception.persistent_share == 0.5
    assert cfg.sim.pose_drift_xy_m_per_sqrt_s == 0.02
    assert cfg.sim.pose_drift_yaw_rad_per_sqrt_s == 0.005


def test_the_papers_levels_ignore_the_perception_section():
    from smana.services.sim.simulation import FrameFinisher

    cfg = SmanaConfig.load(None, ["sim.noise=high", "sim.perception.persistent_share=1"]).sim
    f = FrameFinisher(cfg, LUT)
    assert f.noise is None
    assert np.array_equal(f.degrader.matrix, LabelDegrader("high", None, LUT).matrix)
    realistic = FrameFinisher(SmanaConfig.load(None, ["sim.noise=realistic"]).sim, LUT)
    assert realistic.noise is not None and realistic.noise.bleed_px == 2


@pytest.mark.parametrize(
    "override, message",
    [
        ("sim.noise=noisy", "sim.noise: expected one of"),
        ("sim.perception.persistent_share=1.5", "sim.perception.persistent_share: expected"),
        ("sim.perception.bleed_px=-1", "sim.perception.bleed_px: expected"),
        ("sim.perception.cell_m=0", "sim.perception.cell_m: expected a number > 0"),
        ("sim.perception.confusion=cityscapes", "sim.perception.confusion: expected one of"),
        ("sim.pose_drift_xy_m_per_sqrt_s=-0.1", "sim.pose_drift_xy_m_per_sqrt_s: expected"),
        ("sim.pose_drift_yaw_rad_per_sqrt_s=-1", "sim.pose_drift_yaw_rad_per_sqrt_s: expected"),
    ],
)
def test_bad_perception_values_name_the_key(override, message):
    with pytest.raises(ConfigError) as info:
        SmanaConfig.load(None, [override])
    assert message in str(info.value)


def test_a_bad_noise_on_the_command_line_is_one_line_and_exit_2():
    r = smana("up", "--set", "sim.noise=noisy", "--duration", "1")
    one_line_misuse(r, "up", "sim.noise", "realistic")
    r = smana("up", "--set", "sim.perception.bleed_px=100", "--duration", "1")
    one_line_misuse(r, "up", "sim.perception.bleed_px")


def test_the_lidar_carries_the_cameras_persistent_errors():
    from smana.common.config.sim import LidarConfig
    from smana.services.sim.scene import transform_points
    from smana.services.sim.simulation import Simulation

    cfg = SimConfig(
        seed=3,
        noise="realistic",
        camera=CameraConfig(width=32, height=32),
        lidar=LidarConfig(enabled=True, channels=16, columns=256),
    )
    with Simulation(cfg) as sim:
        scan = sim.lidar_scan()
        hits = sim.lidar.scan(sim.true_pose())  # the same pose: the same rays, true labels
        xy = transform_points(hits.points_sensor, hits.world_from_sensor)[:, :2]
        expected = sim.finisher.noise.persistent.labels(hits.labels, xy)
        assert np.array_equal(scan.labels, expected.astype(np.uint16))
        assert (expected != hits.labels).any()
    with Simulation(SimConfig(seed=3, noise="high", lidar=cfg.lidar)) as sim:
        scan, hits = sim.lidar_scan(), sim.lidar.scan(sim.true_pose())
        assert np.array_equal(scan.labels, hits.labels.astype(np.uint16))  # the paper's: true
