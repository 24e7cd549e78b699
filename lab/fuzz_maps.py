"""Structured fuzzing inputs for map files (`.npz`, issue 25): valid maps of every back-end and
format, and corrupt ones, for `SemanticMap.load` and `FleetMap.load`.

Like `lab/fuzz_messages.py` the generators take a `Draw` (a seeded `RandomDraw` in `smana bench
fuzz`, a hypothesis `data` object in the suite). A mutant starts from a valid base file (`bases()`:
the three back-ends, a fleet map, a format-1 file and a TSDF file with float log-probabilities) and
does one thing to it (`MAP_MUTATIONS`):

- `valid`: nothing (it must load, bit for bit);
- `truncate`: the file cut at any offset; `member_short`: one array shorter than its header says;
- `bytes`: bytes flipped anywhere (refused, or loaded as the base when the flip changed nothing
  that counts, a time stamp);
- `dtype`: an array in another dtype (float64, int32, bool, complex, big-endian, strings, dates);
- `shape`: an array with one element (broadcast), a row more or less, other dimensions;
- `header`: a crafted `.npy` header: a declared shape of terabytes, negative or fractional sizes,
  a structured or object dtype, a header longer than its member, an unknown `.npy` version;
- `keys`: block keys duplicated, negative, out of the key range, or floats;
- `values`: NaN, inf or out-of-range numbers in a column (probabilities, confidences, weights);
- `meta`: one metadata key missing, unknown, or set to a wild value
  (`lab.fuzz_values.WILD_SCALARS`, 1e308, 10**400, module:Class back-ends, paths as class
  tables, ...);
- `meta_json`: the metadata's JSON broken: invalid UTF-8, NaN tokens, deep nesting, not an
  object, cut short, 1e400, another dtype or shape;
- `members`: an array missing, one unknown, a name twice in the zip, a non-`.npy` member, a
  pickled object array;
- `bomb`: a deflated member of zeros that decompresses beyond the loader's size limit, or a zip
  directory declaring sizes that the data does not have.

`predict` is None when either outcome is right (a flip that may hit nothing, a wild value that
may be a valid one), True when the file must be refused, False when it must load as its base.
`try_load` loads a mutant the way the mapper does and says what happened: `loaded` (and whether
it equals its base), `refused` (a one-line `MapFileError`), or `crash` (anything else).
"""

from __future__ import annotations

import json
import warnings
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from smana.lab.fuzz_values import WILD_SCALARS, Draw
from smana.lab.npz_bytes import (
    BOMB_BYTES,
    bomb_stream,
    file_bytes,
    meta_bytes,
    npy_bytes,
    npy_header,
    raw_zip,
    read_npz,
    zip_bytes,
)

MAP_MUTATIONS = (
    "valid",
    "truncate",
    "member_short",
    "bytes",
    "dtype",
    "shape",
    "header",
    "keys",
    "values",
    "meta",
    "meta_json",
    "members",
    "bomb",
)
FUZZ_MAX_BYTES = 64 << 20  # the loaders' limit in the fuzz: a bomb over it stays cheap to make
CLASS_TABLE = "garden3drms"


@dataclass
class Base:
    """A valid map file and what loading it must give."""

    name: str  # "octree-max", ..., "fleet", "format1", "tsdf-float-logp"
    backend: str
    fleet: bool
    arrays: dict[str, np.ndarray]  # as saved (the file's members)
    meta: dict
    expect: dict[str, np.ndarray] = field(default_factory=dict)  # grid arrays after loading


@dataclass
class MapMutant:
    data: bytes
    base: str
    how: str  # "<mutation>:<detail>"
    predict: bool | None  # True: must be refused; False: must load as the base; None: either


# -- the valid files ------------------------------------------------------------------------------


def _cloud(seed: int, n: int = 1500):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-2.5, 2.5, (n, 3)).astype(np.float32)
    pts[:, 2] = rng.uniform(-0.3, 0.6, n)
    labels = rng.choice(np.array([0, 1, 2, 4, 5, 6, 7, 8]), n)
    return pts, labels, rng.uniform(0.3, 1.0, n).astype(np.float32)


