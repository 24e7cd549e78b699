"""PLY export of labelled voxels: x y z, a colour, the class id and its confidence per voxel
centre. Open3D keeps every field (`open3d.t.io.read_point_cloud`); CloudCompare shows label and
confidence as scalar fields."""

from __future__ import annotations

import numpy as np

from smana.common.ply_files import read_ply
from smana.common.ply_files import write_ply as _write

__all__ = ["read_ply", "write_ply"]


def write_ply(path, points, colours, labels, confidences) -> None:
    points = np.asarray(points, np.float32)
    colours = np.asarray(colours, np.uint8)
    _write(
        path,
        {
            "x": points[:, 0],
            "y": points[:, 1],
            "z": points[:, 2],
            "red": colours[:, 0],
            "green": colours[:, 1],
            "blue": colours[:, 2],
            "label": np.asarray(labels, np.int32),
            "confidence": np.asarray(confidences, np.float32),
        },
        comment="smana semantic map",
    )
