"""Damaged mapper journals and block-store region files, for the replay and the store to survive.

A journal (`services/mapper/journal.py`) is built from a few small clouds (`journal()`), each
record's byte span kept; then one thing is done to it:

- `truncated(j, at)`: the file cut at `at` (any offset);
- `flipped(j, at, bit)`: one bit flipped at byte `at`;
- `with_record(j, i, payload)`: record `i` replaced by a crafted one whose checksum holds
  (`CRAFTED`: bad shapes, dtypes, keys, columns, NaN, inf, out-of-range values, counters that
  are not numbers, not a map at all).

`expected_state(j, lost)` is the slow, obvious reference of what a reader must make of it: a
dict from voxel key to its columns, the records applied in order in plain Python, all but the
lost ones. `region_file(kind, ...)` writes a damaged block-store region (`blockstore.py`).
"""

from __future__ import annotations

import io
import zlib
from dataclasses import dataclass

import numpy as np

from smana.services.mapper.journal import MAGIC, RECORD_FRAME, JournalWriter, frame, packed_array


@dataclass
class Journal:
    data: bytes
    spans: list[tuple[int, int]]  # (start, end) of each record; spans[0] is the header
    records: list[dict]  # the voxel records as written (keys, cols), header excluded
    backend: str


def small_map(backend: str = "octree-bayes"):
    from smana.services.mapper.semantic_map import SemanticMap

    return SemanticMap(backend, 0.25, 2.0, 1.0)


def small_cloud(seed: int, n: int = 12):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32)
    pts[:, 2] = rng.uniform(-0.5, 0.5, n)
    labels = rng.choice(np.array([1, 2, 4, 8], np.uint16), n)
    return pts, labels, rng.uniform(0.3, 1.0, n).astype(np.float32), (0.1 * seed, 0.0, 0.5)


def journal(
    tmp, n_records: int = 4, backend: str = "octree-bayes", seed: int = 0, n_points: int = 12
) -> Journal:
    """A journal of `n_records` integrations of `n_points`, written by the real writer."""
    path = tmp / f"j{seed}.journal"
    m = small_map(backend)
    w = JournalWriter(path, m, {"clouds": 0})
    spans = [(0, w.bytes)]
    records = []
    for i in range(n_records):
        d = m.integrate(*small_cloud(seed * 100 + i + 1, n_points))
        start = w.bytes
        w.append(d.keys, {"clouds": i + 1})
        spans.append((start, w.bytes))
        records.append({"keys": np.asarray(d.keys, np.int32), "cols": m.voxel_state(d.keys)})
    w.close()
    return Journal(path.read_bytes(), spans, records, backend)


def truncated(j: Journal, at: int) -> bytes:
    return j.data[:at]


def flipped(j: Journal, at: int, bit: int) -> bytes:
    b = bytearray(j.data)
    b[at] ^= 1 << bit
    return bytes(b)


def record_at(j: Journal, offset: int) -> int:
    """Which record holds byte `offset` (0: the header, i: voxel record i - 1)."""
    return next(i for i, (s, e) in enumerate(j.spans) if s <= offset < e)


def with_record(j: Journal, i: int, payload) -> bytes:
    """Voxel record `i` (0-based) replaced by `payload`, framed with a valid checksum."""
    s, e = j.spans[i + 1]
    if isinstance(payload, bytes):  # a body that is not msgpack of a record at all
        body = RECORD_FRAME.pack(MAGIC, len(payload), zlib.crc32(payload)) + payload
    else:
        body = frame(payload)
    return j.data[:s] + body + j.data[e:]


def _good(rec: dict) -> dict:
    return {
        "kind": "voxels",
        "keys": packed_array(rec["keys"]),
        "cols": {k: packed_array(v) for k, v in rec["cols"].items()},
        "service": {"clouds": 1},
    }


def _col(rec, name, f):
    out = _good(rec)
    out["cols"][name] = f(out["cols"][name], rec["cols"][name])
    return out


def _float_col(rec) -> str:
    return next(k for k, v in rec["cols"].items() if v.dtype.kind == "f")


def _set_float(rec, value):
    k = _float_col(rec)
    a = rec["cols"][k].copy()
    a.flat[0] = value
    return _col(rec, k, lambda d, _a, a=a: packed_array(a))