@cache
def bases() -> tuple[Base, ...]:
    """The valid files every mutant starts from (built once per process, a few seconds)."""
    import tempfile

    from smana.common.config.fleet import FleetConfig
    from smana.common.config.mapper import MapperConfig
    from smana.services.mapper.fleet import FleetMap
    from smana.services.mapper.semantic_map import SemanticMap

    out = []
    with tempfile.TemporaryDirectory(prefix="smana-fuzz-maps-") as tmp:
        for i, backend in enumerate(("octree-max", "octree-bayes", "tsdf")):
            m = SemanticMap(backend, 0.2, 4.0, 1.0)
            for s in range(3):
                m.integrate(*_cloud(10 * i + s), origin=(0.0, 0.0, 0.4))
            if backend == "tsdf":
                log_ratio = float(m._core.log_ratio)
            arrays = read_npz(m.save(Path(tmp) / f"{backend}.npz").read_bytes())
            meta = json.loads(arrays["meta"].tobytes())
            expect = {k: v for k, v in arrays.items() if k != "meta"}
            out.append(Base(backend, backend, False, arrays, meta, expect))
        # a fleet map: two members' deltas merged, its layers saved beside
        mc = MapperConfig(resolution_m=0.2, max_range_m=4.0)
        fm = FleetMap(mc, ["r1", "r2"], FleetConfig(robots=["r1", "r2"]))
        for j, name in enumerate(("r1", "r2")):
            m = SemanticMap.from_config(mc)
            d = m.integrate(*_cloud(40 + j), origin=(0.0, 0.0, 0.4))
            fm.apply(name, d.centres, d.labels, d.confidences, d.values)
        arrays = read_npz(fm.save(Path(tmp) / "fleet.npz").read_bytes())
        meta = json.loads(arrays["meta"].tobytes())
        expect = {k: v for k, v in arrays.items() if k.startswith("layer")}
        out.append(Base("fleet", "octree-max", True, arrays, meta, expect))
    # format 1 (before the back-end registry): the octrees' config in two tables
    octree = out[0]
    meta = dict(octree.meta)
    meta.pop("smana_version", None)
    cfg = meta.pop("config")
    fusion = ("max_same_gain", "max_disagree_factor", "bayes_min_confidence")
    meta["occupancy"] = {k: v for k, v in cfg.items() if k not in fusion}
    meta["fusion"] = {k: cfg[k] for k in fusion}
    meta["tsdf"] = dict(out[2].meta["config"])
    meta["format"] = 1
    arrays = {**octree.arrays, "meta": meta_bytes(meta)}
    out.append(Base("format1", "octree-max", False, arrays, meta, octree.expect))
    # a TSDF map from before the int16 step counts: float32 log-probabilities in nats
    tsdf = out[2]
    arrays = dict(tsdf.arrays)
    arrays["col_logp"] = (tsdf.arrays["col_logp"] * log_ratio).astype(np.float32)
    meta = dict(tsdf.meta)
    meta.pop("smana_version", None)
    arrays["meta"] = meta_bytes(meta)
    out.append(Base("tsdf-float-logp", "tsdf", False, arrays, meta, tsdf.expect))
    return tuple(out)


# -- writing files --------------------------------------------------------------------------------


# -- mutations ------------------------------------------------------------------------------------


def _pick_array(d: Draw, base: Base, floats: bool = False) -> str:
    names = [k for k in base.arrays if k != "meta"]
    if floats:
        names = [k for k in names if base.arrays[k].dtype.kind == "f"]
    return d.choice(sorted(names))


_WRONG_DTYPES = (
    "<f8",
    "<f2",
    "<i4",
    "<i8",
    "<u2",
    "|u1",
    "|i1",
    "|b1",
    "<c8",
    "<c16",
    ">f4",
    ">i8",
    ">u2",
    "<U2",
    "<M8[s]",
)


def _as_dtype(a: np.ndarray, dt: str) -> np.ndarray:
    if dt.startswith("<U"):
        return a.astype("U2") if a.dtype.kind != "f" else np.full(a.shape, "x", "U2")
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a cast that overflows is still a wrong dtype
        if "M8" in dt:
            return a.astype(np.int64).astype(dt)
        return a.astype(dt)


