"""A folder of labelled PLY or NPZ scans with a pose file: the format for data from anywhere else.

Scans are read in file-name order. An NPZ holds `points` (N x 3), `labels` (N, integers) and
optionally `confidences` (N), `pose` (4 x 4, sensor -> world) and `stamp_s`. A PLY (ASCII or
binary) holds a `vertex` element with float x, y, z, an integer label property (`label` by
default) and optionally a float `confidence`. Poses come from `poses.txt`, one line per scan, as
12 numbers (KITTI row-major 3 x 4) or 8 (TUM: stamp x y z qx qy qz qw); an NPZ's own `pose` wins.
Without stamps from TUM poses, NPZ files or `times.txt`, scans are spaced at `rate_hz`.
With `label_field="none"` no labels are read (a PLY needs no label property, an NPZ no `labels`):
the replay labels the points by geometry.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from smana.common import ply_files
from smana.common.messages import quat_to_matrix

from .base import (
    NO_LABELS,
    NO_LABELS_HINT,
    DatasetError,
    DatasetReader,
    Scan,
    check_poses,
    rate_from_stamps,
    read_times,
)


def write_ply(path: Path, points, labels, confidences=None, binary: bool = True) -> None:
    """Write a labelled PLY (the format this reader takes), e.g. to export scans from elsewhere."""
    points = np.asarray(points, np.float32)
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "label": np.asarray(labels)}
    if confidences is not None:
        columns["confidence"] = np.asarray(confidences, np.float32)
    ply_files.write_ply(path, columns, binary=binary)


def _npz_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Array shapes and dtypes of an NPZ without loading the data."""
    out = {}
    try:
        with zipfile.ZipFile(path) as z:
            for name in z.namelist():
                if not name.endswith(".npy"):
                    continue
                with z.open(name) as f:
                    major, _ = np.lib.format.read_magic(f)
                    read_header = (
                        np.lib.format.read_array_header_1_0
                        if major == 1
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read_header(f)
                out[name[:-4]] = (shape, dtype)
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        raise DatasetError(path, f"not a readable NPZ ({exc})") from None
    return out


def read_pose_file(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """`poses.txt` with KITTI (12) or TUM (8) columns -> (f8[K,4,4], stamps or None)."""
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        raise DatasetError(path, f"not a table of numbers ({exc})") from None
    if table.size == 0:
        raise DatasetError(path, "pose file is empty")
    if not np.all(np.isfinite(table)):
        raise DatasetError(path, "non-finite value")
    poses = np.tile(np.eye(4), (table.shape[0], 1, 1))
    if table.shape[1] == 12:
        poses[:, :3, :] = table.reshape(-1, 3, 4)
        return poses, None
    if table.shape[1] == 8:
        q = table[:, 4:8]
        if np.any(np.linalg.norm(q, axis=1) < 1e-6):
            raise DatasetError(path, "zero-norm quaternion")
        poses[:, :3, :3] = [quat_to_matrix(qi) for qi in q]
        poses[:, :3, 3] = table[:, 1:4]
        return poses, table[:, 0].copy()
    raise DatasetError(
        path, f"{table.shape[1]} columns: expected 12 (KITTI 3x4) or 8 (TUM t x y z qx qy qz qw)"
    )


class FolderReader(DatasetReader):
    format = "folder"
    default_class_table = "garden3drms"

    def __init__(
        self, path, *, label_field: str = "label", rate_hz: float = 10.0, strict: bool = False
    ):
        super().__init__(path, strict=strict)
        if not self.path.is_dir():
            raise DatasetError(self.path, "expected a folder of .ply or .npz scans")
        self.labelled = label_field != NO_LABELS
        self.label_field = label_field if self.labelled else None
        plys, npzs = sorted(self.path.glob("*.ply")), sorted(self.path.glob("*.npz"))
        if plys and npzs:
            raise DatasetError(self.path, "holds both .ply and .npz scans; keep one kind")
        files = plys or npzs
        if not files:
            raise DatasetError(self.path, "no .ply or .npz scans")
        pose_path = self.path / "poses.txt"
        if plys and not pose_path.is_file():
            raise DatasetError(pose_path, "missing (PLY scans carry no pose)")
        poses, stamps = (None, None)
        if pose_path.is_file():
            poses, stamps = read_pose_file(pose_path)
            if len(poses) != len(files):
                raise DatasetError(pose_path, f"{len(poses)} poses for {len(files)} scans")
            check_poses(poses, pose_path)
        if stamps is None:
            stamps = read_times(self.path / "times.txt", len(files))
        self._stamps_given = stamps is not None
        self._nominal_rate = rate_hz
        self._items: list[tuple[Path, np.ndarray | None, float | None]] = []
        for k, f in enumerate(files):
            why = self._problem(f, has_pose=poses is not None)
            if why:
                self.skip(str(f), why)
            else:
                self._items.append(
                    (
                        f,
                        None if poses is None else poses[k],
                        None if stamps is None else float(stamps[k]),
                    )
                )
        if not self._items:
            first = self.skipped[0].reason if self.skipped else ""
            raise DatasetError(self.path, f"every scan was skipped: {first}")

    def _problem(self, f: Path, has_pose: bool) -> str | None:
        if f.suffix == ".ply":
            try:
                why = ply_files.PlyHeader(f).problem(self.label_field)
            except ply_files.PlyError as exc:
                return exc.problem
            if why and self.label_field is not None and repr(self.label_field) in why:
                why = f"{why}; {NO_LABELS_HINT}"
            return why
        try:
            shapes = _npz_shapes(f)
        except DatasetError as exc:
            return exc.problem
        has = ", ".join(shapes) or "none"
        if "points" not in shapes:
            return f"NPZ needs a 'points' array (has: {has})"
        if self.labelled and "labels" not in shapes:
            return f"NPZ needs 'points' and 'labels' arrays (has: {has}; {NO_LABELS_HINT})"
        pshape = shapes["points"][0]
        if len(pshape) != 2 or pshape[1] != 3:
            return f"points has shape {pshape}, expected (N, 3)"
        if self.labelled:
            lshape, ldtype = shapes["labels"]
            if lshape != (pshape[0],):
                return f"labels has shape {lshape} for {pshape[0]} points"
            if ldtype.kind not in "iu":
                return f"labels are {ldtype}, expected integers"
        if "confidences" in shapes and shapes["confidences"][0] != (pshape[0],):
            return f"confidences has shape {shapes['confidences'][0]} for {pshape[0]} points"
        if "pose" in shapes and shapes["pose"][0] != (4, 4):
            return f"pose has shape {shapes['pose'][0]}, expected (4, 4)"
        if not has_pose and "pose" not in shapes:
            return "no pose: neither poses.txt nor a 'pose' array"
        return None

    def __len__(self) -> int:
        return len(self._items)

    @property
    def rate_hz(self) -> float:
        stamps = [s for _, _, s in self._items if s is not None]
        if len(stamps) == len(self._items):
            return rate_from_stamps(np.asarray(stamps), self._nominal_rate)
        return self._nominal_rate

    def scan(self, i: int) -> Scan:
        f, pose, stamp = self._items[i]
        conf = None
        if f.suffix == ".ply":
            try:
                v = ply_files.PlyHeader(f).read()
            except ply_files.PlyError as exc:
                raise DatasetError(f, exc.problem) from None
            points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
            labels = None if self.label_field is None else v[self.label_field].astype(np.int64)
            if "confidence" in v.dtype.names:
                conf = v["confidence"].astype(np.float32)
        else:
            with np.load(f, allow_pickle=False) as z:
                points = np.asarray(z["points"], np.float32)
                labels = np.asarray(z["labels"]) if self.labelled else None
                if "confidences" in z:
                    conf = np.asarray(z["confidences"], np.float32)
                if "pose" in z:
                    pose = np.asarray(z["pose"], np.float64)
                    check_poses(pose[None], f)
                if stamp is None and "stamp_s" in z:
                    stamp = float(z["stamp_s"])
        if stamp is None:
            stamp = i / self._nominal_rate
        return Scan(i, f.name, stamp, points, labels, pose.copy(), conf)
