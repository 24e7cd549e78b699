"""The validating codec of every message: msgpack on the wire, JSON for queries typed by hand.

Decoding checks every field against its schema (`message_schema.py`) and raises one error type,
`MessageError`, whose `kind` names what was wrong; nothing a remote peer sends can crash it.
Code imports it from `smana.common.messages`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from typing import Any

import msgpack
import numpy as np

from smana.common.message_schema import (
    INT_LIMIT,
    MAX_PAYLOAD_BYTES,
    REGISTRY,
    SCHEMA_VERSION,
    ArraySpec,
    Message,
    MessageError,
)


def _fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("local")]


def _array_to_wire(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def encode(msg: Message) -> bytes:
    """Serialise a message to msgpack bytes."""
    out: dict[str, Any] = {"_type": msg.TYPE, "_v": msg.VERSION}
    over = msg.wire_overrides()
    for f in _fields(type(msg)):
        v = over[f.name] if f.name in over else getattr(msg, f.name)
        out[f.name] = _array_to_wire(np.asarray(v)) if "array" in f.metadata else _plain(v)
    return msgpack.packb(out, use_bin_type=True)


def json_default(o):
    """`default=` for json.dumps and msgpack.packb: numpy scalars and arrays as plain values."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"cannot encode {type(o).__name__}")


