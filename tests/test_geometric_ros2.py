"""The geometric labeller behind the ros2 service's cloud input (`ros2.label_field = none`): the
real KITTI scan as a PointCloud2 without a label field, in the sensor frame, placed by odometry
and an extrinsic, labelled in the world frame; with a label field, the labels win."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.common.config import SmanaConfig  # noqa: E402
from smana.common.geometric import GROUND, OBSTACLE, GeometricLabeller  # noqa: E402
from smana.services.ros2 import convert, rmw  # noqa: E402
from smana.services.ros2.bridge import CloudInput  # noqa: E402
from tests.support.ros2_sdk import pointcloud2  # noqa: E402

TYPES = rmw.RosTypes()
KITTI_SCAN = Path(__file__).parent / "data" / "kitti" / "000000.bin"
SENSOR_HEIGHT_M = 1.73


def ros_cloud(points, labels=None, frame="velodyne", t_s=0.5):
    return pointcloud2(TYPES, points, labels, frame, t_s)


def cloud_input(label_field):
    cfg = SmanaConfig.load(
        overrides=[
            f'ros2.label_field="{label_field}"',
            f"ros2.sensor_extrinsic=[0.0, 0.0, {SENSOR_HEIGHT_M}, 0.0, 0.0, 0.0]",
            "ros2.max_range_m=20.0",
        ]
    )
    labeller = GeometricLabeller.from_config(cfg).label if label_field == "none" else None
    ci = CloudInput(cfg, labeller)
    # the robot stands at (5, -2) on the ground, turned 30 degrees
    q = np.array(convert.yaw_quat(np.radians(30.0)))
    ci.poses.add(0.4, np.array([5.0, -2.0, 0.0]), q)
    ci.poses.add(0.6, np.array([5.0, -2.0, 0.0]), q)
    return ci


def test_an_unlabelled_kitti_cloud_is_labelled_in_the_world_frame():
    pts = np.fromfile(KITTI_SCAN, np.float32).reshape(-1, 4)[:, :3]
    ci = cloud_input("none")
    cloud = ci.convert(ros_cloud(pts))
    share = np.bincount(cloud.labels, minlength=3) / len(cloud.labels)
    road = np.abs(cloud.points[:, 2]) < 0.15  # the road is at z = 0 in the world now
    print(
        f"\nros2 input, KITTI 00/000000 within 20 m: {len(cloud.labels)} points, ground "
        f"{share[GROUND]:.3f} obstacle {share[OBSTACLE]:.3f}; road plane ground "
        f"{np.mean(cloud.labels[road] == GROUND):.3f}, higher than 1 m ground "
        f"{np.mean(cloud.labels[cloud.points[:, 2] > 1.0] == GROUND):.3f}"
    )
    np.testing.assert_allclose(cloud.sensor_position, [5.0, -2.0, SENSOR_HEIGHT_M], atol=1e-6)
    assert np.mean(cloud.labels[road] == GROUND) > 0.9  # the rest: cells beside cars, walls
    assert share[GROUND] > 0.5 and 0.1 < share[OBSTACLE] < 0.5
    # Higher than 1 m, a few flat tops read as ground: a roof or a canopy seen without anything
    # below it or beside it (no cell to be a step from).
    assert np.mean(cloud.labels[cloud.points[:, 2] > 1.0] == GROUND) < 0.05


def test_labels_win_when_the_cloud_has_them():
    pts = np.fromfile(KITTI_SCAN, np.float32).reshape(-1, 4)[:2000, :3]
    labels = np.full(len(pts), 7, np.uint32)
    cloud = cloud_input("label").convert(ros_cloud(pts, labels))
    assert len(cloud.labels) and np.all(cloud.labels == 7)
