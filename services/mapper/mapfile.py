"""Map files (`.npz`) checked before use: the one reader behind `SemanticMap.load` and
`FleetMap.load`.

A map file is a zip of `.npy` arrays (`np.savez`): `meta` (JSON text as uint8), `block_keys`,
`col_<field>` per voxel column of the back-end and, in a fleet map, `layer<m>_block_keys` and
`layer<m>_<field>` per member. Nothing in a file is trusted. In this order:

1. the container: a regular file under `max_bytes`, a zip whose members are distinct `.npy`
   names (stored or deflated), each `.npy` header read with `numpy.lib.format` without reading
   the array; the size a header declares (shape x item size) must be exactly the member's size
   in the zip directory, and the members together under `max_bytes`, so that no array is
   allocated before its size is known to be sane (a header declaring terabytes, a zip bomb);
2. `meta`: at most `MAX_META_BYTES` of strict JSON (no NaN, no Infinity), every key known and of
   its type, numbers finite and in range (`check_meta`), the back-end a registered name (a file
   never makes smana import a module it names, unless the caller trusts that spec);
3. every array against what the back-end declares: the member set exactly, dtypes exactly (no
   complex, no object, no other byte order), shapes exactly (one row per voxel of the blocks:
   no broadcast), only then read;
4. values: block keys inside the key range and distinct, float columns finite, probabilities
   and confidences in [0, 1], weights >= 0.

Any failure is a `MapFileError` (a `ValueError`) of one line naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import os
import stat
import struct
import tokenize
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.lib import format as npy

from smana.common.config.mapper import RESOLUTION_RANGE_M, max_range_for
from smana.common.config.section import build
from smana.services.mapper.block_grid import KEY_LIMIT, PACK_MASK, PACK_OFF

MAX_MAP_BYTES = 4 << 30  # a map file (and its arrays together) at most this big: 4 GiB
MAX_META_BYTES = 1 << 20
MAX_MEMBERS = 4096  # arrays in one file (a fleet map has 1 + 5 per member)
MAX_COUNT = 2**63 - 1  # integrations, points, deltas: int64
MAX_NAME = 255
# 2: the back-end's config section under "config"; 1 (still read): the octrees' under
# "occupancy" and "fusion", the TSDF's under "tsdf"
FORMAT_VERSION = 2
FORMATS = (1, FORMAT_VERSION)
FRAMES = ("world", "start_pose")
BLOCK_BITS = (2, 3, 4)
# What reading a broken zip or npy member can raise besides ValueError: all mean "broken file"
_BROKEN = (OSError, EOFError, zipfile.BadZipFile, zlib.error, struct.error, NotImplementedError)
# What numpy's header parser (a Python literal, tokenized then evaluated) raises on bad text
_BAD_TEXT = (ValueError, TypeError, SyntaxError, RecursionError, tokenize.TokenError)


class MapFileError(ValueError):
    """A map file that cannot be used; the message is one line naming the file."""


@dataclass(frozen=True)
class Member:
    """One `.npy` array in the zip, as its header declares it."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    fortran: bool


def _fail(path, why: str) -> MapFileError:
    return MapFileError(f"{path}: not a smana map file ({' '.join(why.split())})")