def mutate_map(base: Base, d: Draw) -> MapMutant:
    """One mutant of `base` (see the module docstring)."""
    kind = d.choice(MAP_MUTATIONS)
    data, how, predict = _MUTATORS[kind](base, d)
    return MapMutant(data, base.name, f"{kind}:{how}", predict)


def _valid(base, d):
    return file_bytes(base.arrays, compress=d.boolean(0.2)), "as saved", False


def _truncate(base, d):
    data = file_bytes(base.arrays)
    k = d.choice((0, 1, 4, 30, d.integer(0, len(data) - 1), len(data) - 1, len(data) - 22))
    return data[: max(0, k)], f"{k} of {len(data)} bytes", True


def _member_short(base, d):
    name = _pick_array(d, base)
    raw = npy_bytes(base.arrays[name])
    cut = d.integer(1, max(1, len(raw) - 1 - 128)) if len(raw) > 129 else 1
    arrays = {**base.arrays, name: raw[: len(raw) - cut]}
    return file_bytes(arrays), f"{name} {cut} bytes short", True


def _bytes(base, d):
    data = bytearray(file_bytes(base.arrays))
    n = d.integer(1, 8)
    for _ in range(n):
        i = d.integer(0, len(data) - 1)
        data[i] ^= 1 << d.integer(0, 7)
    return bytes(data), f"{n} bits flipped", None


def _dtype(base, d):
    name = _pick_array(d, base)
    a = base.arrays[name]
    dt = d.choice(_WRONG_DTYPES)
    if np.dtype(dt) == a.dtype or (name == "col_logp" and dt in ("<f4",)):
        dt = "<c8"
    arrays = {**base.arrays, name: _as_dtype(a, dt)}
    return file_bytes(arrays), f"{name} as {dt}", True


def _shape(base, d):
    name = _pick_array(d, base)
    a = base.arrays[name]
    k = d.integer(0, 6)
    if k == 0:
        b, what = a[:1], "one element"
    elif k == 1:
        b, what = np.concatenate([a, a[:1]]), "a row more"
    elif k == 2:
        b, what = a[:-1], "a row less"
    elif k == 3:
        b, what = a.reshape(1, *a.shape), "an axis more"
    elif k == 4:
        b, what = np.asarray(a.flat[0] if a.size else 0, a.dtype), "a scalar"
    elif k == 5:
        b, what = a[:0], "empty"
    else:
        b, what = (a.reshape(-1) if a.ndim > 1 else a.reshape(-1, 1)), "other dimensions"
    if b.shape == a.shape:  # an empty grid: any other shape is wrong
        b, what = np.zeros((3, *a.shape[1:]), a.dtype), "three rows"
    arrays = {**base.arrays, name: np.ascontiguousarray(b)}
    return file_bytes(arrays), f"{name}: {what}", True


def _header(base, d):
    name = _pick_array(d, base)
    a = base.arrays[name]
    data = npy_bytes(a)[len(npy_header(a.dtype.str, a.shape)) :]
    huge = d.choice(((2**40,), (2**62,), (2**31, 2**31), (2**20, 2**20, 2**20), (-1,), (1.5,)))
    k = d.integer(0, 6)
    if k == 0:
        h, what = npy_header(a.dtype.str, huge), f"shape {huge}"
    elif k == 1:
        h, what = npy_header("|O", a.shape), "object dtype"
    elif k == 2:
        h, what = npy_header([("x", "<f4"), ("y", "<i8")], a.shape), "structured dtype"
    elif k == 3:
        h, what = npy_header(a.dtype.str, a.shape, raw=d.choice(_BAD_HEADERS)), "bad text"
    elif k == 4:
        h, what = npy_header(a.dtype.str, a.shape, version=d.choice((3, 2))), "version"
        if h[6] == 2:
            h, what = b"\x93NUMPY\x02\x00\xff\xff\xff\x7f", "header longer than the member"
    elif k == 5:
        h, what = b"\x93NUMPX\x01\x00" + npy_header(a.dtype.str, a.shape)[8:], "bad magic"
    else:
        h, what = npy_header(a.dtype.str, a.shape)[: d.integer(0, 20)], "cut in its header"
        data = b""
    arrays = {**base.arrays, name: h + data}
    return file_bytes(arrays), f"{name}: {what}", True


