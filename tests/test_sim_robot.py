"""The PyBullet scene and the differential-drive robot: ground agreement, arcs, stopping."""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
import pytest

from smana.common.config.sim import CameraConfig, SimConfig
from smana.services.sim.scene import DROP, GROUND, BulletScene
from smana.services.sim.simulation import Simulation
from smana.services.sim.worlds.cloud import from_cloud
from smana.services.sim.worlds.garden import GardenConfig, generate


@pytest.fixture(scope="module")
def sim():
    with Simulation(
        SimConfig(
            garden=GardenConfig(size_m=8.0),
            seed=2,
            camera=CameraConfig(enabled=False),
            noise="off",
        )
    ) as s:
        yield s


def test_height_field_agrees_with_the_ground_model():
    world = generate(seed=11, size_m=5.0, layout="classic")
    with BulletScene(world) as scene:
        rng = np.random.default_rng(0)
        xy = rng.uniform(-2.3, 2.3, (300, 2))
        hits = p.rayTestBatch(
            [[x, y, 5.0] for x, y in xy],
            [[x, y, -5.0] for x, y in xy],
            physicsClientId=scene.client,
        )
        ground = np.array([h[0] == scene.ground_body for h in hits])
        z = np.array([h[3][2] for h in hits])
        model = world.ground.height_at(xy[:, 0], xy[:, 1])
        assert ground.sum() > 150  # the rest fall on objects
        assert np.abs(z[ground] - model[ground]).max() < 1e-3
        assert scene.label_lut[scene.ground_body] == GROUND
        for body in scene.object_bodies:
            assert scene.label_lut[body] in (4, 5, 6, 7, 8)
        # hits off the ground take the class of their body
        hit_bodies = np.array([h[0] for h in hits])
        labels = scene.labels_of(hit_bodies, xy)
        assert np.array_equal(labels[ground], world.ground.class_at(xy[ground, 0], xy[ground, 1]))
        assert np.all(labels[~ground] >= 4)
        assert scene.labels_of(np.array([-1, 10_000]), np.zeros((2, 2))).tolist() == [DROP, DROP]


def test_voxel_world_bodies_are_closed_meshes(tmp_path):
    """A world from a cloud: rays hit the voxel meshes where the voxels are."""
    box = np.stack(np.meshgrid(*[np.arange(-0.3, 0.3, 0.02)] * 3, indexing="ij"), -1)
    box = box.reshape(-1, 3) + [0.0, 0.0, 0.5]
    g = np.arange(-1.5, 1.5, 0.05)
    gx, gy = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    pts = np.concatenate([np.column_stack([gx, gy, np.zeros_like(gx)]), box])
    labels = np.concatenate([np.full(len(gx), 2), np.full(len(box), 5)])
    world = from_cloud(pts, labels, voxel_m=0.1)
    with BulletScene(world) as scene:
        hit = p.rayTest([-1.0, 0.05, 0.5], [1.0, 0.05, 0.5], physicsClientId=scene.client)[0]
        assert scene.label_lut[hit[0]] == 5
        assert hit[3][0] == pytest.approx(-0.3, abs=0.11)  # the voxel grid's outer face
        down = p.rayTest([0.05, 0.05, 3.0], [0.05, 0.05, -1.0], physicsClientId=scene.client)[0]
        assert scene.label_lut[down[0]] == 5 and down[3][2] == pytest.approx(0.8, abs=0.11)


def _settle(sim, x, y, yaw):
    z = float(sim.world.ground.height_at(x, y))
    sim.robot.reset((x, y), z, yaw)
    sim.step(0.5)


def test_robot_drives_a_commanded_arc_and_stops(sim):
    x0, y0, _ = sim.world.spawn_pose(0.5)
    _settle(sim, x0, y0, 0.0)
    start = sim.true_pose()
    yaw0 = math.atan2(start[1, 0], start[0, 0])
    v, w = 0.3, 0.4
    t_end = sim.time_s + 3.0
    while sim.time_s < t_end:  # commands at 10 Hz, like a planner's
        sim.set_velocity(v, w)
        sim.step(0.1)
    end = sim.true_pose()
    yaw1 = math.atan2(end[1, 0], end[0, 0])
    turned = (yaw1 - yaw0 + math.pi) % (2 * math.pi) - math.pi
    measured_v, measured_w = sim.robot.twist()
    assert measured_v == pytest.approx(v, rel=0.05)
    assert measured_w == pytest.approx(w, rel=0.05)
    # the arc: the chord between start and end fits a circle of radius v / w
    chord = np.linalg.norm(end[:2, 3] - start[:2, 3])
    radius = chord / (2 * math.sin(turned / 2))
    assert radius == pytest.approx(v / w, rel=0.08)
    assert turned == pytest.approx(w * 3.0, rel=0.1)  # less the acceleration ramp
    # no more commands: still moving within the timeout, stopped soon after
    sim.step(0.3)
    assert sim.robot.twist()[0] > 0.2
    sim.step(0.7)
    assert abs(sim.robot.twist()[0]) < 0.01 and abs(sim.robot.twist()[1]) < 0.01
    parked = sim.true_pose()[:3, 3].copy()
    sim.step(1.0)
    assert np.linalg.norm(sim.true_pose()[:3, 3] - parked) < 0.01


def test_commands_are_clamped_and_checked(sim):
    sim.set_velocity(5.0, -9.0)
    assert sim.robot.target == (1.0, -2.0)
    with pytest.raises(ValueError, match="finite"):
        sim.set_velocity(float("nan"), 0.0)
    sim.set_velocity(0.0, 0.0)
    with pytest.raises(ValueError):
        sim.step(-1.0)


def test_robot_stays_upright_driving_across_the_garden(sim):
    x0, y0, _ = sim.world.spawn_pose(0.5)
    _settle(sim, x0, y0, 1.0)
    for _ in range(40):
        sim.set_velocity(0.8, 0.5)
        sim.step(0.1)
    up = sim.true_pose()[:3, 2]
    assert up[2] > math.cos(math.radians(20))  # never tipped beyond 20 degrees
