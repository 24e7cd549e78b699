"""SemanticKITTI layout: `sequences/NN/{velodyne,labels}/NNNNNN.{bin,label}`, poses, calib.

Scans are float32 (x, y, z, remission); labels uint32 with the semantic class in the low 16 bits
and the instance id in the high 16. With `label_field="none"` the labels (and their folder) are not
read: the replay labels the points by geometry, as for KITTI odometry scans that never had any.
`poses.txt` holds the left camera's poses, so the LiDAR's are
inv(Tr) @ P @ Tr with Tr (LiDAR -> camera) from `calib.txt`. RELLIS-3D ships the same files under
other folder names (see `rellis3d.py`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import (
    NO_LABELS,
    NO_LABELS_HINT,
    DatasetError,
    DatasetReader,
    Scan,
    camera_to_lidar_poses,
    check_poses,
    rate_from_stamps,
    read_kitti_calib,
    read_kitti_poses,
    read_times,
)

POINT_BYTES = 16  # float32 x, y, z, remission
LABEL_BYTES = 4


class KittiLayoutReader(DatasetReader):
    """Shared indexing of the KITTI-style layouts; subclasses name the folders."""

    cloud_dir = "velodyne"
    label_dir = "labels"
    sequences_dir = "sequences"
    calib_required = True
    nominal_rate_hz = 10.0

    def __init__(
        self,
        path,
        *,
        sequence: str | None = None,
        label_field: str = "label",
        strict: bool = False,
    ):
        super().__init__(path, strict=strict)
        if label_field not in ("label", NO_LABELS):
            raise ValueError(
                f"label field {label_field!r}: {self.format} labels come from .label files; "
                f"only {NO_LABELS!r} applies (label the points by geometry)"
            )
        self.labelled = label_field != NO_LABELS
        self.seq_dir = self._find_sequence(self.path, sequence)
        clouds = self.seq_dir / self.cloud_dir
        labels = self.seq_dir / self.label_dir
        if self.labelled and not labels.is_dir():
            raise DatasetError(labels, f"label folder is missing ({NO_LABELS_HINT})")
        bins = []
        for b in sorted(clouds.glob("*.bin")):
            if b.stem.isdigit():
                bins.append(b)
            else:
                self.skip(str(b), "file name is not a scan number")
        if not bins:
            raise DatasetError(clouds, "no numbered .bin scans")
        for k, b in enumerate(bins):
            if int(b.stem) != k:  # poses are matched to scans by line number
                raise DatasetError(b, f"scan numbering has a gap: expected {k:06d}.bin here")

        poses_path = self.seq_dir / "poses.txt"
        poses = read_kitti_poses(poses_path)
        if len(poses) != len(bins):
            raise DatasetError(poses_path, f"{len(poses)} poses for {len(bins)} scans in {clouds}")
        calib_path = self.seq_dir / "calib.txt"
        if calib_path.is_file() or self.calib_required:
            calib = read_kitti_calib(calib_path)
            if "Tr" not in calib:
                raise DatasetError(calib_path, "no 'Tr' (LiDAR -> camera) line")
            poses = camera_to_lidar_poses(poses, calib["Tr"])
        check_poses(poses, poses_path)
        stamps = read_times(self.seq_dir / "times.txt", len(bins))
        if stamps is None:
            stamps = np.arange(len(bins)) / self.nominal_rate_hz
        self._rate_hz = rate_from_stamps(stamps, self.nominal_rate_hz)

        # Per-scan checks need only file sizes, so the skip list is complete before replay starts.
        self._items: list[tuple[Path, Path | None, np.ndarray, float]] = []
        for k, b in enumerate(bins):
            lab = labels / (b.stem + ".label")
            size = b.stat().st_size
            if size == 0 or size % POINT_BYTES:
                self.skip(str(b), f"truncated: {size} bytes is not a multiple of {POINT_BYTES}")
            elif not self.labelled:
                self._items.append((b, None, poses[k], float(stamps[k])))
            elif not lab.is_file():
                self.skip(str(b), f"no label file {lab} ({NO_LABELS_HINT})")
            elif lab.stat().st_size != size // POINT_BYTES * LABEL_BYTES:
                n_lab = lab.stat().st_size / LABEL_BYTES
                self.skip(str(b), f"{lab.name} holds {n_lab:g} labels for {size // 16} points")
            else:
                self._items.append((b, lab, poses[k], float(stamps[k])))
        if not self._items:
            raise DatasetError(clouds, f"every scan was skipped ({len(self.skipped)})")

    def _find_sequence(self, path: Path, sequence: str | None) -> Path:
        if (path / self.cloud_dir).is_dir():
            return path
        bases = [path / self.sequences_dir, path]
        if sequence is not None:
            for base in bases:
                if (base / sequence / self.cloud_dir).is_dir():
                    return base / sequence
            raise DatasetError(path / sequence, f"not a {self.format} sequence")
        found = [
            c
            for b in bases
            if b.is_dir()
            for c in sorted(b.iterdir())
            if (c / self.cloud_dir).is_dir()
        ]
        if len(found) == 1:
            return found[0]
        if found:
            names = ", ".join(c.name for c in found[:10])
            raise DatasetError(path, f"holds several sequences, name one: {names}")
        raise DatasetError(path, f"not a {self.format} sequence (no '{self.cloud_dir}' folder)")

    def __len__(self) -> int:
        return len(self._items)

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    def scan(self, i: int) -> Scan:
        b, lab, pose, stamp = self._items[i]
        raw = np.fromfile(b, dtype=np.float32).reshape(-1, 4)
        if lab is None:  # unlabelled: the replay labels the points by geometry
            return Scan(i, b.name, stamp, np.ascontiguousarray(raw[:, :3]), None, pose.copy())
        labels = np.fromfile(lab, dtype=np.uint32) & 0xFFFF
        if labels.size != raw.shape[0]:  # the file changed since it was indexed
            raise DatasetError(lab, f"{labels.size} labels for {raw.shape[0]} points")
        return Scan(i, b.name, stamp, np.ascontiguousarray(raw[:, :3]), labels, pose.copy())


class SemanticKittiReader(KittiLayoutReader):
    format = "semantickitti"
    default_class_table = "semantickitti"
