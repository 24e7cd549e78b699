"""The simulated robot: a small differential-drive base with physics, driven by (v, w) commands.

Built from primitives rather than loaded from `husky/husky.urdf`: TinyRenderer draws every
triangle of every body in each camera frame, and the Husky's meshes alone cost ~30 ms per
640x640 frame, a third of the camera budget. The base is sized like the paper's Wifibot-class
robot: two driven wheels on one axle, a free caster front and back (frictionless spheres), so
the commanded arc is the one driven (a four-wheel skid-steer slips by an amount that depends on
the ground). Wheels are velocity-controlled by Bullet's motors with a torque limit; commands are
clamped and rate limited, and the base stops when no command has arrived for `cmd_timeout_s`
(simulated time). Parameters: `[sim.robot]` (`RobotConfig`).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from smana.common.config.sim import RobotConfig
from smana.common.messages import matrix_to_quat, quat_to_matrix


class DiffDriveRobot:
    """A differential-drive base in a PyBullet client.

    `command(v, w, now_s)` sets the target twist; `update(now_s, dt_s)` must be called before each
    physics step (it applies the timeout and the rate limits); `pose()` and `matrix()` give the
    true pose of the base frame (chassis centre, x forward, z up).
    """

    def __init__(
        self,
        client: int,
        config: RobotConfig | None = None,
        *,
        xy: tuple[float, float] = (0.0, 0.0),
        ground_z: float = 0.0,
        yaw: float = 0.0,
    ):
        self.client = client
        self.config = s = config or RobotConfig()
        hx, hy, hz = s.chassis_half_extents
        axle_z = s.wheel_radius_m - s.base_height_m  # axle height in the base frame
        caster_z = s.caster_radius_m - s.base_height_m + 0.005  # a hair above the ground
        c = client
        chassis = p.createCollisionShape(p.GEOM_BOX, halfExtents=[hx, hy, hz], physicsClientId=c)
        chassis_vis = p.createVisualShape(
            p.GEOM_BOX, halfExtents=[hx, hy, hz], rgbaColor=list(s.colour), physicsClientId=c
        )
        # cylinders are along z: turn the wheel shapes so their axis is the y (axle) axis
        axle_rot = p.getQuaternionFromEuler([math.pi / 2, 0, 0])
        no_rot = [0, 0, 0, 1]
        # A wheel collides as a ball: it touches the ground on its mid-plane whatever the roll,
        # whereas a cylinder rides on its inner rim and shrinks the effective track by ~10 %.
        wheel = p.createCollisionShape(p.GEOM_SPHERE, radius=s.wheel_radius_m, physicsClientId=c)
        wheel_vis = p.createVisualShape(
            p.GEOM_CYLINDER,
            radius=s.wheel_radius_m,
            length=s.wheel_width_m,
            visualFrameOrientation=axle_rot,
            rgbaColor=[0.1, 0.1, 0.1, 1],
            physicsClientId=c,
        )
        caster = p.createCollisionShape(p.GEOM_SPHERE, radius=s.caster_radius_m, physicsClientId=c)
        self.body = p.createMultiBody(
            baseMass=s.chassis_mass_kg,
            baseCollisionShapeIndex=chassis,
            baseVisualShapeIndex=chassis_vis,
            basePosition=[xy[0], xy[1], ground_z + s.base_height_m + 0.01],
            baseOrientation=p.getQuaternionFromEuler([0, 0, yaw]),
            linkMasses=[s.wheel_mass_kg, s.wheel_mass_kg, 0.2, 0.2],
            linkCollisionShapeIndices=[wheel, wheel, caster, caster],
            linkVisualShapeIndices=[wheel_vis, wheel_vis, -1, -1],
            linkPositions=[
                [0, s.track_m / 2, axle_z],
                [0, -s.track_m / 2, axle_z],
                [s.caster_offset_m, 0, caster_z],
                [-s.caster_offset_m, 0, caster_z],
            ],
            linkOrientations=[no_rot] * 4,
            linkInertialFramePositions=[[0, 0, 0]] * 4,
            linkInertialFrameOrientations=[no_rot] * 4,
            linkParentIndices=[0, 0, 0, 0],
            linkJointTypes=[p.JOINT_REVOLUTE, p.JOINT_REVOLUTE, p.JOINT_FIXED, p.JOINT_FIXED],
            linkJointAxis=[[0, 1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1]],
            physicsClientId=c,
        )
        self.left_wheel, self.right_wheel = 0, 1
        for link in (self.left_wheel, self.right_wheel):
            p.changeDynamics(
                self.body,
                link,
                lateralFriction=1.2,
                rollingFriction=0.0,
                spinningFriction=0.0,
                physicsClientId=c,
            )
        for link in (-1, 2, 3):  # chassis and casters slide: only the wheels grip
            p.changeDynamics(
                self.body,
                link,
                lateralFriction=0.0,
                rollingFriction=0.0,
                spinningFriction=0.0,
                physicsClientId=c,
            )
        self.target = (0.0, 0.0)  # commanded (v, w), clamped
        self.applied = (0.0, 0.0)  # after rate limits
        self.last_command_s = -math.inf
        self.timed_out = True

    def command(self, linear_mps: float, angular_radps: float, now_s: float) -> None:
        """Set the target twist (clamped to the config's limits). Non-finite values are refused."""
        if not (math.isfinite(linear_mps) and math.isfinite(angular_radps)):
            raise ValueError(
                f"velocity command must be finite, got ({linear_mps}, {angular_radps})"
            )
        s = self.config
        v = min(max(float(linear_mps), -s.max_linear_mps), s.max_linear_mps)
        w = min(max(float(angular_radps), -s.max_angular_radps), s.max_angular_radps)
        self.target = (v, w)
        self.last_command_s = now_s
        self.timed_out = False

    def update(self, now_s: float, dt_s: float) -> None:
        """Apply the command timeout and rate limits, then set the wheel motors."""
        s = self.config
        if now_s - self.last_command_s > s.cmd_timeout_s:
            self.target = (0.0, 0.0)
            self.timed_out = True
        v0, w0 = self.applied
        dv = s.max_linear_accel_mps2 * dt_s
        dw = s.max_angular_accel_radps2 * dt_s
        v = v0 + min(max(self.target[0] - v0, -dv), dv)
        w = w0 + min(max(self.target[1] - w0, -dw), dw)
        self.applied = (v, w)
        half = s.track_m / 2
        left = (v - w * half) / s.wheel_radius_m
        right = (v + w * half) / s.wheel_radius_m
        p.setJointMotorControlArray(
            self.body,
            [self.left_wheel, self.right_wheel],
            p.VELOCITY_CONTROL,
            targetVelocities=[left, right],
            forces=[s.max_wheel_torque_nm] * 2,
            physicsClientId=self.client,
        )

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(position f8[3], orientation xyzw f8[4]) of the base frame, world frame."""
        pos, orn = p.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        return np.array(pos), np.array(orn)

    def matrix(self) -> np.ndarray:
        pos, orn = self.pose()
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(orn)
        m[:3, 3] = pos
        return m

    def yaw(self) -> float:
        r = self.matrix()[:3, :3]
        return math.atan2(r[1, 0], r[0, 0])

    def twist(self) -> tuple[float, float]:
        """Measured (forward speed, yaw rate) in the body frame."""
        lin, ang = p.getBaseVelocity(self.body, physicsClientId=self.client)
        r = self.matrix()[:3, :3]
        return float(r[:, 0] @ np.array(lin)), float(np.array(ang)[2])

    def reset(self, xy: tuple[float, float], ground_z: float, yaw: float) -> None:
        pos = [xy[0], xy[1], ground_z + self.config.base_height_m + 0.01]
        orn = matrix_to_quat(_rot_z(yaw))
        p.resetBasePositionAndOrientation(self.body, pos, orn, physicsClientId=self.client)
        p.resetBaseVelocity(self.body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)
        self.target = self.applied = (0.0, 0.0)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
