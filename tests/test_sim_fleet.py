"""Several robots in one simulated world: they spawn apart on free ground, see each other (depth,
occlusion) without mapping each other, collide as rigid bodies with each contact episode counted
once, and keep the single robot's random streams for member 0; the service, in-process on the
fake zenoh, publishes each member on its own keys, drives each on its own cmd_vel and reports the
fleet in its status and in `<run_dir>/sim.json`."""

from __future__ import annotations

import json
import math
import signal

import msgpack
import numpy as np
import pybullet as p
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config.fleet import FleetConfig
from smana.common.config.sim import CameraConfig, LidarConfig, SimConfig
from smana.common.messages import (
    MapDelta,
    Pose,
    SemanticCloud,
    ServiceStatus,
    VelocityCommand,
    decode,
    encode,
)
from smana.common.query import request
from smana.services.sim.finishing import finished, make_worker
from smana.services.sim.scene import transform_points
from smana.services.sim.simulation import Simulation, place_members
from smana.services.sim.worlds import build_world
from smana.services.sim.worlds.garden import GardenConfig
from tests.conftest import wait_for
from tests.test_sim_service import SMALL, Collector

CFG = SimConfig(
    noise="low",
    pose_noise_xy_m=0.05,
    pose_noise_yaw_rad=0.01,
    camera=CameraConfig(width=64, height=64),
    lidar=LidarConfig(channels=16, columns=256),
    garden=GardenConfig(size_m=8.0),
)


@pytest.fixture(scope="module")
def world():
    return build_world(CFG, ClassTable.load("garden3drms"))


def _spawn(world) -> tuple[float, float]:
    x, y, _ = world.spawn_pose(CFG.robot.radius_m + 0.05)
    return x, y


def test_members_spawn_apart_on_free_ground(world):
    spacing = 1.2
    with Simulation(CFG, world=world, robots=["r1", "r2", "r3"]) as sim:
        assert sim.robots == ["r1", "r2", "r3"]
        xy = np.array([sim.true_pose(i)[:2, 3] for i in range(3)])
        # the first where a single robot spawns (the settling moves it by a hair)
        assert np.allclose(xy[0], _spawn(world), atol=0.02)
        free = world.traversability(CFG.robot.radius_m + 0.05)
        for i in range(3):
            assert free.at(*xy[i])
            for j in range(i):
                assert np.hypot(*(xy[i] - xy[j])) >= spacing - 0.03
        # nothing touches: not each other, not the world's objects
        assert sim.robot_contacts() == {"r1-r2": 0, "r1-r3": 0, "r2-r3": 0}
        c = sim.scene.client
        for m in sim.members:
            for body in sim.scene.object_bodies:
                assert not p.getContactPoints(m.robot.body, body, physicsClientId=c)
    # the placement against an obvious reference: every pair of free cells far enough apart
    spots = place_members(world, _spawn(world), 3, spacing, CFG.robot.radius_m + 0.05)
    assert spots == place_members(world, _spawn(world), 3, spacing, CFG.robot.radius_m + 0.05)
    d = [math.dist(spots[0], s) for s in spots[1:]]
    assert max(d) < spacing + 0.3  # the nearest places that fit, not just any
    with pytest.raises(ValueError, match="cannot place 40 robots"):
        place_members(world, _spawn(world), 40, 3.0, CFG.robot.radius_m + 0.05)


def _run(sim: Simulation, member) -> tuple[list, list]:
    """Drive a member, then its published poses and camera / LiDAR clouds."""
    poses, clouds = [], []
    for _ in range(3):
        sim.set_velocity(0.3, 0.2, member)
        sim.step(0.25)
        poses.append(sim.published_pose(member))
        f = sim.camera_frame(member=member)
        clouds.append((f.seq, f.points, f.labels, f.confidences))
        s = sim.lidar_scan(member=member)
        clouds.append((s.seq, s.points, s.labels))
    return poses, clouds


