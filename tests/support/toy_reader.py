"""A toy dataset reader from outside smana, for the "adding a dataset reader" recipe
(tests/test_replay_toy_reader.py registers it and replays it into a mapper).

A toy dataset is a folder with `toy.txt`: one line per scan, `stamp_s x y yaw` (the sensor's
pose; it sits 0.8 m above the ground). Each scan sees a 4 x 4 m patch of terrain (class 2 of the
garden3drms table) and a hedge (class 4) 2 m ahead, as points in the sensor frame.
"""

from __future__ import annotations

import math

import numpy as np

from smana.services.replay.readers import DatasetError, DatasetReader, Scan

SENSOR_HEIGHT_M = 0.8
TERRAIN, HEDGE = 2, 4


def write_toy_dataset(folder, poses) -> None:
    """Write `toy.txt` for a list of (stamp_s, x, y, yaw)."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = [" ".join(f"{v:g}" for v in p) for p in poses]
    (folder / "toy.txt").write_text("\n".join(lines) + "\n")


class ToyReader(DatasetReader):
    format = "toy"
    default_class_table = "garden3drms"
    sensor = "lidar"

    def __init__(self, path, *, strict: bool = False):
        super().__init__(path, strict=strict)
        index = self.path / "toy.txt"
        if not index.is_file():
            raise DatasetError(index, "missing: a toy dataset is a folder with toy.txt")
        try:
            self.poses = np.loadtxt(index, ndmin=2)
        except ValueError as exc:
            raise DatasetError(index, f"not a table of numbers ({exc})") from None
        if self.poses.shape[1] != 4:
            raise DatasetError(index, f"{self.poses.shape[1]} columns, expected stamp_s x y yaw")

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def rate_hz(self) -> float:
        stamps = self.poses[:, 0]
        return 1.0 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 10.0

    def scan(self, i: int) -> Scan:
        stamp, x, y, yaw = self.poses[i]
        g = np.arange(0.1, 4.0, 0.2)
        gx, gy = np.meshgrid(g, g - 2.0, indexing="ij")
        ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -SENSOR_HEIGHT_M)], axis=1)
        hy, hz = np.meshgrid(np.arange(-1.0, 1.0, 0.1), np.arange(0.0, 1.0, 0.1), indexing="ij")
        hedge = np.stack(
            [np.full(hy.size, 2.0), hy.ravel(), hz.ravel() - SENSOR_HEIGHT_M + 0.05], axis=1
        )
        pose = np.eye(4)
        c, s = math.cos(yaw), math.sin(yaw)
        pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        pose[:3, 3] = [x, y, SENSOR_HEIGHT_M]
        return Scan(
            index=i,
            name=f"toy line {i + 1}",
            stamp_s=float(stamp),
            points=np.concatenate([ground, hedge]).astype(np.float32),
            labels=np.concatenate([np.full(len(ground), TERRAIN), np.full(len(hedge), HEDGE)]),
            pose=pose,
        )