class MapFile:
    """An open map file whose container and headers have been checked (step 1); `meta()` and
    `array()` read what is in it. Use as a context manager."""

    def __init__(self, path: str | Path, max_bytes: int = MAX_MAP_BYTES):
        self.path = Path(path)
        self.max_bytes = max_bytes
        try:
            st = os.stat(self.path)
        except OSError as exc:
            raise _fail(self.path, exc.strerror or str(exc)) from None
        if not stat.S_ISREG(st.st_mode):
            raise _fail(self.path, "not a regular file")
        if st.st_size > max_bytes:
            raise _fail(self.path, f"{st.st_size} bytes > the limit {max_bytes}")
        self.size = st.st_size
        try:
            self._zip = zipfile.ZipFile(self.path)
        except (*_BROKEN, ValueError) as exc:
            raise _fail(self.path, f"not a zip of arrays ({_why(exc)})") from None
        try:
            self.members = self._scan()
        except BaseException:
            self._zip.close()
            raise

    def __enter__(self) -> MapFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()

    def _scan(self) -> dict[str, Member]:
        infos = self._zip.infolist()
        if len(infos) > MAX_MEMBERS:
            raise _fail(self.path, f"{len(infos)} members > {MAX_MEMBERS}")
        members: dict[str, Member] = {}
        total = 0
        for info in infos:
            fname = info.filename
            if not fname.endswith(".npy") or len(fname) > MAX_NAME + 4:
                raise _fail(self.path, f"member {fname[:80]!r} is not an .npy array")
            name = fname[:-4]
            if name in members:
                raise _fail(self.path, f"member {fname!r} twice")
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
                raise _fail(self.path, f"{fname}: compression {info.compress_type} not supported")
            if info.flag_bits & 0x1:
                raise _fail(self.path, f"{fname}: encrypted")
            if info.compress_type == zipfile.ZIP_STORED and info.compress_size != info.file_size:
                raise _fail(self.path, f"{fname}: stored size {info.compress_size} != its size")
            if info.header_offset + info.compress_size > self.size:
                raise _fail(self.path, f"{fname}: runs past the end of the file (truncated?)")
            total += info.file_size
            if total > self.max_bytes:
                raise _fail(self.path, f"its arrays declare more than {self.max_bytes} bytes")
            members[name] = self._header(info, name)
        return members

    def _header(self, info: zipfile.ZipInfo, name: str) -> Member:
        """The member's .npy header, read without its data; its declared size checked."""
        try:
            with self._zip.open(info) as fp:
                version = npy.read_magic(fp)
                if version == (1, 0):
                    shape, fortran, dtype = npy.read_array_header_1_0(fp)
                elif version == (2, 0):
                    shape, fortran, dtype = npy.read_array_header_2_0(fp)
                else:
                    raise ValueError(f"npy version {version} not supported")
                header = fp.tell()  # magic, length and header text: where the data starts
        except (*_BROKEN, *_BAD_TEXT, KeyError) as exc:
            raise _fail(self.path, f"{name}: broken .npy header ({_why(exc)})") from None
        if dtype.hasobject or dtype.kind not in "biuf" or dtype.fields is not None:
            raise _fail(self.path, f"{name}: dtype {dtype.str} is not a plain number type")
        if not all(isinstance(d, int) and d >= 0 for d in shape):
            raise _fail(self.path, f"{name}: shape {shape!r}")
        nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        if nbytes > self.max_bytes:
            raise _fail(self.path, f"{name}: declares {nbytes} bytes > the limit {self.max_bytes}")
        if header + nbytes != info.file_size:
            raise _fail(
                self.path,
                f"{name}: its header declares {nbytes} bytes of data, the zip holds "
                f"{info.file_size - header}",
            )
        return Member(name, dtype, tuple(shape), bool(fortran))

    def check(self, name: str, dtypes: tuple, shape: tuple[int, ...]) -> Member:
        """The member `name`, which must exist with one of `dtypes` and this shape."""
        mem = self.members.get(name)
        if mem is None:
            raise _fail(self.path, f"no array {name!r}")
        if not any(mem.dtype == np.dtype(d) for d in dtypes):
            want = " or ".join(np.dtype(d).str for d in dtypes)
            raise _fail(self.path, f"{name}: dtype {mem.dtype.str}, expected {want}")
        if mem.shape != shape:
            raise _fail(self.path, f"{name}: shape {mem.shape}, expected {shape}")
        return mem

    def array(self, name: str) -> np.ndarray:
        """The array `name` (its header checked when the file was opened)."""
        info = self._zip.getinfo(name + ".npy")
        try:
            with self._zip.open(info) as fp:
                a = npy.read_array(fp, allow_pickle=False)
        except (*_BROKEN, ValueError, RuntimeError) as exc:
            raise _fail(self.path, f"{name}: unreadable ({_why(exc)})") from None
        mem = self.members[name]
        if a.dtype != mem.dtype or a.shape != mem.shape:  # pragma: no cover - numpy's promise
            raise _fail(self.path, f"{name}: read back as {a.dtype.str} {a.shape}")
        return np.ascontiguousarray(a)

    def meta(self) -> dict:
        """The metadata as JSON (checked for its syntax here, its content by `check_meta`)."""
        mem = self.members.get("meta")
        if mem is None:
            raise _fail(self.path, "no array 'meta'")
        if mem.dtype != np.uint8 or len(mem.shape) != 1 or mem.shape[0] > MAX_META_BYTES:
            raise _fail(self.path, f"meta: {mem.dtype.str} {mem.shape}, expected short uint8 text")
        raw = self.array("meta").tobytes()
        try:
            meta = json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise _fail(self.path, f"meta: not JSON ({_why(exc)})") from None
        if not isinstance(meta, dict):
            raise _fail(self.path, f"meta: expected a JSON object, got {type(meta).__name__}")
        return meta


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number")