_BAD_HEADERS = (
    "{}",
    "[]",
    "{'descr': '<f4', 'fortran_order': False}",
    "{'descr': '<f4', 'fortran_order': 'no', 'shape': (3,)}",
    "{'descr': 'f4 junk', 'fortran_order': False, 'shape': (3,)}",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (3,), 'x': 1}",
    "{'descr': '<f4', 'fortran_order': False, 'shape': [3]}",
    "{'descr': '<f4', 'fortran_order': False, 'shape': ('3',)}",
    "__import__('os')",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (" + "(" * 200 + ")" * 200 + ",)}",
    "\x00\xff",
)


def _keys(base, d):
    prefix = d.choice(sorted({k[: -len("block_keys")] for k in base.arrays if "block_keys" in k}))
    name = prefix + "block_keys"
    keys = base.arrays[name].copy()
    k = d.integer(0, 3)
    bits = base.meta["block_bits"]
    if k == 0 and keys.size >= 2:
        i = d.integer(1, keys.size - 1)
        keys[i] = keys[d.integer(0, i - 1)]
        what = "a key twice"
    elif k == 1 and keys.size:
        keys[d.integer(0, keys.size - 1)] = d.choice((-1, -(2**63)))
        what = "negative"
    elif k == 2 and keys.size:
        off, limit = 1 << 20, 32768 >> bits  # _grid's packing; blocks in [-limit, limit)
        b = d.choice((limit, -limit - 1, off - 1, -off))
        coords = [0, 0, 0]
        coords[d.integer(0, 2)] = b
        x, y, z = (c + off for c in coords)
        keys[d.integer(0, keys.size - 1)] = (x << 42) | (y << 21) | z
        what = f"block {coords} outside the key range"
    else:
        arrays = {**base.arrays, name: keys.astype(np.float64) + 0.5}
        return file_bytes(arrays), f"{name} as floats", True
    arrays = {**base.arrays, name: keys}
    return file_bytes(arrays), f"{name}: {what}", True


def _values(base, d):
    name = _pick_array(d, base, floats=True)
    col = base.arrays[name].copy()
    flat = col.reshape(-1)
    i = d.integer(0, flat.size - 1)
    short = name.rsplit("_", 1)[-1]
    legacy = name == "col_logp"  # float log-probabilities: -inf is still a log-probability
    pool = [np.nan] + ([] if legacy else [np.inf, -np.inf])
    if short in ("prob", "conf"):
        pool += [1.5, -0.1, 1e30]
    elif short == "weight":
        pool += [-1.0, -1e-30]
    v = d.choice(pool)
    flat[i] = v
    arrays = {**base.arrays, name: col}
    return file_bytes(arrays), f"{name}[{i}] = {v}", True


_META_WILD = (
    *WILD_SCALARS,
    1e308,
    -1e308,
    10**400,
    -(10**400),
    "octree-max",
    "tsdf",
    "os:system",
    "numpy:ndarray",
    "antigravity:x",
    "tests.support.toy_backend:LastLabel",
    "/etc/passwd",
    "../../etc/hosts",
    "garden3drms",
    "x" * 300,
    [1, 2, 4],
    {"members": ["r1"]},
)


def meta_value_ok(base: Base, key: str, v) -> bool | None:
    """Would this value of `key` still make a usable file? True / False / None (may be)."""
    from smana.services.mapper.mapfile import KEY_LIMIT, MAX_COUNT

    def number(x, lo, hi):
        return (
            isinstance(x, int | float)
            and not isinstance(x, bool)
            and abs(x) < 1e300
            and lo <= x <= hi
        )

    old = base.meta.get(key, "missing")
    if v == old and type(v) is type(old):
        return True
    if key in ("integrations", "points"):
        return isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= MAX_COUNT
    if key == "smana_version":
        return isinstance(v, str) and len(v) <= 100
    if key == "resolution_m":
        if not number(v, 0.01, 10.0):
            return False
        # the fleet mapper's config names the resolution: another one is refused
        return False if base.fleet else base.meta["max_range_m"] <= 4 * KEY_LIMIT * v
    if key in ("max_range_m", "ray_length_m"):
        if key == "ray_length_m" and v is None:
            return True
        res = base.meta["resolution_m"]
        return number(v, 1e-9, 4 * KEY_LIMIT * res) and v > 0
    sections = ("config", "occupancy", "fusion", "tsdf")  # {} loads with the defaults
    if key in ("backend", "class_table", "format", "fleet", "class_ids", *sections):
        return None if isinstance(v, str | dict | list | int) else False
    return False


