"""common/ply_files.py: the one PLY writer and reader behind the map, ground-truth and scan
files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from smana.common.ply_files import PlyError, PlyHeader, read_ply, write_ply

# the property types Open3D 0.18-0.20 keeps (`open3d.t.io.read_point_cloud` skips short, ushort and
# uint with a warning; checked by hand with open3d 0.20.0, see docs/architecture.md)
OPEN3D_TYPES = {"char", "uchar", "int", "float", "double"}


def _columns(n=300, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n).astype(np.float32),
        "z": rng.normal(size=n).astype(np.float64),
        "red": rng.integers(0, 256, n).astype(np.uint8),
        "label": rng.integers(0, 60000, n).astype(np.uint16),
        "confidence": rng.random(n).astype(np.float32),
    }


def _properties(path):
    text = path.read_bytes().split(b"end_header")[0].decode()
    return [line.split()[1:] for line in text.splitlines() if line.startswith("property")]


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_in_the_types_open3d_keeps(tmp_path, binary):
    cols = _columns()
    path = tmp_path / "c.ply"
    write_ply(path, cols, comment="two\nlines", binary=binary)
    props = _properties(path)
    assert [name for _, name in props] == list(cols)
    assert {t for t, _ in props} <= OPEN3D_TYPES
    assert dict((n, t) for t, n in props)["label"] == "int"
    v = read_ply(path)
    for name, values in cols.items():
        np.testing.assert_array_equal(v[name], values, err_msg=name)
    assert not list(tmp_path.glob("*.tmp"))


def test_reads_big_endian_with_an_element_before_the_vertices(tmp_path):
    # a slow, obvious writer: struct, one value at a time
    pts = [(1.5, -2.0, 3.25, 7), (0.0, 1.0, -1.0, 300)]
    body = struct.pack(">ii", 1, 2)  # element "camera" with two ints, before the vertices
    for x, y, z, lab in pts:
        body += struct.pack(">fffH", x, y, z, lab)
    body += b"\x03" + struct.pack(">iii", 0, 1, 0)  # a face after them
    path = tmp_path / "be.ply"
    path.write_bytes(
        b"ply\nformat binary_big_endian 1.0\nelement camera 1\nproperty int a\nproperty int b\n"
        b"element vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        b"property ushort label\nelement face 1\nproperty list uchar int vertex_indices\n"
        b"end_header\n" + body
    )
    h = PlyHeader(path)
    assert h.problem("label") is None and h.n_vertices == 2
    v = h.read()
    assert [tuple(float(r[k]) for k in ("x", "y", "z", "label")) for r in v] == pts


def test_problems_are_named(tmp_path):
    path = tmp_path / "c.ply"
    write_ply(
        path,
        {
            "x": np.zeros(4, np.float32),
            "y": np.zeros(4, np.float32),
            "z": np.zeros(4, np.float32),
            "cls": np.zeros(4, np.float32),
        },
    )
    h = PlyHeader(path)
    assert (
        h.problem("label") == "integer vertex property 'label' missing (properties: x, y, z, cls)"
    )
    assert h.problem("cls") is not None and h.problem("cls", float_labels=True) is None
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(PlyError, match="truncated"):
        read_ply(path)
    cases = {
        b"solid cube\n": "no 'ply' magic",
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n": "no end_header",
        b"ply\nformat weird 1.0\nelement vertex 0\nend_header\n": "format 'weird'",
        b"ply\nformat ascii 1.0\nelement face 0\nend_header\n": "no 'vertex' element",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n": "not understood",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1 2\n": "ASCII",
    }
    for raw, message in cases.items():
        path.write_bytes(raw)
        with pytest.raises(PlyError, match=message):
            read_ply(path)
    with pytest.raises(ValueError, match="shape"):
        write_ply(path, {"x": np.zeros(3), "y": np.zeros(2)})
    with pytest.raises(ValueError, match="int32"):
        write_ply(path, {"label": np.array([2**40])})