# -- the metadata ----------------------------------------------------------------------------------

_KEYS = {
    "format",
    "backend",
    "resolution_m",
    "max_range_m",
    "ray_length_m",
    "class_table",
    "class_ids",
    "block_bits",
    "integrations",
    "points",
}
_OPTIONAL = {"smana_version", "fleet"}  # smana_version: files before it have none
_BY_FORMAT = {1: {"occupancy", "fusion", "tsdf"}, 2: {"config"}}
_FLEET_KEYS = {"members", "frame", "poses", "deltas_applied", "replaced"}


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    return abs(v) <= 1e300 if isinstance(v, int) else math.isfinite(v)  # 10**400: no float


def _count(path, key: str, v) -> int:
    if not (_is_int(v) and 0 <= v <= MAX_COUNT):
        raise _fail(path, f"meta.{key}: expected a count, got {_show(v)}")
    return v


def _number(path, key: str, v, lo: float, hi: float) -> float:
    if not (_is_number(v) and lo <= v <= hi):
        raise _fail(path, f"meta.{key}: expected a number in [{lo:g}, {hi:g}], got {_show(v)}")
    return float(v)


def _show(v) -> str:
    text = json.dumps(v) if not isinstance(v, float) else repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _section(path, key: str, v, config_class) -> dict | None:
    """A back-end's saved config section: the config's own checks, and finite numbers."""
    if config_class is None:
        if v is not None:
            raise _fail(path, f"meta.{key}: the back-end takes no config, got {_show(v)}")
        return None
    if not isinstance(v, dict):
        raise _fail(path, f"meta.{key}: expected an object, got {_show(v)}")
    for k, x in v.items():
        if isinstance(x, float) and not math.isfinite(x):  # pragma: no cover - strict JSON
            raise _fail(path, f"meta.{key}.{k}: not finite")
        if isinstance(x, int | float) and not isinstance(x, bool) and abs(x) > 1e300:
            raise _fail(path, f"meta.{key}.{k}: {_show(x)} out of range")
    try:
        build(config_class, v, f"meta.{key}.")
    except (ValueError, TypeError) as exc:
        raise _fail(path, str(exc)) from None
    return v