def _meta(base, d):
    meta = dict(base.meta)
    k = d.integer(0, 9)
    if k == 0:
        key = d.choice(sorted(meta))
        del meta[key]
        predict = key != "smana_version"
        what = f"no {key}"
    elif k == 1:
        key = d.choice(("extra", "Format", "format ", "\x00", "fleet2"))
        meta[key] = 1
        predict, what = True, f"unknown key {key!r}"
    else:
        key = d.choice(sorted(meta))
        v = d.choice(_META_WILD)
        meta[key] = v
        ok = meta_value_ok(base, key, v)
        predict = None if ok is None else not ok
        what = f"{key} = {str(v)[:40]!r}"
    try:
        text = json.dumps(meta)
    except (ValueError, TypeError):  # a value json cannot write (bytes); NaN and 10**400 it can
        text = json.dumps(base.meta)
        predict, what = False, "unchanged"
    arrays = {**base.arrays, "meta": np.frombuffer(text.encode(), np.uint8)}
    return file_bytes(arrays), what, predict


def _meta_json(base, d):
    text = json.dumps(base.meta).encode()
    k = d.integer(0, 8)
    if k == 0:
        raw, what = text[:-1] + b"\xff}", "invalid UTF-8"
    elif k == 1:
        raw, what = text.replace(b'"points": ', b'"points": NaN, "x": ', 1), "a NaN token"
    elif k == 2:
        raw, what = b"[" * 100_000 + b"]" * 100_000, "deep nesting"
    elif k == 3:
        raw, what = d.choice((b"[]", b"1", b'"x"', b"null", b"")), "not an object"
    elif k == 4:
        raw, what = text[: d.integer(0, len(text) - 1)], "cut short"
    elif k == 5:
        raw, what = text.replace(b'"points": ', b'"points": 1e400, "y": ', 1), "1e400"
    elif k == 6:
        arr = np.frombuffer(text, np.uint8).astype(d.choice(("<u2", "<f4", "|i1")))
        return file_bytes({**base.arrays, "meta": arr}), "meta of another dtype", True
    elif k == 7:
        arr = np.frombuffer(text + b" " * (len(text) % 2), np.uint8).reshape(2, -1)
        return file_bytes({**base.arrays, "meta": arr}), "meta in two rows", True
    else:
        raw, what = text + b" " * (1 << 20), "over 1 MiB"
    return file_bytes({**base.arrays, "meta": np.frombuffer(raw, np.uint8)}), what, True


def _members(base, d):
    arrays = dict(base.arrays)
    k = d.integer(0, 4)
    if k == 0:
        name = d.choice(sorted(arrays))
        del arrays[name]
        return file_bytes(arrays), f"no {name}", True
    if k == 1:
        name = d.choice(("extra", "col_bogus", "layer9_flags", "block_keys2"))
        arrays[name] = np.zeros(3, np.float32)
        return file_bytes(arrays), f"unknown {name}", True
    if k == 2:
        name = d.choice(sorted(arrays))
        members = [(f"{n}.npy", npy_bytes(a)) for n, a in arrays.items()]
        members.append((f"{name}.npy", npy_bytes(np.zeros(2, np.float32))))
        return zip_bytes(members), f"{name} twice", True
    if k == 3:
        members = [(f"{n}.npy", npy_bytes(a)) for n, a in arrays.items()]
        members.append((d.choice(("notes.txt", "meta", "../x.npy", "a/b.npy")), b"hello"))
        return zip_bytes(members), f"non-array member {members[-1][0]!r}", True
    name = d.choice(sorted(arrays))
    pickled = npy_bytes(np.array([{"x": 1}, None], dtype=object), allow_pickle=True)
    return file_bytes({**arrays, name: pickled}), f"{name} pickled", True


