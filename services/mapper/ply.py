"""Binary PLY export of labelled voxels (Open3D and CloudCompare read it; extra fields become
scalar fields in CloudCompare), and a small reader for tests and tools."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("label", "<u2"),
        ("confidence", "<f4"),
    ]
)
_PLY_TYPES = {"f4": "float", "u1": "uchar", "u2": "ushort"}


def write_ply(path, points, colours, labels, confidences) -> None:
    n = int(points.shape[0])
    v = np.empty(n, _VERTEX)
    v["x"], v["y"], v["z"] = (points[:, i] for i in range(3))
    v["red"], v["green"], v["blue"] = (colours[:, i] for i in range(3))
    v["label"] = labels
    v["confidence"] = confidences
    props = "".join(
        f"property {_PLY_TYPES[_VERTEX[name].str[1:]]} {name}\n" for name in _VERTEX.names
    )
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment smana semantic map\n"
        f"element vertex {n}\n{props}end_header\n"
    )
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
    tmp.replace(path)


def read_ply(path) -> np.ndarray:
    """Read a PLY written by `write_ply` back into a structured array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if header[0] != "ply" or header[1] != "format binary_little_endian 1.0":
        raise ValueError(f"{path}: not a binary little-endian PLY")
    n = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    return np.frombuffer(data, _VERTEX, count=n, offset=end)
