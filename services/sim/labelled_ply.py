"""Labelled point clouds in PLY: the ground-truth export and the input of a `ply:PATH` world.

Writes binary little-endian PLY with the vertex fields `x y z label red green blue`, which Open3D,
CloudCompare and MeshLab open (`common/ply_files.py`). Reads binary (either endianness) and ASCII
PLY with any vertex property layout, as long as x, y, z and a label field are present.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smana.common.ply_files import PlyError, PlyHeader, write_ply

__all__ = ["LABEL_FIELDS", "PlyError", "read_labelled_ply", "write_labelled_ply"]

LABEL_FIELDS = ("label", "class", "semantic", "scalar_label", "scalar_Label", "class_id")


def write_labelled_ply(
    path: str | Path, points: np.ndarray, labels: np.ndarray, colours: np.ndarray
) -> None:
    """Write points (N,3), integer labels (N,) and colours (N,3) uint8 as binary PLY."""
    points = np.asarray(points, np.float32)
    labels = np.asarray(labels)
    colours = np.asarray(colours, np.uint8)
    n = len(points)
    if points.shape != (n, 3) or labels.shape != (n,) or colours.shape != (n, 3):
        raise ValueError(
            f"shapes disagree: points {points.shape}, labels {labels.shape}, "
            f"colours {colours.shape}"
        )
    if labels.dtype.kind not in "iu":
        raise ValueError(f"labels must be integers, not {labels.dtype}")
    write_ply(
        path,
        {
            "x": points[:, 0],
            "y": points[:, 1],
            "z": points[:, 2],
            "label": labels,
            "red": colours[:, 0],
            "green": colours[:, 1],
            "blue": colours[:, 2],
        },
        comment="smana ground truth",
    )


def read_labelled_ply(path: str | Path, label_field: str | None = None) -> tuple[np.ndarray, ...]:
    """Read (points f8[N,3], labels i64[N]) from a PLY file.

    `label_field` names the vertex property holding class ids; by default the first of
    `LABEL_FIELDS` present is used. Float labels are accepted when they hold whole numbers.
    """
    header = PlyHeader(path)
    if label_field is None:
        label_field = next((f for f in LABEL_FIELDS if f in header.properties), None)
        if label_field is None:
            raise PlyError(path, f"no label field (looked for {', '.join(LABEL_FIELDS)})")
    problem = header.problem(label_field, float_labels=True)
    if problem is not None:
        raise PlyError(path, problem)
    v = header.read()
    points = np.stack([np.asarray(v[a], np.float64) for a in "xyz"], axis=1)
    labels_raw = np.asarray(v[label_field])
    if labels_raw.dtype.kind == "f":
        if not np.all(np.isfinite(labels_raw)) or np.any(labels_raw != np.round(labels_raw)):
            raise PlyError(path, f"label field {label_field!r} holds non-integer values")
    return points, labels_raw.astype(np.int64)