def _bomb(base, d):
    members = [(f"{n}.npy", npy_bytes(a)) for n, a in base.arrays.items()]
    entries = [(n, b, zipfile.ZIP_STORED, len(b), zlib.crc32(b)) for n, b in members]
    i = d.integer(0, len(entries) - 1)
    name = entries[i][0]
    k = d.integer(0, 2)
    if k == 0:  # a real bomb: zeros that decompress to BOMB_BYTES
        stream, crc = bomb_stream()
        entries[i] = (name, stream, zipfile.ZIP_DEFLATED, BOMB_BYTES, crc)
        what = f"{name} deflated to {len(stream)} bytes, {BOMB_BYTES} declared"
    elif k == 1:  # a stored member declaring more than it holds
        n, b, _, size, crc = entries[i]
        entries[i] = (n, b, zipfile.ZIP_STORED, d.choice((size + 1, 2**32 - 1, size * 1000)), crc)
        what = f"{name} declares {entries[i][3]} bytes, holds {size}"
    else:  # deflated data that inflates to more than it declares
        n, b, _, size, crc = entries[i]
        c = zlib.compressobj(9, zlib.DEFLATED, -15)
        big = b + bytes(1 << 16)
        entries[i] = (n, c.compress(big) + c.flush(), zipfile.ZIP_DEFLATED, size, crc)
        what = f"{name} inflates past its declared {size} bytes"
        # the reader stops at the declared size (the array and its crc are the base's): loaded
        # as the base or refused, never more memory than declared
        return raw_zip(entries), what, None
    return raw_zip(entries), what, True


_MUTATORS = {
    "valid": _valid,
    "truncate": _truncate,
    "member_short": _member_short,
    "bytes": _bytes,
    "dtype": _dtype,
    "shape": _shape,
    "header": _header,
    "keys": _keys,
    "values": _values,
    "meta": _meta,
    "meta_json": _meta_json,
    "members": _members,
    "bomb": _bomb,
}


# -- loading and judging --------------------------------------------------------------------------


def try_load(path: Path, base: Base, max_bytes: int = FUZZ_MAX_BYTES) -> tuple[str, str]:
    """Load a map file as the mapper would (a fleet map as the fleet mapper does). Returns
    ("loaded", "same" or what differs from the base), ("refused", the message) or ("crash",
    the exception)."""
    from smana.common.config.fleet import FleetConfig
    from smana.common.config.mapper import MapperConfig
    from smana.services.mapper.fleet import FleetMap
    from smana.services.mapper.mapfile import MapFileError
    from smana.services.mapper.semantic_map import SemanticMap

    try:
        if base.fleet:
            mc = MapperConfig(resolution_m=base.meta["resolution_m"], max_range_m=4.0)
            fm = FleetMap.load(
                path, mc, ["r1", "r2"], FleetConfig(robots=["r1", "r2"]), _table(), max_bytes
            )
            got = {}
            for m, layer in enumerate(fm.layers):
                g = layer.grid
                got[f"layer{m}_block_keys"] = g.block_keys[: g.n_blocks]
                got.update({f"layer{m}_{k}": g.used(k) for k in g.cols})
        else:
            sm = SemanticMap.load(path, _table(), base.backend, max_bytes)
            g = sm._core.grid
            got = {"block_keys": g.block_keys[: g.n_blocks]}
            got.update({f"col_{k}": g.used(k) for k in g.cols})
    except MapFileError as exc:
        text = str(exc)
        return ("refused", text) if "\n" not in text else ("crash", f"multi-line: {text!r}")
    except Exception as exc:  # noqa: BLE001 - what the fuzz is for: counted, never raised
        return "crash", f"{type(exc).__name__}: {exc}"[:300]
    diff = _differs(base.expect, got)
    return "loaded", diff or "same"


def _differs(want: dict, got: dict) -> str:
    for k, v in want.items():
        if k not in got:
            return f"no {k}"
        a = got[k]
        if a.shape != v.shape or a.dtype != v.dtype or not np.array_equal(a, v):
            return f"{k} differs"
    return ""


@cache
def _table():
    from smana.common.classes import ClassTable

    return ClassTable.load(CLASS_TABLE)