def test_member_zero_keeps_the_single_robots_streams(world):
    with Simulation(CFG, world=world) as alone:
        ref = _run(alone, 0)
    with Simulation(CFG, world=world, robots=["r1"]) as fleet_of_one:
        got = _run(fleet_of_one, "r1")
    for a, b in zip(ref[0], got[0], strict=True):
        assert np.array_equal(a, b)
    for a, b in zip(ref[1], got[1], strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    # in a real fleet, member 0 draws today's pose noise; the others draw their own
    with Simulation(CFG, world=world, robots=["a", "b"]) as sim:
        offsets = [
            [sim.published_pose(i)[:2, 3] - sim.true_pose(i)[:2, 3] for _ in range(3)]
            for i in range(2)
        ]
    with Simulation(CFG, world=world) as alone:
        single = [alone.published_pose()[:2, 3] - alone.true_pose()[:2, 3] for _ in range(3)]
    assert np.allclose(offsets[0], single, atol=1e-12)
    assert not np.allclose(offsets[1], single)


def test_a_member_sees_another_without_mapping_it(world):
    x0, y0 = _spawn(world)
    fleet = FleetConfig(robots=["a", "b"], start_poses=[[x0, y0, 0.0], [x0 + 2.0, y0, math.pi]])
    with Simulation(CFG, world=world, fleet=fleet) as sim:
        seen = sim.camera_frame(member="a")
        scan = sim.lidar_scan(member="a")
        b_pose = sim.true_pose("b")
        a = sim.member("a")
        assert a.member_px > 20 and scan.member_hits > 5
        # move b out of the way (behind a), and look again from the same pose
        gz = float(world.ground.height_at(x0 - 3.0, y0))
        sim.member("b").robot.reset((x0 - 3.0, y0), gz, 0.0)
        sim.step(0.25)
        assert np.allclose(
            sim.true_pose("a"), seen.true_world_from_sensor @ _inv_mount(), atol=1e-3
        )
        empty = sim.camera_frame(member="a")
        empty_scan = sim.lidar_scan(member="a")
    # the depth image shows b: nearer than the ground behind it
    assert (seen.depth_m < empty.depth_m - 0.2).sum() > 20
    # no point of the clouds lies in b's body (points within its footprint are ground)
    hx, hy, _ = CFG.robot.chassis_half_extents
    half_y = CFG.robot.track_m / 2 + CFG.robot.wheel_radius_m
    for pts in (seen.points, scan.points):
        q = transform_points(pts, np.linalg.inv(b_pose))
        body = (np.abs(q[:, 0]) < hx + 0.05) & (np.abs(q[:, 1]) < half_y + 0.03)
        assert not np.any(body & (q[:, 2] > -CFG.robot.base_height_m + 0.04))

    # b hides the ground behind it: fewer points there than with b away
    def behind(pts):
        return int(
            np.sum((pts[:, 0] > x0 + 2.4) & (pts[:, 0] < x0 + 5.0) & (np.abs(pts[:, 1] - y0) < 0.3))
        )

    assert behind(seen.points) < 0.85 * behind(empty.points)
    assert behind(scan.points) < 0.85 * behind(empty_scan.points)


def _inv_mount() -> np.ndarray:
    return np.linalg.inv(CFG.camera.mount_matrix())


def test_members_collide_and_each_contact_counts_once(world):
    x0, y0 = _spawn(world)
    fleet = FleetConfig(
        robots=["a", "b"], start_poses=[[x0 - 0.6, y0, 0.0], [x0 + 0.6, y0, math.pi]]
    )

    def drive(sim, v, seconds):
        for _ in range(int(seconds / 0.1)):
            sim.set_velocity(v, 0.0, "a")
            sim.set_velocity(v, 0.0, "b")
            sim.step(0.1)

    with Simulation(CFG, world=world, fleet=fleet) as sim:
        assert sim.robot_contacts() == {"a-b": 0}
        drive(sim, 0.5, 2.5)  # head on, and pushing on
        hx = CFG.robot.chassis_half_extents[0]
        assert sim.robot_contacts() == {"a-b": 1}
        assert sim.min_separation_m()["a-b"] >= 2 * hx - 0.03  # not through each other
        assert [pair for _, pair in sim.take_contact_events()] == ["a-b"]
        drive(sim, -0.5, 1.5)  # apart
        gap = np.hypot(*(sim.true_pose("a")[:2, 3] - sim.true_pose("b")[:2, 3]))
        assert gap > 2 * hx + 0.3 and sim.robot_contacts() == {"a-b": 1}
        drive(sim, 0.5, 2.5)  # and once more: a second episode
        assert sim.robot_contacts() == {"a-b": 2}
        assert len(sim.take_contact_events()) == 1 and sim.take_contact_events() == []


def test_fleet_service_publishes_each_member_on_its_keys(fake_stack, tmp_path):
    stack = fake_stack
    run_dir = tmp_path / "run"
    proc = stack.service(
        "sim",
        *SMALL,
        "--camera",
        "32x32",
        "--camera-rate",
        "4",
        "--robots",
        "2",
        "--robot",  # what the supervisor passes (the fake stack's `--robot test` comes first)
        "fleet",
        "--run-dir",
        str(run_dir),
    )
    stack.wait_alive("sim", robot="fleet")
    c = Collector(stack.session)
    for r in ("r1", "r2"):
        c.add(keys.pose_truth(r), lambda b: decode(b, Pose))
        c.add(keys.cloud(r), lambda b: decode(b, SemanticCloud))
        c.add(keys.clock(r), msgpack.unpackb)

    def status() -> ServiceStatus:
        st = request(stack.session, keys.status("fleet", "sim"), timeout_s=5)
        assert isinstance(st, ServiceStatus)
        return st

    try:
        assert wait_for(
            lambda: (
                all(len(c.get(keys.cloud(r))) >= 2 for r in ("r1", "r2"))
                and all(c.get(keys.clock(r)) for r in ("r1", "r2"))
            ),
            30.0,
        )
        for r in ("r1", "r2"):
            seqs = [m.seq for m in c.get(keys.cloud(r))]
            assert seqs == sorted(seqs) and seqs[0] >= 1  # each member numbers its own
            assert len(c.get(keys.cloud(r))[-1].points) > 50
        start = {r: c.get(keys.pose_truth(r))[-1] for r in ("r1", "r2")}
        assert np.hypot(*(start["r1"].position[:2] - start["r2"].position[:2])) >= 1.15

        # r2 drives, r1 stands still
        pub = stack.publisher(keys.cmd_vel("r2"))
        i = 0

        def r2_moved() -> bool:
            nonlocal i
            i += 1
            pub.put(encode(VelocityCommand(stamp_s=0.0, seq=i, linear_mps=0.4, source="test")))
            now = c.get(keys.pose_truth("r2"))[-1]
            return np.linalg.norm(now.position[:2] - start["r2"].position[:2]) > 0.2

        assert wait_for(r2_moved, 30.0, 0.1)
        assert wait_for(
            lambda: c.get(keys.pose_truth("r1"))[-1].stamp_s > start["r2"].stamp_s + 0.5
        )
        r1 = c.get(keys.pose_truth("r1"))[-1]
        assert np.linalg.norm(r1.position[:2] - start["r1"].position[:2]) < 0.01
        pub.undeclare()

        st = status()
        d = st.details
        assert set(d["robots"]) == {"r1", "r2"} and st.books_add_up(), st
        assert d["robots"]["r2"]["commands"] == i and d["robots"]["r1"]["commands"] == 0
        assert d["robots"]["r1"]["camera_frames"] >= 2 and d["robots"]["r2"]["camera_frames"] >= 2
        assert d["robot_contacts"] == {"r1-r2": 0} and d["robot_contacts_total"] == 0
        assert d["min_separation_m"]["r1-r2"] >= 1.1
        assert d["pose_xy_yaw"] == d["robots"]["r1"]["pose_xy_yaw"]  # the old fields: member 0
    finally:
        c.close()
    assert stack.stop(proc, signal.SIGINT) == 0
    summary = json.loads((run_dir / "sim.json").read_text())
    assert summary["robots"] == ["r1", "r2"]
    assert summary["robot_contacts"] == {"r1-r2": 0} and summary["robot_contacts_total"] == 0
    assert summary["min_separation_m"]["r1-r2"] >= 1.1 and summary["sim_time_s"] > 0


@pytest.mark.parametrize("kind", ["thread", "process"])
def test_each_members_frames_finish_with_its_own_streams(world, kind):
    """A camera worker finishes each member's frames with that member's random streams: the
    bytes are those of finishing in line."""
    with (
        Simulation(CFG, world=world, robots=["a", "b"]) as inline,
        Simulation(CFG, world=world, robots=["a", "b"]) as worked,
    ):
        executor, finish = make_worker(kind, CFG, worked.frame_finisher, world.classes.colour_lut)
        try:
            order = ["a", "b", "b", "a"]
            want = [finished(inline.camera_frame(member=m), images=False).cloud for m in order]
            got = [
                executor.submit(finish, worked.capture_camera(member=m)).result(timeout=60)
                for m in order
            ]
        finally:
            executor.shutdown(wait=True)
    assert [g.cloud for g in got] == want
    assert want[0] != want[1]  # the members draw different labels / confidences


def test_fleet_lockstep_waits_for_every_members_map_delta(fake_stack):
    stack = fake_stack
    proc = stack.service(
        "sim",
        *SMALL,
        "--camera",
        "32x32",
        "--camera-rate",
        "10",
        "--rtf",
        "3",
        "--lockstep",
        "--set",
        "sim.lockstep_timeout_s=0.5",
        "--robots",
        "2",
        "--robot",
        "fleet",
    )
    stack.wait_alive("sim", robot="fleet")
    c = Collector(stack.session)
    acks = {}

    def acknowledge(r: str) -> None:
        delta_pub = stack.session.declare_publisher(keys.map_delta(r))

        def ack(sample):
            cloud = decode(sample.payload.to_bytes(), SemanticCloud)
            delta_pub.put(encode(MapDelta(cloud_seq=cloud.seq)))

        acks[r] = (delta_pub, stack.session.declare_subscriber(keys.cloud(r), ack))

    def timeouts() -> int:
        st = request(stack.session, keys.status("fleet", "sim"), timeout_s=5)
        return int(st.details["lockstep_timeouts"])

    for r in ("r1", "r2"):
        c.add(keys.cloud(r), lambda b: decode(b, SemanticCloud))
    try:
        # only r1's mapper answers: the world still waits for r2's, up to each timeout
        acknowledge("r1")
        assert wait_for(lambda: timeouts() >= 2, 30.0)
        # both answer: clouds flow for both members, with no more timeouts (one may be running)
        acknowledge("r2")
        before, t_before = {r: len(c.get(keys.cloud(r))) for r in ("r1", "r2")}, timeouts()
        assert wait_for(
            lambda: all(len(c.get(keys.cloud(r))) - before[r] >= 6 for r in ("r1", "r2")), 60.0
        )
        assert timeouts() - t_before <= 1
    finally:
        c.close()
        for pub, sub in acks.values():
            sub.undeclare()
            pub.undeclare()
    assert stack.stop(proc, signal.SIGINT) == 0


def test_robots_flag_makes_a_fleet_under_its_name(monkeypatch):
    from smana.services.sim import __main__ as sim_main
    from smana.services.sim import service

    seen = []
    monkeypatch.setattr(service, "main", lambda cfg: seen.append(cfg) or 0)
    assert sim_main.cli(["--robots", "3"]) == 0
    assert seen[-1].fleet.robots == ["r1", "r2", "r3"] and seen[-1].general.robot == "fleet"
    assert sim_main.cli(["--robots", "2", "--robot", "f2"]) == 0
    assert seen[-1].fleet.robots == ["r1", "r2"] and seen[-1].general.robot == "f2"
    assert sim_main.cli([]) == 0
    assert seen[-1].fleet.robots == [] and seen[-1].general.robot == "r1"


def test_members_start_with_room_the_navigation_graph_leaves_open():
    """`fleet.member_clearance_m`: in the 12 m garden of seed 8 (the fleet experiment's), with
    the first member starting at (3.2, -4.3), the second once spawned at (4.4, -4.3), 0.47 m from
    a hedge in a pocket that the navigation graph's safety zone closed, and never moved. Now every
    member has the member clearance and is joined to the first through passages that wide; with
    the robot's own clearance the old spot comes back."""
    from scipy import ndimage

    from smana.common.config import SmanaConfig

    cfg = SmanaConfig.load(None, ["sim.seed=8", "sim.garden.size_m=12.0"]).sim
    world = build_world(cfg, ClassTable.load("garden3drms"))
    first = (3.2, -4.3)
    room = FleetConfig().member_clearance_m
    spots = place_members(world, first, 3, 1.2, max(cfg.robot.radius_m + 0.05, room))
    trav = world.traversability(room)
    comps, _ = ndimage.label(trav.data)
    assert all(trav.at(*s) for s in spots)
    assert len({int(comps[trav.index_of(*s)]) for s in spots}) == 1
    assert all(math.dist(s, (4.4, -4.3)) > 0.5 for s in spots)
    old = place_members(world, first, 3, 1.2, cfg.robot.radius_m + 0.05)
    assert any(math.dist(s, (4.4, -4.3)) < 0.1 for s in old)  # the spot that never moved