def check_meta(meta: dict, path, trusted_backend: str | None = None) -> dict:
    """The checked metadata: every key known and of its type, in range. Returns it with the
    back-end's config section under "config" (a format-1 file's two sections merged)."""
    from smana.common.classes import bundled_tables
    from smana.services.mapper.backends import BACKENDS, backend_class

    fmt = meta.get("format")
    if not (_is_int(fmt) and fmt in FORMATS):
        raise _fail(path, f"unsupported map format {_show(fmt)} (known: {list(FORMATS)})")
    allowed = _KEYS | _OPTIONAL | _BY_FORMAT[fmt]
    missing = sorted((_KEYS | _BY_FORMAT[fmt]) - set(meta))
    unknown = sorted(set(meta) - allowed)
    if missing or unknown:
        what = (f"missing {missing}" if missing else "") + (
            f"{'; ' if missing else ''}unknown {[k[:40] for k in unknown[:5]]}" if unknown else ""
        )
        raise _fail(path, f"meta: {what}")
    name = meta["backend"]
    if not isinstance(name, str) or not name or len(name) > MAX_NAME:
        raise _fail(path, f"meta.backend: expected a back-end name, got {_show(name)}")
    if name not in BACKENDS and name != trusted_backend:
        # a module:Class spec is imported only when the caller (its config) names it itself
        known = ", ".join(repr(n) for n in BACKENDS)
        raise _fail(path, f"meta.backend {_show(name)} is none of the known back-ends ({known})")
    try:
        backend = backend_class(name)
    except ValueError as exc:
        raise _fail(path, str(exc)) from None
    out = dict(meta)
    res = _number(path, "resolution_m", meta["resolution_m"], *RESOLUTION_RANGE_M)
    extent = max_range_for(res)
    _number(path, "max_range_m", meta["max_range_m"], 1e-9, extent)
    if meta["ray_length_m"] is not None:
        _number(path, "ray_length_m", meta["ray_length_m"], 1e-9, extent)
    table = meta["class_table"]
    if not isinstance(table, str) or table not in bundled_tables():
        # a path here would make the loader read any file the map names
        raise _fail(path, f"meta.class_table {_show(table)} is not a bundled table: pass the table")
    ids = meta["class_ids"]
    if not (isinstance(ids, list) and len(ids) <= 65536 and all(_is_int(i) for i in ids)):
        raise _fail(path, f"meta.class_ids: expected a list of integers, got {_show(ids)}")
    if not (_is_int(meta["block_bits"]) and meta["block_bits"] in BLOCK_BITS):
        raise _fail(path, f"meta.block_bits: expected one of {list(BLOCK_BITS)}")
    _count(path, "integrations", meta["integrations"])
    _count(path, "points", meta["points"])
    version = meta.get("smana_version", "")
    if not isinstance(version, str) or len(version) > 100:
        raise _fail(path, f"meta.smana_version: expected a short string, got {_show(version)}")
    if fmt == 1:  # the octrees' section was two tables, the TSDF's its own; both checked
        from smana.services.mapper.backends.occupancy import OctreeConfig
        from smana.services.mapper.backends.tsdf import TsdfConfig

        for key in ("occupancy", "fusion", "tsdf"):
            if not isinstance(meta[key], dict):
                raise _fail(path, f"meta.{key}: expected an object, got {_show(meta[key])}")
        octree = _section(path, "occupancy", {**meta["occupancy"], **meta["fusion"]}, OctreeConfig)
        tsdf = _section(path, "tsdf", meta["tsdf"], TsdfConfig)
        out["config"] = tsdf if backend.config_key == "tsdf" else octree
        if backend.config_class is None:
            out["config"] = None
    else:
        _section(path, "config", meta["config"], backend.config_class)
    if "fleet" in meta:
        check_fleet_meta(meta["fleet"], path)
    return out


def check_fleet_meta(fleet, path) -> None:
    if not isinstance(fleet, dict) or set(fleet) != _FLEET_KEYS:
        raise _fail(path, f"meta.fleet: expected an object with {sorted(_FLEET_KEYS)}")
    members = fleet["members"]
    ok = isinstance(members, list) and len(members) <= (MAX_MEMBERS - 3) // 5
    if not (ok and all(isinstance(x, str) and 0 < len(x) <= MAX_NAME for x in members)):
        raise _fail(path, f"meta.fleet.members: expected a list of names, got {_show(members)}")
    if len(set(members)) != len(members):
        raise _fail(path, "meta.fleet.members: a name twice")
    if fleet["frame"] not in FRAMES:
        raise _fail(path, f"meta.fleet.frame: expected one of {list(FRAMES)}")
    n = len(members)
    for key in ("deltas_applied", "replaced"):
        v = fleet[key]
        if not (isinstance(v, list) and len(v) == n):
            raise _fail(path, f"meta.fleet.{key}: expected {n} counts, got {_show(v)}")
        for x in v:
            _count(path, f"fleet.{key}", x)
    poses = fleet["poses"]
    if not (isinstance(poses, list) and len(poses) == n):
        raise _fail(path, f"meta.fleet.poses: expected {n} poses, got {_show(poses)}")
    for p in poses:
        if p is not None and not (
            isinstance(p, list) and len(p) == 4 and all(_is_number(x) for x in p)
        ):
            raise _fail(path, f"meta.fleet.poses: expected null or 4 numbers, got {_show(p)}")


# -- the arrays ------------------------------------------------------------------------------------

# A fleet map's layer per member (`FleetMap`): its columns, beside `layer<m>_block_keys`
LAYER = {
    "logodds": (np.float32, ()),
    "label": (np.uint16, ()),
    "conf": (np.float32, ()),
    "flags": (np.uint8, ()),
}


