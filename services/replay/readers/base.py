"""What every dataset reader yields and how it reports broken data.

A reader indexes its dataset when it is opened: structural problems (a missing folder, a pose
file that cannot be parsed or whose count does not match the scans) raise `DatasetError` at once,
naming the file and the problem. Problems that only spoil one scan (no label file, a truncated
binary, a label count that does not match the point count) skip that scan, and the reader lists
it in `skipped`, so a long recording with one bad file still replays. `strict=True` turns those
into errors too.
"""

from __future__ import annotations

import math
import sys
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# `label_field` value of a dataset read without labels: its points are labelled by geometry
# (common/geometric.py) in the world frame, with the `geometric` class table.
NO_LABELS = "none"
NO_LABELS_HINT = "--label-field none labels the points by geometry"


class DatasetError(ValueError):
    """A dataset is missing something or holds malformed data; the message names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


@dataclass(frozen=True)
class SkippedScan:
    name: str  # the scan's file name (or bag message), as the user would look for it
    reason: str


@dataclass
class Scan:
    """One scan in its sensor frame, with the sensor pose in the world frame.

    `labels` keep the dataset's own numbering; the class table maps them (`maps_from`). None: the
    scan is read without labels (`label_field = "none"`), the replay labels it by geometry.
    """

    index: int  # position in the replayed sequence (skipped scans leave no gap)
    name: str
    stamp_s: float
    points: np.ndarray  # f4[N, 3], sensor frame
    labels: np.ndarray | None  # integer [N], dataset ids; None = unlabelled
    pose: np.ndarray  # f8[4, 4], sensor -> world
    confidences: np.ndarray | None = None  # f4[N] in [0, 1], None = all 1

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


@dataclass
class DatasetInfo:
    format: str
    path: str
    n_scans: int
    rate_hz: float
    class_table: str
    sensor: str  # "lidar" or "camera": which robot topic the scans belong on
    skipped: list[SkippedScan] = field(default_factory=list)


class DatasetReader(ABC):
    """A sequence of `Scan`s. Subclasses index in `__init__` and read lazily in `scan(i)`."""

    format: str = ""
    default_class_table: str = ""
    sensor: str = "lidar"
    sequential: bool = False  # True: scan(i) is cheap only going forward (a stream)
    labelled: bool = True  # False: scans come without labels (label_field "none")

    def __init__(self, path: str | Path, *, strict: bool = False):
        self.path = Path(path)
        self.strict = strict
        self.skipped: list[SkippedScan] = []
        if not self.path.exists():
            raise DatasetError(self.path, "does not exist")

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def scan(self, i: int) -> Scan:
        """Read the i-th (not skipped) scan."""

    @property
    @abstractmethod
    def rate_hz(self) -> float: ...

    def __iter__(self) -> Iterator[Scan]:
        for i in range(len(self)):
            yield self.scan(i)

    def close(self) -> None:  # noqa: B027 (optional hook, not abstract)
        """Release open files; readers with nothing open keep this no-op."""

    def __enter__(self) -> DatasetReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def info(self) -> DatasetInfo:
        return DatasetInfo(
            self.format,
            str(self.path),
            len(self),
            self.rate_hz,
            self.class_table,
            self.sensor,
            list(self.skipped),
        )

    @property
    def class_table(self) -> str:
        """The table the scans' labels belong to: the dataset's own, or `geometric` unlabelled."""
        from smana.common.geometric import TABLE

        return self.default_class_table if self.labelled else TABLE

    def skip(self, name: str, reason: str) -> None:
        """Record a scan that cannot be replayed (or raise, in strict mode)."""
        if self.strict:
            raise DatasetError(name, reason)
        self.skipped.append(SkippedScan(name, reason))

    def report_skipped(self, stream=sys.stderr, limit: int = 20) -> None:
        if not self.skipped:
            return
        print(f"{self.path}: skipping {len(self.skipped)} scan(s):", file=stream)
        for s in self.skipped[:limit]:
            print(f"  {s.name}: {s.reason}", file=stream)
        if len(self.skipped) > limit:
            print(f"  ... and {len(self.skipped) - limit} more", file=stream)


# -- KITTI-style files shared by the SemanticKITTI and RELLIS-3D layouts ------------------------


def read_kitti_poses(path: Path) -> np.ndarray:
    """`poses.txt`: 12 floats a line, a row-major 3x4 matrix -> f8[K, 4, 4]."""
    if not path.is_file():
        raise DatasetError(path, "pose file is missing")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(path, f"line {n}: not a list of numbers") from None
        if len(vals) != 12:
            raise DatasetError(path, f"line {n}: expected 12 numbers (3x4 matrix), got {len(vals)}")
        if not all(math.isfinite(v) for v in vals):
            raise DatasetError(path, f"line {n}: non-finite value")
        rows.append(vals)
    if not rows:
        raise DatasetError(path, "pose file is empty")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = np.asarray(rows).reshape(-1, 3, 4)
    return poses


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """`calib.txt`: `KEY: 12 floats` lines -> {KEY: f8[4, 4]} (3x4 completed with 0 0 0 1)."""
    if not path.is_file():
        raise DatasetError(path, "calibration file is missing")
    calib = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DatasetError(path, f"line {n}: expected 'KEY: 12 numbers'")
        try:
            vals = [float(v) for v in rest.split()]
        except ValueError:
            raise DatasetError(path, f"line {n} ({key.strip()}): not a list of numbers") from None
        if len(vals) != 12:
            raise DatasetError(path, f"line {n} ({key.strip()}): expected 12 numbers")
        m = np.eye(4)
        m[:3, :] = np.asarray(vals).reshape(3, 4)
        calib[key.strip()] = m
    return calib


def camera_to_lidar_poses(poses_cam: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """KITTI poses are of the left camera; the LiDAR's are inv(Tr) @ P @ Tr (Tr: LiDAR->camera)."""
    return np.linalg.inv(tr) @ poses_cam @ tr


def read_times(path: Path, n: int) -> np.ndarray | None:
    """`times.txt` (one stamp in seconds a line) if present; must match the scan count."""
    if not path.is_file():
        return None
    try:
        times = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except ValueError as exc:
        raise DatasetError(path, f"not a column of numbers ({exc})") from None
    if times.shape != (n,):
        raise DatasetError(path, f"{times.size} stamps for {n} scans")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
        raise DatasetError(path, "stamps must be finite and non-decreasing")
    return times


def check_poses(poses: np.ndarray, path: Path) -> None:
    """Rotation blocks must be rotations: a transposed or mangled file shows up here."""
    r = poses[:, :3, :3]
    err = np.abs(r @ np.transpose(r, (0, 2, 1)) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-3) | (np.abs(np.linalg.det(r) - 1) > 1e-3))
    if bad.size:
        raise DatasetError(path, f"pose {int(bad[0])} is not a rigid transform (bad rotation)")


def rate_from_stamps(stamps: np.ndarray, default: float) -> float:
    if stamps.size < 2:
        return default
    dt = float(np.median(np.diff(stamps)))
    return 1.0 / dt if dt > 0 else default
