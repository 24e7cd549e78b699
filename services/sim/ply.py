"""Labelled point clouds in PLY: the ground-truth export and the input of `GardenWorld.from_ply`.

Writes binary little-endian PLY with the vertex fields `x y z label red green blue`, which Open3D,
CloudCompare and MeshLab open. Reads binary (either endianness) and ASCII PLY with any vertex
property layout, as long as x, y, z and a label field are present; other elements (faces) that
come after the vertices are ignored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
LABEL_FIELDS = ("label", "class", "semantic", "scalar_label", "scalar_Label", "class_id")


class PlyError(ValueError):
    """A PLY file is malformed or lacks a field we need."""


def write_labelled_ply(
    path: str | Path, points: np.ndarray, labels: np.ndarray, colours: np.ndarray
) -> None:
    """Write points (N,3), labels (N,) as uint16 and colours (N,3) uint8 as binary PLY."""
    points = np.asarray(points, np.float32)
    labels = np.asarray(labels)
    colours = np.asarray(colours, np.uint8)
    n = len(points)
    if points.shape != (n, 3) or labels.shape != (n,) or colours.shape != (n, 3):
        raise ValueError(
            f"shapes disagree: points {points.shape}, labels {labels.shape}, "
            f"colours {colours.shape}"
        )
    if n and (labels.min() < 0 or labels.max() > 65535):
        raise ValueError("labels must fit in uint16")
    record = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2"),
         ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )  # fmt: skip
    data = np.empty(n, record)
    data["x"], data["y"], data["z"] = points.T
    data["label"] = labels
    data["red"], data["green"], data["blue"] = colours.T
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment smana ground truth\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\nproperty ushort label\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())


def read_labelled_ply(path: str | Path, label_field: str | None = None) -> tuple[np.ndarray, ...]:
    """Read (points f8[N,3], labels i64[N]) from a PLY file.

    `label_field` names the vertex property holding class ids; by default the first of
    `LABEL_FIELDS` present is used. Float labels are accepted when they hold whole numbers.
    """
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:body_start].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info", "end_header"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise PlyError(f"{path}: property before any element")
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], "list"))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise PlyError(f"{path}: unknown property type {parts[1]!r}")
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise PlyError(f"{path}: unsupported format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise PlyError(f"{path}: the first element must be 'vertex'")
    _, n, props = elements[0]
    if any(t == "list" for _, t in props):
        raise PlyError(f"{path}: list properties on vertices are not supported")
    names = [name for name, _ in props]
    for axis in "xyz":
        if axis not in names:
            raise PlyError(f"{path}: vertex has no {axis!r} property")
    if label_field is None:
        label_field = next((f for f in LABEL_FIELDS if f in names), None)
        if label_field is None:
            raise PlyError(f"{path}: no label field (looked for {', '.join(LABEL_FIELDS)})")
    elif label_field not in names:
        raise PlyError(f"{path}: no vertex property {label_field!r} (has {', '.join(names)})")

    if fmt == "ascii":
        text = raw[body_start:].decode("ascii").split("\n", n)[:n]
        if len(text) < n:
            raise PlyError(f"{path}: expected {n} vertex lines, found {len(text)}")
        table = np.loadtxt(text, dtype=np.float64, ndmin=2) if n else np.zeros((0, len(names)))
        if table.shape[1] < len(names):
            raise PlyError(f"{path}: vertex lines have fewer values than properties")
        column = {name: table[:, i] for i, name in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + t) for name, t in props])
        if len(raw) - body_start < n * dtype.itemsize:
            raise PlyError(f"{path}: file truncated ({n} vertices announced)")
        column = np.frombuffer(raw, dtype, count=n, offset=body_start)
    points = np.stack([np.asarray(column[a], np.float64) for a in "xyz"], axis=1)
    labels_raw = np.asarray(column[label_field])
    if labels_raw.dtype.kind == "f":
        if not np.all(np.isfinite(labels_raw)) or np.any(labels_raw != np.round(labels_raw)):
            raise PlyError(f"{path}: label field {label_field!r} holds non-integer values")
    labels = labels_raw.astype(np.int64)
    return points, labels