def layer_names(n_members: int) -> set[str]:
    """The arrays a fleet map file adds for its members."""
    return {f"layer{m}_{k}" for m in range(n_members) for k in ("block_keys", *LAYER)}


# Value ranges of columns by name (every float column must be finite besides)
_RANGES = {"prob": (0.0, 1.0), "conf": (0.0, 1.0), "weight": (0.0, math.inf)}


def check_members(f: MapFile, expected: set[str]) -> None:
    """The file holds exactly these arrays (no unknown one, none missing)."""
    have = set(f.members)
    if have != expected:
        missing, unknown = sorted(expected - have), sorted(have - expected)
        what = (f"missing {missing[:5]}" if missing else "") + (
            f"{'; ' if missing else ''}unknown {[u[:40] for u in unknown[:5]]}" if unknown else ""
        )
        raise _fail(f.path, f"arrays: {what}")


def check_grid(
    f: MapFile, keys_name: str, prefix: str, fields: dict, bits: int, legacy: set[str] = frozenset()
) -> None:
    """The headers of one block grid's arrays: block keys (int64, one dimension) and a column
    per field (`fields`: name -> (dtype, trailing shape)) of one row per voxel of those blocks.
    A column in `legacy` may also be float32 (a layout a loader of the back-end converts)."""
    mem = f.members.get(keys_name)
    if mem is None:
        raise _fail(f.path, f"no array {keys_name!r}")
    if len(mem.shape) != 1:
        raise _fail(f.path, f"{keys_name}: shape {mem.shape}, expected one dimension")
    n = mem.shape[0]
    f.check(keys_name, (np.int64,), (n,))
    vpb = 1 << (3 * bits)
    for k, (dt, shape) in fields.items():
        dts = (dt, np.float32) if k in legacy else (dt,)
        f.check(prefix + k, dts, (n * vpb, *shape))


def read_grid(
    f: MapFile, keys_name: str, prefix: str, fields: dict, bits: int, legacy: set[str] = frozenset()
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Block keys and voxel columns of one block grid, their headers checked (`check_grid`)
    before they are read, their values after."""
    check_grid(f, keys_name, prefix, fields, bits, legacy)
    block_keys = f.array(keys_name)
    check_block_keys(block_keys, bits, f.path, keys_name)
    cols = {}
    for k in fields:
        col = f.array(prefix + k)
        try:
            check_values(col, k, prefix, k in legacy)
        except ValueError as exc:
            raise _fail(f.path, str(exc)) from None
        cols[k] = col
    return block_keys, cols


def check_values(col: np.ndarray, field: str, prefix: str = "", legacy: bool = False) -> None:
    """A voxel column's values: finite floats, within the field's range (`_RANGES`); else a
    ValueError of one line. The one check for every way into a map: map files, journal records
    (journal.py), block-store regions (blockstore.py)."""
    if col.dtype.kind != "f":
        return
    bad = np.isnan(col) if legacy else ~np.isfinite(col)
    if bad.any():
        raise ValueError(f"{prefix}{field}: {int(bad.sum())} values not finite")
    lo, hi = _RANGES.get(field, (-math.inf, math.inf))
    if col.size and (col.min() < lo or col.max() > hi):
        raise ValueError(f"{prefix}{field}: values outside [{lo:g}, {hi:g}]")


def check_block_keys(keys: np.ndarray, bits: int, path, name: str = "block_keys") -> None:
    """Packed block keys (21 bits an axis) inside the map's key range, each once."""
    if keys.size == 0:
        return
    if keys.min() < 0:
        raise _fail(path, f"{name}: negative packed keys")
    limit = KEY_LIMIT >> bits
    for shift in (42, 21, 0):
        b = ((keys >> shift) & PACK_MASK) - PACK_OFF
        if b.min() < -limit or b.max() >= limit:
            raise _fail(path, f"{name}: blocks outside the key range +-{limit}")
    if np.unique(keys).shape[0] != keys.shape[0]:
        raise _fail(path, f"{name}: a block twice")


__all__ = [
    "MAX_MAP_BYTES",
    "MapFile",
    "MapFileError",
    "LAYER",
    "check_block_keys",
    "check_grid",
    "layer_names",
    "check_members",
    "check_meta",
    "check_values",
    "max_range_for",
    "read_grid",
]