# Crafted records whose checksum holds: each must be refused whole, nothing of it applied.
CRAFTED = {
    "not_a_map": lambda rec: b"\x93\x01\x02\x03",
    "not_msgpack": lambda rec: b"\xc1\xc1\xc1",
    "a_list": lambda rec: [1, 2, 3],
    "no_keys": lambda rec: {k: v for k, v in _good(rec).items() if k != "keys"},
    "no_cols": lambda rec: {k: v for k, v in _good(rec).items() if k != "cols"},
    "no_service": lambda rec: {k: v for k, v in _good(rec).items() if k != "service"},
    "extra_field": lambda rec: {**_good(rec), "more": 1},
    "keys_float": lambda rec: {**_good(rec), "keys": packed_array(rec["keys"].astype(np.float32))},
    "keys_2d": lambda rec: {**_good(rec), "keys": packed_array(rec["keys"][:, :2])},
    "keys_out_of_range": lambda rec: {**_good(rec), "keys": packed_array(rec["keys"] + (1 << 20))},
    "keys_shape_lies": lambda rec: {
        **_good(rec),
        "keys": {**packed_array(rec["keys"]), "shape": [len(rec["keys"]) + 1, 3]},
    },
    "keys_object_dtype": lambda rec: {
        **_good(rec),
        "keys": {**packed_array(rec["keys"]), "dtype": "|O"},
    },
    "col_missing": lambda rec: {
        **_good(rec),
        "cols": dict(list(_good(rec)["cols"].items())[1:]),
    },
    "col_unknown": lambda rec: {**_good(rec), "cols": {**_good(rec)["cols"], "evil": b""}},
    "col_dtype": lambda rec: _col(
        rec, _float_col(rec), lambda d, a: packed_array(a.astype(np.float64))
    ),
    "col_short": lambda rec: _col(rec, _float_col(rec), lambda d, a: packed_array(a[:-1])),
    "col_nan": lambda rec: _set_float(rec, np.nan),
    "col_inf": lambda rec: _set_float(rec, np.inf),
    "counters_text": lambda rec: {**_good(rec), "service": {"clouds": "many"}},
    "counters_huge": lambda rec: {**_good(rec), "service": {"clouds": 2**64 - 1}},
    "counters_nan": lambda rec: {**_good(rec), "service": {"clouds": float("nan")}},
    "counters_list": lambda rec: {**_good(rec), "service": [1]},
}


def crafted(j: Journal, i: int, name: str) -> bytes:
    return with_record(j, i, CRAFTED[name](j.records[i]))


def expected_state(j: Journal, lost: set[int] = frozenset()) -> dict[tuple, tuple]:
    """The reference: voxel key -> its columns (as bytes), each record applied in order in plain
    Python, all but the records in `lost` (0-based voxel record indices)."""
    out: dict[tuple, tuple] = {}
    for i, rec in enumerate(j.records):
        if i in lost:
            continue
        names = sorted(rec["cols"])
        for r, key in enumerate(rec["keys"].tolist()):
            out[tuple(key)] = tuple(rec["cols"][k][r].tobytes() for k in names)
    return out


def state_of(m, j: Journal) -> dict[tuple, tuple]:
    """The same dict read from a map, over every key any record of `j` holds; a voxel the map
    holds as blank (never observed) is left out, as the reference leaves it out."""
    keys = np.unique(np.concatenate([r["keys"] for r in j.records]), axis=0)
    g = m._core.grid.lookup(keys)
    names = sorted(m.column_names())
    out = {}
    for key, gi in zip(keys.tolist(), g.tolist(), strict=True):
        if gi < 0:
            continue
        cols = tuple(m._core.grid.cols[k][gi].tobytes() for k in names)
        if any(np.frombuffer(c, np.uint8).any() for c in cols):
            out[tuple(key)] = cols
    return out


def region_file(path, kind: str, good: bytes) -> None:
    """A block-store region file: `good` (a valid one's bytes) damaged by `kind`."""
    if kind == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif kind == "flipped":
        b = bytearray(good)
        b[len(b) // 2] ^= 0x10
        path.write_bytes(bytes(b))
    elif kind in ("nan", "foreign_blocks", "missing_column"):
        with np.load(io.BytesIO(good)) as f:
            arrays = {k: f[k].copy() for k in f.files}
        if kind == "nan":
            k = next(k for k, v in arrays.items() if k.startswith("col_") and v.dtype.kind == "f")
            arrays[k].flat[0] = np.nan
        elif kind == "foreign_blocks":
            arrays["block_keys"] = arrays["block_keys"] + (64 << 21)  # 64 blocks over in y
        else:
            arrays.pop(next(k for k in arrays if k.startswith("col_")))
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    elif kind == "not_a_file":
        path.unlink()
        path.mkdir()
    else:
        raise ValueError(kind)


REGION_DAMAGE = ("truncated", "flipped", "nan", "foreign_blocks", "missing_column", "not_a_file")

__all__ = [
    "CRAFTED",
    "REGION_DAMAGE",
    "Journal",
    "crafted",
    "expected_state",
    "flipped",
    "journal",
    "record_at",
    "region_file",
    "state_of",
    "truncated",
]
