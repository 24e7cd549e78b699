"""Camera and LiDAR: clouds land on the ground-truth surfaces with the right labels."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest
from scipy.spatial import cKDTree

from smana.common.config.sim import CameraConfig, LidarConfig, SimConfig
from smana.services.sim.camera import label_pixels, linearise_depth, unproject, view_matrix
from smana.services.sim.simulation import Simulation
from smana.services.sim.worlds import BOX, SPHERE, Primitive, Raster, World
from smana.services.sim.worlds.cloud import from_cloud
from smana.services.sim.worlds.garden import GardenConfig

GROUND_IDS = (1, 2)


@pytest.fixture(scope="module")
def sim():
    cfg = SimConfig(
        garden=GardenConfig(size_m=7.0),
        seed=4,
        noise="off",
        camera=CameraConfig(width=160, height=160),
        lidar=LidarConfig(channels=16, columns=512),
    )
    with Simulation(cfg) as s:
        yield s


@pytest.fixture(scope="module")
def gt(sim):
    pts, labels = sim.world.gt_cloud(0.02)
    return cKDTree(pts), labels


def _poses(sim, n=4):
    """A few settled robot poses around the spawn point, looking in different directions."""
    x0, y0, _ = sim.world.spawn_pose(0.5)
    for k in range(n):
        yaw = 0.3 + k * 2 * math.pi / n
        sim.robot.reset((x0, y0), float(sim.world.ground.height_at(x0, y0)), yaw)
        sim.step(0.3)
        yield k


def _check_cloud(world: World, tree, gt_labels, pts, labels):
    d, idx = tree.query(pts)
    # GT samples are 2 cm apart (1.4 cm to the nearest at worst); TinyRenderer draws spheres
    # as polygons with chords ~3 cm inside the true sphere
    assert np.percentile(d, 99) < 0.03 and d.max() < 0.06
    # labels: ground points carry the raster's class, object points their object's class
    ground = np.isin(labels, GROUND_IDS)
    gx, gy = pts[ground, 0].astype(float), pts[ground, 1].astype(float)
    assert np.abs(pts[ground, 2] - world.ground.height_at(gx, gy)).max() < 0.02
    assert np.array_equal(labels[ground], world.ground.class_at(gx, gy))
    obj = ~ground
    inside = world.object_class_at(pts[obj], grow_m=0.04)
    assert np.mean(inside == labels[obj]) > 0.995
    assert np.mean(gt_labels[idx] == labels) > 0.97  # across class borders the nearest differs


def test_camera_cloud_lands_on_ground_truth(sim, gt):
    tree, gt_labels = gt
    seen = set()
    for _ in _poses(sim):
        f = sim.camera_frame()
        assert f.points.dtype == np.float32 and f.labels.dtype == np.uint16
        assert len(f.points) > 0.5 * 160 * 160  # the ground fills most of the view
        assert np.all(f.confidences == 1.0)
        assert np.array_equal(f.semantic, f.semantic_true)
        assert np.allclose(f.world_from_sensor, f.true_world_from_sensor)
        rng = np.linalg.norm(f.points - f.world_from_sensor[:3, 3], axis=1)
        assert rng.max() <= sim.config.camera.max_range_m + 1e-3
        _check_cloud(sim.world, tree, gt_labels, f.points, f.labels)
        seen |= set(np.unique(f.labels).tolist())
    assert len(seen - set(GROUND_IDS)) >= 2  # objects of several classes were seen


def test_lidar_scan_lands_on_ground_truth(sim, gt):
    tree, gt_labels = gt
    for k in _poses(sim, n=2):
        s = sim.lidar_scan()
        assert len(s.points) > 0.3 * 16 * 512
        r = np.linalg.norm(s.points - s.world_from_sensor[:3, 3], axis=1)
        assert r.min() >= 0.3 - 1e-3 and r.max() <= 20.0 + 1e-3
        _check_cloud(sim.world, tree, gt_labels, s.points, s.labels)
        if k == 0:
            # rays attached to the robot give the same hits as rays cast in the world frame
            from smana.services.sim.lidar import Lidar

            free = Lidar(sim.scene, sim.config.lidar, parent_body=-1).scan(sim.true_pose())
            assert np.allclose(free.points_world, s.points, atol=1e-3)


def test_pose_noise_moves_the_published_cloud_rigidly():
    cfg = SimConfig(
        garden=GardenConfig(size_m=6.0),
        seed=4,
        noise="off",
        camera=CameraConfig(width=64, height=64),
        pose_noise_xy_m=0.2,
        pose_noise_yaw_rad=0.05,
    )
    with Simulation(cfg) as sim:
        f = sim.camera_frame()
        delta = f.world_from_sensor @ np.linalg.inv(f.true_world_from_sensor)
        true_pts = f.points - delta[:3, 3]
        true_pts = true_pts @ delta[:3, :3]  # rotate back
        d, _ = cKDTree(sim.world.gt_cloud(0.02)[0]).query(true_pts)
        assert np.percentile(d, 99) < 0.03
        assert np.linalg.norm(delta[:2, 3]) > 1e-3  # the noise did move it
        assert abs(delta[2, 3]) < 1e-9 and np.allclose(delta[2, :3], [0, 0, 1])


def test_degraded_frames_change_labels_not_geometry():
    cfg = SimConfig(
        garden=GardenConfig(size_m=6.0),
        seed=4,
        noise="high",
        camera=CameraConfig(width=96, height=96),
    )
    with Simulation(cfg) as sim:
        f = sim.camera_frame()
        assert np.array_equal(f.semantic >= 0, f.semantic_true >= 0)
        assert f.confidences.min() >= 0.33 and f.confidences.max() <= 1.0
        assert len(f.points) == np.count_nonzero(f.semantic >= 0)
        with Simulation(cfg) as again:  # same seed, same draws
            g = again.camera_frame()
        assert np.array_equal(f.labels, g.labels) and np.array_equal(f.confidences, g.confidences)
        half = sim.camera_frame(stride=2)
        assert len(half.points) < 0.3 * len(f.points) + 10
        msg = f.to_cloud()
        assert msg.points.shape == f.points.shape and msg.source == "camera"


def test_world_from_a_labelled_cloud_is_seen_with_its_classes(tmp_path):
    """The camera in a world built from a small labelled cloud (grass for x < 0, terrain for
    x >= 0, a hedge box, a rose ball, walls added around) sees each class where it should."""
    from tests.test_sim_world import _toy_cloud

    pts, labels = _toy_cloud(0.03)
    world = from_cloud(pts, labels, voxel_m=0.05)
    hedge = Primitive(BOX, (-1.0, 0.5, 0.5), (0.6 + 0.08, 0.25 + 0.08, 0.5 + 0.08))
    rose = Primitive(SPHERE, (1.0, -1.0, 0.3), (0.33, 0.33, 0.33))
    x0, y0, x1, y1 = world.bounds
    cfg = SimConfig(noise="off", camera=CameraConfig(width=128, height=128), spawn=[0.0, -0.2, 2.6])
    with Simulation(cfg, world=world) as sim:
        seen = set()
        for yaw in (2.6, 1.8, -0.6):
            sim.robot.reset((0.0, -0.2), 0.0, yaw)
            sim.step(0.3)
            f = sim.camera_frame()
            q = f.points.astype(float)
            on_ground = np.abs(q[:, 2] - 0.02 * q[:, 0]) < 0.015  # the toy ground's plane
            expected = np.full(len(q), 7)  # off the ground and in no object: a wall
            expected[hedge.contains(q)] = 4
            expected[rose.contains(q)] = 6
            expected[on_ground] = np.where(q[on_ground, 0] < 0, 1, 2)
            wall = (q[:, 0] < x0 + 0.25) | (q[:, 0] > x1 - 0.25)
            wall |= (q[:, 1] < y0 + 0.25) | (q[:, 1] > y1 - 0.25)
            assert np.all(wall[expected == 7])
            clear = np.abs(q[:, 0]) > 0.06  # the grass/terrain border is blurred by one cell
            assert np.mean(expected[clear] == f.labels[clear]) > 0.99
            seen |= set(np.unique(f.labels).tolist())
        assert {1, 2, 4, 6, 7} <= seen


# -- the pieces, against obvious references -------------------------------------------------------


def test_view_matrix_matches_pybullet():
    eye, target = np.array([1.0, 2.0, 0.7]), np.array([3.0, 1.0, 0.2])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    left = np.cross([0, 0, 1.0], fwd)
    left /= np.linalg.norm(left)
    up = np.cross(fwd, left)
    m = np.eye(4)
    m[:3, :3] = np.column_stack([fwd, left, up])
    m[:3, 3] = eye
    ref = p.computeViewMatrix(eye.tolist(), target.tolist(), [0, 0, 1])
    assert np.allclose(view_matrix(m), ref, atol=1e-6)


def test_unproject_inverts_the_pinhole_projection():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 5.0, (6, 8)).astype(np.float32)
    f = 7.0
    pts = unproject(depth, f)
    for r in range(6):
        for c in range(8):
            x, y, z = pts[r, c]
            assert x == pytest.approx(depth[r, c])
            assert (-y / x) * f + 4 == pytest.approx(c + 0.5, abs=1e-4)  # column from the left
            assert (-z / x) * f + 3 == pytest.approx(r + 0.5, abs=1e-4)  # row from the top
    rows, cols = np.array([1, 5]), np.array([2, 7])
    assert np.allclose(unproject(depth, f, rows, cols), pts[rows, cols])
    # the depth buffer round trip: z_ndc -> metres
    near, far = 0.1, 10.0
    d = np.array([0.1, 1.0, 9.0])
    zbuf = (far / (far - near)) * (1 - near / d)
    assert np.allclose(linearise_depth(zbuf, near, far), d)


def _label_pixels_reference(zbuf, seg, rgba, near, far, focal, max_range, m, lut, ground, colours):
    h, w = zbuf.shape
    depth = np.full((h, w), np.inf, np.float32)
    labels = np.full((h, w), -1, np.int32)
    rgb = rgba[..., :3].copy()
    for r in range(h):
        for c in range(w):
            if seg[r, c] < 0 or zbuf[r, c] >= 1.0:
                continue
            d = far * near / (far - (far - near) * zbuf[r, c])
            pt = np.array([d, -(c + 0.5 - w / 2) / focal * d, -(r + 0.5 - h / 2) / focal * d])
            if np.linalg.norm(pt) > max_range:
                continue
            lab = lut[seg[r, c]] if seg[r, c] < len(lut) else -1
            if lab == -2:
                wx, wy, _ = m[:3, :3] @ pt + m[:3, 3]
                lab = int(ground.at(wx, wy))
                shade = rgba[r, c, :3].astype(float).mean() / 255
                rgb[r, c] = np.minimum(colours[lab] * shade, 255).astype(np.uint8)
            if lab < 0:
                continue
            depth[r, c], labels[r, c] = d, lab
    return depth, labels, rgb


def test_label_pixels_matches_a_slow_reference():
    rng = np.random.default_rng(5)
    h, w = 12, 17
    zbuf = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    zbuf[0, :3] = 1.0
    seg = rng.integers(-1, 6, (h, w)).astype(np.int32)
    seg[1, 1] = 99  # an unregistered body
    rgba = rng.integers(0, 256, (h, w, 4)).astype(np.uint8)
    lut = np.array([-2, 4, 5, -1, 7, 8], np.int32)  # body 0 is the ground, 3 the robot
    ground = Raster((-1.0, -1.0), 0.25, rng.choice([1, 2], (9, 9)).astype(np.uint16))
    colours = rng.integers(0, 256, (9, 3)).astype(np.uint8)
    m = np.eye(4)
    m[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    m[:3, 3] = [0.2, -0.1, 0.5]
    args = dict(near=0.1, far=6.0, focal_px=9.0, max_range_m=4.0)
    got = label_pixels(
        zbuf,
        seg,
        rgba,
        world_from_sensor=m,
        label_lut=lut,
        ground=ground,
        colour_lut=colours,
        **args,
    )
    ref = _label_pixels_reference(zbuf, seg, rgba, 0.1, 6.0, 9.0, 4.0, m, lut, ground, colours)
    assert np.array_equal(got[1], ref[1])
    assert np.allclose(got[0], ref[0], rtol=1e-5)
    assert np.abs(got[2].astype(int) - ref[2].astype(int)).max() <= 1
    assert (got[1] >= 0).sum() > 20 and (got[1] == -1).sum() > 20
    with pytest.raises(ValueError, match="shapes"):
        label_pixels(
            zbuf,
            seg[:5],
            rgba,
            world_from_sensor=m,
            label_lut=lut,
            ground=ground,
            colour_lut=colours,
            **args,
        )


def test_lidar_pattern_is_an_os1_64():
    spec = LidarConfig()
    d = spec.directions()
    assert d.shape == (131072, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    el = np.degrees(np.arcsin(d[:, 2]))
    assert el.max() == pytest.approx(16.6) and el.min() == pytest.approx(-16.6)
    assert len(np.unique(np.round(el, 6))) == 64


@pytest.mark.parametrize("kind", ["thread", "process"])
def test_frames_finished_on_a_worker_match_sequential_frames(kind):
    """The service finishes frames on a worker (a process by default): the published bytes, label
    and confidence draws included, must not depend on where."""
    from smana.common.messages import SemanticCloud, decode
    from smana.services.sim.finishing import finished, make_worker

    cfg = SimConfig(
        garden=GardenConfig(size_m=6.0),
        seed=4,
        noise="medium",
        camera=CameraConfig(width=64, height=64, publish_images=True),
    )
    with Simulation(cfg) as a, Simulation(cfg) as b:
        sequential, futures = [], []
        executor, finish = make_worker(kind, cfg, b.finisher, b.world.classes.colour_lut)
        with executor:
            for _ in range(3):
                for s in (a, b):
                    s.set_velocity(0.3, 0.5)
                    s.step(0.2)
                sequential.append(finished(a.camera_frame(), images=True))
                futures.append(executor.submit(finish, b.capture_camera()))
            piped = [f.result() for f in futures]
    for f, g in zip(sequential, piped, strict=True):
        assert f.seq == g.seq
        assert f.cloud == g.cloud  # the encoded message, to the byte
        assert f.images == g.images and set(g.images) == {"rgb", "depth", "semantic"}
        cloud = decode(g.cloud, SemanticCloud)
        assert len(cloud.points) > 100 and cloud.confidences.min() < 1.0  # noise was applied


def test_safety_scan_is_in_the_base_frame_untouched_by_pose_noise(gt):
    """robot/safety_scan: placed with the robot's true pose, its points land on the world; the
    published pose's noise never reaches them; none is on the robot itself."""
    tree, _ = gt
    cfg = SimConfig(
        garden=GardenConfig(size_m=7.0),
        seed=4,
        noise="off",
        camera=CameraConfig(width=32, height=32),
        pose_noise_xy_m=0.3,
        pose_noise_yaw_rad=0.1,
    )
    with Simulation(cfg) as s:
        for _ in _poses(s, n=2):
            c = s.safety_scan()
            assert c.frame_id == "base_link" and c.source == "safety_scan"
            assert len(c.points) > 0.3 * cfg.safety_scan.n_rays
            world = (s.true_pose() @ np.c_[c.points, np.ones(len(c.points))].T).T[:, :3]
            d, _ = tree.query(world)
            assert np.percentile(d, 99) < 0.03
            r = np.hypot(c.points[:, 0], c.points[:, 1])
            assert r.max() <= cfg.safety_scan.max_range_m + 1e-3
            low = c.points[:, 2] < cfg.safety_scan.mount_xyz[2] - 1e-3  # from beams pointing down
            assert r[low].min() >= cfg.safety_scan.body_radius_m - 1e-3
