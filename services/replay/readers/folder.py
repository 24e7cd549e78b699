"""A folder of labelled PLY or NPZ scans with a pose file: the format for data from anywhere else.

Scans are read in file-name order. An NPZ holds `points` (N x 3), `labels` (N, integers) and
optionally `confidences` (N), `pose` (4 x 4, sensor -> world) and `stamp_s`. A PLY (ASCII or
binary) holds a `vertex` element with float x, y, z, an integer label property (`label` by
default) and optionally a float `confidence`. Poses come from `poses.txt`, one line per scan, as
12 numbers (KITTI row-major 3 x 4) or 8 (TUM: stamp x y z qx qy qz qw); an NPZ's own `pose` wins.
Without stamps from TUM poses, NPZ files or `times.txt`, scans are spaced at `rate_hz`.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from smana.common.messages import quat_to_matrix

from .base import DatasetError, DatasetReader, Scan, check_poses, rate_from_stamps, read_times

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


class PlyHeader:
    """The parts of a PLY header needed to read its vertices."""

    def __init__(self, path: Path):
        self.path = path
        with path.open("rb") as f:
            if f.readline().strip() != b"ply":
                raise DatasetError(path, "not a PLY file (no 'ply' magic)")
            self.format = None
            elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
            while True:
                line = f.readline()
                if not line:
                    raise DatasetError(path, "PLY header has no end_header")
                words = line.decode("ascii", "replace").split()
                if not words or words[0] in ("comment", "obj_info"):
                    continue
                if words[0] == "end_header":
                    break
                if words[0] == "format" and len(words) >= 2:
                    self.format = words[1]
                elif words[0] == "element" and len(words) == 3:
                    elements.append((words[1], int(words[2]), []))
                elif words[0] == "property" and elements:
                    if words[1] == "list":  # a list (faces): no fixed size
                        elements[-1][2].append((words[-1], None))
                    elif words[1] in _PLY_TYPES and len(words) == 3:
                        elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
                    else:
                        raise DatasetError(path, f"PLY property line not understood: {line!r}")
                else:
                    raise DatasetError(path, f"PLY header line not understood: {line!r}")
            self.data_offset = f.tell()
        if self.format not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise DatasetError(path, f"PLY format {self.format!r} not supported")
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise DatasetError(path, "PLY has no 'vertex' element")
        k = names.index("vertex")
        if any(t is None for e in elements[: k + 1] for _, t in e[2]):
            raise DatasetError(path, "PLY list properties before or in 'vertex' are not supported")
        self.skip_rows = sum(e[1] for e in elements[:k])  # only for ASCII
        order = ">" if self.format == "binary_big_endian" else "<"
        self.skip_bytes = sum(e[1] * np.dtype([(n, order + t) for n, t in e[2]]).itemsize
                              for e in elements[:k])  # fmt: skip
        self.n_vertices = elements[k][1]
        self.properties = dict(elements[k][2])
        self.dtype = np.dtype([(n, order + t) for n, t in elements[k][2]])

    def problem(self, label_field: str) -> str | None:
        props = ", ".join(self.properties)
        for axis in "xyz":
            if self.properties.get(axis, "")[:1] != "f":
                return f"vertex property {axis!r} missing or not float (properties: {props})"
        if self.properties.get(label_field, "")[:1] not in ("i", "u"):
            return f"integer vertex property {label_field!r} missing (properties: {props})"
        if self.format != "ascii":
            need = self.data_offset + self.skip_bytes + self.n_vertices * self.dtype.itemsize
            size = self.path.stat().st_size
            if size < need:
                return f"truncated: {size} bytes, the header announces {need}"
        return None

    def read(self) -> np.ndarray:
        if self.format == "ascii":
            with self.path.open("rb") as f:
                f.seek(self.data_offset)
                for _ in range(self.skip_rows):
                    f.readline()
                rows = [f.readline() for _ in range(self.n_vertices)]
            try:
                table = np.loadtxt(rows, dtype=np.float64, ndmin=2)
            except ValueError as exc:
                raise DatasetError(self.path, f"bad ASCII vertex data ({exc})") from None
            if table.shape != (self.n_vertices, len(self.dtype.names)) and self.n_vertices:
                raise DatasetError(self.path, "ASCII vertex rows do not match the properties")
            out = np.zeros(self.n_vertices, self.dtype)
            for j, n in enumerate(self.dtype.names):
                out[n] = table[:, j] if self.n_vertices else 0
            return out
        return np.fromfile(
            self.path, self.dtype, count=self.n_vertices,
            offset=self.data_offset + self.skip_bytes,
        )  # fmt: skip


def write_ply(path: Path, points, labels, confidences=None, binary: bool = True) -> None:
    """Write a labelled PLY (the format this reader takes), e.g. to export scans from elsewhere."""
    points = np.asarray(points, np.float32)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2")]
    if confidences is not None:
        fields.append(("confidence", "<f4"))
    arr = np.zeros(points.shape[0], fields)
    arr["x"], arr["y"], arr["z"] = points.T
    arr["label"] = labels
    if confidences is not None:
        arr["confidence"] = confidences
    ply_names = {"<f4": "float", "<u2": "ushort"}
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              f"element vertex {arr.size}"]  # fmt: skip
    header += [f"property {ply_names[t]} {n}" for n, t in fields] + ["end_header"]
    with Path(path).open("wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        if binary:
            f.write(arr.tobytes())
        else:
            for row in arr:
                f.write((" ".join(str(v) for v in row) + "\n").encode())


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

    def __init__(self, path, *, label_field: str = "label", rate_hz: float = 10.0,
                 strict: bool = False):  # fmt: skip
        super().__init__(path, strict=strict)
        if not self.path.is_dir():
            raise DatasetError(self.path, "expected a folder of .ply or .npz scans")
        self.label_field = label_field
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
                    (f, None if poses is None else poses[k],
                     None if stamps is None else float(stamps[k]))
                )  # fmt: skip
        if not self._items:
            first = self.skipped[0].reason if self.skipped else ""
            raise DatasetError(self.path, f"every scan was skipped: {first}")
        self._plys: dict[Path, PlyHeader] = {}

    def _problem(self, f: Path, has_pose: bool) -> str | None:
        if f.suffix == ".ply":
            try:
                return PlyHeader(f).problem(self.label_field)
            except DatasetError as exc:
                return exc.problem
        try:
            shapes = _npz_shapes(f)
        except DatasetError as exc:
            return exc.problem
        if "points" not in shapes or "labels" not in shapes:
            return f"NPZ needs 'points' and 'labels' arrays (has: {', '.join(shapes) or 'none'})"
        (pshape, _), (lshape, ldtype) = shapes["points"], shapes["labels"]
        if len(pshape) != 2 or pshape[1] != 3:
            return f"points has shape {pshape}, expected (N, 3)"
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
            v = PlyHeader(f).read()
            points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
            labels = v[self.label_field].astype(np.int64)
            if "confidence" in v.dtype.names:
                conf = v["confidence"].astype(np.float32)
        else:
            with np.load(f, allow_pickle=False) as z:
                points = np.asarray(z["points"], np.float32)
                labels = np.asarray(z["labels"])
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
