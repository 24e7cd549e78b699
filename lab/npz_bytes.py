"""Map files byte by byte, for the map-file fuzzer (fuzz_maps.py): `.npy` members and their
headers (any declared shape and dtype, valid or not), zip archives (also ones no zip library
would write: `raw_zip`), a deflated member of zeros that decompresses past any limit
(`bomb_stream`) and a whole `.npz` file from its arrays (`file_bytes`)."""

from __future__ import annotations

import io
import json
import struct
import warnings
import zipfile
import zlib
from functools import cache

import numpy as np

BOMB_BYTES = 256 << 20  # what a bomb member decompresses to


def npy_bytes(a: np.ndarray, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, allow_pickle=allow_pickle)
    return buf.getvalue()


def npy_header(descr: str, shape, fortran=False, version: int = 1, raw: str | None = None) -> bytes:
    """An .npy header as written (padded to 64 bytes), with any content: `raw` replaces the
    dict's text."""
    text = (
        raw if raw is not None else repr({"descr": descr, "fortran_order": fortran, "shape": shape})
    )
    body = text.encode("latin1", "replace")
    fmt = "<H" if version == 1 else "<I"
    pre = len(b"\x93NUMPY") + 2 + struct.calcsize(fmt)
    pad = (-(pre + len(body) + 1)) % 64
    body += b" " * pad + b"\n"
    return b"\x93NUMPY" + bytes([version, 0]) + struct.pack(fmt, len(body)) + body


def zip_bytes(members: list[tuple[str, bytes]], compress: bool = False) -> bytes:
    """A zip of these (name, content) members in order; a name may come twice."""
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Duplicate name": that is the point
        with zipfile.ZipFile(buf, "w", method) as z:
            for name, content in members:
                z.writestr(name, content)
    return buf.getvalue()


def raw_zip(entries: list[tuple[str, bytes, int, int, int]]) -> bytes:
    """A zip written by hand: (name, data as stored, method, declared size, crc) per member, so
    that a member may declare any size and hold pre-compressed data."""
    out, central = io.BytesIO(), io.BytesIO()
    for name, data, method, size, crc in entries:
        fname = name.encode()
        offset = out.tell()
        out.write(
            struct.pack(
                "<4s5H3L2H",
                b"PK\x03\x04",
                20,
                0,
                method,
                0,
                0,
                crc,
                len(data),
                size & 0xFFFFFFFF,
                len(fname),
                0,
            )
        )
        out.write(fname)
        out.write(data)
        central.write(
            struct.pack(
                "<4s6H3L5H2L",
                b"PK\x01\x02",
                20,
                20,
                0,
                method,
                0,
                0,
                crc,
                len(data),
                size & 0xFFFFFFFF,
                len(fname),
                0,
                0,
                0,
                0,
                0,
                offset,
            )
        )
        central.write(fname)
    cd = central.getvalue()
    start = out.tell()
    out.write(cd)
    n = len(entries)
    out.write(struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, n, n, len(cd), start, 0))
    return out.getvalue()


def file_bytes(arrays: dict[str, np.ndarray | bytes], compress: bool = False) -> bytes:
    """A map file of these members (an array, or the bytes of an .npy member as they are)."""
    members = [
        (f"{k}.npy", v if isinstance(v, bytes) else npy_bytes(np.asarray(v)))
        for k, v in arrays.items()
    ]
    return zip_bytes(members, compress)


@cache
def bomb_stream() -> tuple[bytes, int]:
    """An .npy array of zeros, BOMB_BYTES in all, raw-deflated (about 1/1000 of it), and its
    crc: a zip bomb's member (made once)."""
    head = npy_header("<f4", ((BOMB_BYTES - 128) // 4,))
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    parts, crc = [c.compress(head)], zlib.crc32(head)
    left = BOMB_BYTES - len(head)
    chunk = bytes(1 << 20)
    while left:
        part = chunk[: min(left, len(chunk))]
        parts.append(c.compress(part))
        crc = zlib.crc32(part, crc)
        left -= len(part)
    parts.append(c.flush())
    return b"".join(parts), crc


def read_npz(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of a `.npz` file's bytes."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def meta_bytes(meta: dict) -> np.ndarray:
    """A map file's metadata as its `meta` member holds it: JSON bytes."""
    return np.frombuffer(json.dumps(meta).encode(), np.uint8)