def _plain(v):
    """numpy scalars and containers of them to plain Python (msgpack and JSON want these)."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, dict):
        return {(k if isinstance(k, str) else str(k)): _plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v


def decode(
    payload: bytes | bytearray | memoryview,
    expect: type[Message] | tuple[type[Message], ...] | None = None,
    *,
    drop_nonfinite: bool = False,
    max_bytes: int = MAX_PAYLOAD_BYTES,
) -> Message:
    """Parse and validate msgpack bytes. With `drop_nonfinite`, per-point rows holding NaN/inf (or
    coordinates beyond COORD_LIMIT_M) are removed (a SemanticCloud records how many in
    `n_dropped_nonfinite`) instead of rejected. Every failure is a MessageError."""
    if len(payload) > max_bytes:
        raise MessageError("oversize", f"{len(payload)} bytes > limit {max_bytes}")
    try:
        raw = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise MessageError("malformed", f"not msgpack: {exc}") from None
    return from_dict(raw, expect, drop_nonfinite=drop_nonfinite, wire=True)


def to_json(msg: Message) -> bytes:
    """The JSON form: same fields, arrays as nested lists."""
    out: dict[str, Any] = {"_type": msg.TYPE, "_v": msg.VERSION}
    over = msg.wire_overrides()
    for f in _fields(type(msg)):
        out[f.name] = _plain(over[f.name] if f.name in over else getattr(msg, f.name))
    return json.dumps(out, allow_nan=False).encode()


def from_json(
    payload: bytes | str, expect=None, *, drop_nonfinite=False, max_bytes=MAX_PAYLOAD_BYTES
) -> Message:
    """Parse a JSON message. `_type` and `_v` may be omitted when `expect` names one type (so a
    user can type `{"start": [0, 0], "goal": [5, 3]}` into any zenoh tool)."""
    if len(payload) > max_bytes:
        raise MessageError("oversize", f"{len(payload)} bytes > limit {max_bytes}")
    try:
        raw = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise MessageError("malformed", f"not JSON: {type(exc).__name__}: {exc}") from None
    if isinstance(raw, dict) and isinstance(expect, type):
        raw.setdefault("_type", expect.TYPE)
        raw.setdefault("_v", expect.VERSION)
    return from_dict(raw, expect, drop_nonfinite=drop_nonfinite, wire=False)


def from_dict(raw, expect=None, *, drop_nonfinite=False, wire=True) -> Message:
    """Validate a decoded map (msgpack wire form, or JSON form with `wire=False`)."""
    try:
        return _from_dict(raw, expect, drop_nonfinite, wire)
    except MessageError:
        raise
    except Exception as exc:  # a check this codec lacks: still a rejection, never a crash
        raise MessageError("malformed", f"{type(exc).__name__}: {exc}") from None


def _from_dict(raw, expect, drop_nonfinite: bool, wire: bool) -> Message:
    if not isinstance(raw, dict) or not isinstance(raw.get("_type"), str):
        raise MessageError("malformed", "expected a map with a '_type' field")
    tname = raw["_type"]
    cls = REGISTRY.get(tname)
    if cls is None:
        raise MessageError("type", f"unknown message type {tname!r}")
    if expect is not None:
        allowed = expect if isinstance(expect, tuple) else (expect,)
        if cls not in allowed:
            names = ", ".join(c.TYPE for c in allowed)
            raise MessageError("type", f"expected {names}, got {tname}")
    version = raw.get("_v")
    if type(version) is not int or not SCHEMA_VERSION <= version <= cls.VERSION:  # not True, 1.0
        speaks = f"v{cls.VERSION}" if cls.VERSION == SCHEMA_VERSION else f"v1 to v{cls.VERSION}"
        raise MessageError("version", f"{tname} v{version!r}, this build speaks {speaks}")

    # the fields of this version: a newer field is absent from an older message (then unknown)
    fields = {f.name: f for f in _fields(cls) if f.metadata.get("since", 1) <= version}
    unknown = set(raw) - set(fields) - {"_type", "_v"}
    if unknown:
        raise MessageError("unknown_field", f"{tname} has no field(s) {sorted(unknown)}")
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in raw:
            if not wire and name in cls.JSON_OPTIONAL:
                continue
            raise MessageError("missing_field", f"{tname}.{name}")
        if "array" in f.metadata:
            values[name] = _check_array(tname, name, raw[name], f.metadata["array"], wire)
        else:
            rng = f.metadata.get("range", (None, None))
            values[name] = _check_scalar(tname, name, raw[name], hints[name], rng)
    msg = cls(**values)
    if version < cls.VERSION:
        msg.upgrade(version)
    _check_groups(tname, msg, drop_nonfinite)
    msg.check()
    return msg


def _check_array(tname, name, v, spec: ArraySpec, wire: bool) -> np.ndarray:
    where = f"{tname}.{name}"
    if wire:
        if not isinstance(v, dict) or set(v) != {"dtype", "shape", "data"}:
            raise MessageError("malformed", f"{where}: expected {{dtype, shape, data}}")
        try:
            dt = np.dtype(v["dtype"])
        except (TypeError, ValueError):
            raise MessageError("dtype", f"{where}: unknown dtype {v['dtype']!r}") from None
        if dt.str not in spec.dtypes:
            raise MessageError("dtype", f"{where}: dtype {dt.str}, allowed {list(spec.dtypes)}")
        shape = v["shape"]
        # Python integers throughout, before anything is allocated: a product taken in int64
        # wraps ([2**32, 2**32] is 0) and would let a claimed shape past the length check.
        if not isinstance(shape, list) or not all(
            type(s) is int and 0 <= s <= MAX_PAYLOAD_BYTES for s in shape
        ):
            raise MessageError("shape", f"{where}: shape must be a list of non-negative ints")
        if len(shape) not in {len(s) for s in spec.allowed_shapes()}:
            raise MessageError("shape", f"{where}: shape {shape}, expected {_fmt(spec)}")
        data = v["data"]
        if not isinstance(data, bytes | bytearray):
            raise MessageError("malformed", f"{where}: data must be bytes")
        if len(data) != math.prod(shape) * dt.itemsize:
            raise MessageError(
                "shape", f"{where}: {len(data)} bytes do not hold shape {shape} of {dt.str}"
            )
        a = np.frombuffer(data, dt).reshape(shape)
    else:
        try:
            a = np.asarray(v, dtype=np.dtype(spec.dtypes[0]))
        except (TypeError, ValueError, OverflowError):
            raise MessageError("value", f"{where}: not an array of {spec.dtypes[0]}") from None
        if a.size == 0 and len(spec.shape) > 1:
            a = a.reshape((0, *spec.shape[1:]))
    if not any(_shape_ok(a.shape, s) for s in spec.allowed_shapes()):
        raise MessageError("shape", f"{where}: shape {list(a.shape)}, expected {_fmt(spec)}")
    if spec.group is None:
        if spec.finite and a.dtype.kind == "f" and not np.isfinite(a).all():
            raise MessageError("nonfinite", f"{where}: NaN or inf")
        if spec.limit is not None and a.size and np.abs(a).max() > spec.limit:
            raise MessageError("value", f"{where}: a value beyond +-{spec.limit:g}")
    return a


def _shape_ok(shape, want) -> bool:
    if len(shape) != len(want):
        return False
    return all(w is None or s == w for s, w in zip(shape, want, strict=True))


def _fmt(spec: ArraySpec) -> str:
    return " or ".join(str([("N" if d is None else d) for d in s]) for s in spec.allowed_shapes())


def _check_groups(tname, msg: Message, drop_nonfinite: bool) -> None:
    """Arrays of one group must share their first dimension; their float rows must be finite and
    within their limit. With `drop_nonfinite` the bad rows are removed instead."""
    groups: dict[str, list[tuple[str, ArraySpec]]] = {}
    for f in _fields(type(msg)):
        spec = f.metadata.get("array")
        if spec is not None and spec.group is not None:
            groups.setdefault(spec.group, []).append((f.name, spec))
    for members in groups.values():
        lengths = {name: len(getattr(msg, name)) for name, _ in members}
        if len(set(lengths.values())) > 1:
            raise MessageError("length", f"{tname}: array lengths disagree {lengths}")
        checked = [
            (name, spec)
            for name, spec in members
            if spec.finite and getattr(msg, name).dtype.kind == "f" and getattr(msg, name).size
        ]
        if all(_all_within(getattr(msg, name), spec.limit) for name, spec in checked):
            continue  # the usual case, two reductions per array: no row to drop
        nonfinite = beyond = None
        for name, spec in checked:
            a = getattr(msg, name)
            flat = a.reshape(len(a), -1)
            rows = ~np.isfinite(flat).all(axis=1)
            nonfinite = rows if nonfinite is None else nonfinite | rows
            if spec.limit is not None:
                with np.errstate(invalid="ignore"):
                    far = (np.abs(flat) > spec.limit).any(axis=1)
                beyond = far if beyond is None else beyond | far
        bad = nonfinite if beyond is None else (beyond if nonfinite is None else nonfinite | beyond)
        if bad is None or not bad.any():
            continue
        if not drop_nonfinite:
            if nonfinite is not None and nonfinite.any():
                raise MessageError(
                    "nonfinite", f"{tname}: {int(nonfinite.sum())} rows hold NaN or inf"
                )
            raise MessageError("value", f"{tname}: {int(beyond.sum())} rows beyond their limit")
        keep = ~bad
        for name, _ in members:
            setattr(msg, name, getattr(msg, name)[keep])
        if hasattr(msg, "n_dropped_nonfinite"):
            msg.n_dropped_nonfinite = int(bad.sum())


def _all_within(a: np.ndarray, limit: float | None) -> bool:
    """Every value finite (and within +-limit), from the array's minimum and maximum: NaN
    propagates into both and fails every comparison, inf fails the bound."""
    lo, hi = float(a.min()), float(a.max())
    bound = math.inf if limit is None else limit
    return -bound <= lo and hi <= bound and math.isfinite(lo) and math.isfinite(hi)


_SCALARS = {float: (int, float), int: (int,), str: (str,), bool: (bool,), dict: (dict,)}


def _check_scalar(tname, name, v, hint, rng=(None, None)):
    where = f"{tname}.{name}"
    optional = isinstance(hint, types.UnionType) and type(None) in typing.get_args(hint)
    if optional:
        if v is None:
            return None
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    ok_types = _SCALARS.get(hint, (object,))
    if isinstance(v, bool) and hint is not bool:
        raise MessageError("value", f"{where}: expected {hint.__name__}, got bool")
    if not isinstance(v, ok_types):
        raise MessageError("value", f"{where}: expected {hint.__name__}, got {type(v).__name__}")
    if hint is float:
        v = float(v)
        if not math.isfinite(v):
            raise MessageError("nonfinite", f"{where}: NaN or inf")
    if hint is int and not -INT_LIMIT <= v <= INT_LIMIT:
        raise MessageError("value", f"{where}: {v} does not fit int64")
    lo, hi = rng
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise MessageError("value", f"{where}: {v!r} outside [{lo}, {hi}]")
    if hint is dict:
        _check_dict_values(where, v)
    return v


def _check_dict_values(where, d: dict) -> None:
    for k, x in d.items():
        if isinstance(x, float) and not math.isfinite(x):
            raise MessageError("nonfinite", f"{where}[{k!r}]: NaN or inf")
        if isinstance(x, dict):
            _check_dict_values(f"{where}[{k!r}]", x)
