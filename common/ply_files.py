"""PLY point clouds: one writer and one reader for every labelled cloud smana exchanges.

The writer makes binary little-endian (or ASCII) PLY with one `vertex` element; its property
types are the ones both Open3D and CloudCompare keep. Open3D's tensor reader drops `short`,
`ushort` and `uint` properties with a warning, so integer labels are written as `int` (int32).

The reader (`PlyHeader`) takes ASCII and binary PLY of either endianness with any vertex layout;
elements before the vertices are skipped, elements after them (faces) ignored. It reads only the
header until asked for the vertices, so a dataset of many scans can be checked cheaply.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# numpy kind+size -> the PLY type written; unsigned 16/32-bit widen to int (Open3D drops them)
_WRITE_TYPES = {
    "i1": ("char", "i1"),
    "u1": ("uchar", "u1"),
    "i2": ("int", "i4"),
    "u2": ("int", "i4"),
    "i4": ("int", "i4"),
    "u4": ("int", "i4"),
    "i8": ("int", "i4"),
    "u8": ("int", "i4"),
    "f2": ("float", "f4"),
    "f4": ("float", "f4"),
    "f8": ("double", "f8"),
    "b1": ("uchar", "u1"),
}


class PlyError(ValueError):
    """A PLY file is malformed or lacks what the caller needs; the message names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


def write_ply(
    path: str | Path, columns: dict[str, np.ndarray], comment: str = "", binary: bool = True
) -> None:
    """Write one vertex per row of `columns` (name -> array of N values), in that order.

    Integers wider than a byte are written as `int` (values must fit in int32). The file appears
    atomically (written beside it, then renamed), so a reader never sees half a map.
    """
    if not columns:
        raise ValueError("no columns to write")
    n = len(next(iter(columns.values())))
    fields, ply_types = [], []
    for name, values in columns.items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise ValueError(f"column {name!r} has shape {values.shape}, expected ({n},)")
        code = values.dtype.kind + str(values.dtype.itemsize)
        if code not in _WRITE_TYPES:
            raise ValueError(f"column {name!r}: dtype {values.dtype} has no PLY type")
        ply_type, dt = _WRITE_TYPES[code]
        if dt == "i4" and n and values.dtype.itemsize >= 2:
            lo, hi = values.min(), values.max()
            if lo < -(2**31) or hi >= 2**31:
                raise ValueError(f"column {name!r} does not fit in int32 ({lo}..{hi})")
        fields.append((name, "<" + dt))
        ply_types.append(ply_type)
    rows = np.empty(n, fields)
    for name, values in columns.items():
        rows[name] = values
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    header += [f"comment {line}" for line in comment.splitlines()]
    header += [f"element vertex {n}"]
    header += [f"property {t} {name}" for t, (name, _) in zip(ply_types, fields)]
    header += ["end_header", ""]
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write("\n".join(header).encode("ascii"))
        if binary:
            f.write(rows.tobytes())
        else:
            # enough digits that every value reads back exactly
            digits = {"f4": "%.9g", "f8": "%.17g"}
            fmt = " ".join(digits.get(dt[1:], "%d") for _, dt in fields)
            np.savetxt(f, rows.tolist(), fmt=fmt)
    tmp.replace(path)


class PlyHeader:
    """The parts of a PLY header needed to read its vertices; `read()` reads them."""

    def __init__(self, path: str | Path):
        self.path = path = Path(path)
        with path.open("rb") as f:
            if f.readline().strip() != b"ply":
                raise PlyError(path, "not a PLY file (no 'ply' magic)")
            self.format = None
            elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
            while True:
                line = f.readline()
                if not line:
                    raise PlyError(path, "PLY header has no end_header")
                words = line.decode("ascii", "replace").split()
                if not words or words[0] in ("comment", "obj_info"):
                    continue
                if words[0] == "end_header":
                    break
                if words[0] == "format" and len(words) >= 2:
                    self.format = words[1]
                elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
                    elements.append((words[1], int(words[2]), []))
                elif words[0] == "property" and elements:
                    if words[1] == "list":  # a list (faces): no fixed size
                        elements[-1][2].append((words[-1], None))
                    elif words[1] in PLY_TYPES and len(words) == 3:
                        elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
                    else:
                        raise PlyError(path, f"PLY property line not understood: {line!r}")
                else:
                    raise PlyError(path, f"PLY header line not understood: {line!r}")
            self.data_offset = f.tell()
        if self.format not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise PlyError(path, f"PLY format {self.format!r} not supported")
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise PlyError(path, "PLY has no 'vertex' element")
        k = names.index("vertex")
        if any(t is None for e in elements[: k + 1] for _, t in e[2]):
            raise PlyError(path, "PLY list properties before or in 'vertex' are not supported")
        self.skip_rows = sum(e[1] for e in elements[:k])  # only for ASCII
        order = ">" if self.format == "binary_big_endian" else "<"
        self.skip_bytes = sum(
            e[1] * np.dtype([(n, order + t) for n, t in e[2]]).itemsize for e in elements[:k]
        )
        self.n_vertices = elements[k][1]
        self.properties: dict[str, str] = dict(elements[k][2])
        self.dtype = np.dtype([(n, order + t) for n, t in elements[k][2]])

    def problem(self, label_field: str | None = None, float_labels: bool = False) -> str | None:
        """Why these vertices cannot be read as a labelled cloud (None if they can): float x, y, z,
        an integer `label_field` (or a float one when `float_labels`), and enough bytes."""
        props = ", ".join(self.properties)
        for axis in "xyz":
            if self.properties.get(axis, "")[:1] != "f":
                return f"vertex property {axis!r} missing or not float (properties: {props})"
        if label_field is not None:
            kinds = ("i", "u", "f") if float_labels else ("i", "u")
            if self.properties.get(label_field, "")[:1] not in kinds:
                what = "numeric" if float_labels else "integer"
                return f"{what} vertex property {label_field!r} missing (properties: {props})"
        return self._truncated()

    def _truncated(self) -> str | None:
        if self.format == "ascii":
            return None
        need = self.data_offset + self.skip_bytes + self.n_vertices * self.dtype.itemsize
        size = self.path.stat().st_size
        return f"truncated: {size} bytes, the header announces {need}" if size < need else None

    def read(self) -> np.ndarray:
        """The vertices as a structured array (one field per property)."""
        if self.format == "ascii":
            with self.path.open("rb") as f:
                f.seek(self.data_offset)
                for _ in range(self.skip_rows):
                    f.readline()
                rows = [f.readline() for _ in range(self.n_vertices)]
            try:
                table = np.loadtxt(rows, dtype=np.float64, ndmin=2)
            except ValueError as exc:
                raise PlyError(self.path, f"bad ASCII vertex data ({exc})") from None
            if table.shape != (self.n_vertices, len(self.dtype.names)) and self.n_vertices:
                raise PlyError(self.path, "ASCII vertex rows do not match the properties")
            out = np.zeros(self.n_vertices, self.dtype)
            for j, n in enumerate(self.dtype.names):
                out[n] = table[:, j] if self.n_vertices else 0
            return out
        problem = self._truncated()
        if problem is not None:
            raise PlyError(self.path, problem)
        return np.fromfile(
            self.path,
            self.dtype,
            count=self.n_vertices,
            offset=self.data_offset + self.skip_bytes,
        )


def read_ply(path: str | Path) -> np.ndarray:
    """All vertices of a PLY file as a structured array."""
    return PlyHeader(path).read()
