"""A second, deliberately naive statement of the message schemas (docs/architecture.md), to judge
the codec by: `violations(raw, expect)` lists every rule a decoded msgpack map breaks (the codec
must report one of them, and accept the map when there are none); `check_decoded(msg)` says what
is wrong with a message the codec let through.

Nothing here calls the codec or reads its field metadata: the schema is written out again below,
field by field, from the documentation. Slow and obvious on purpose (stumpy's `tests/naive.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_BYTES = 64 * 1024 * 1024
COORD = 1.0e6
STAMP = 1.0e10
I64 = 2**63 - 1


@dataclass(frozen=True)
class Num:
    lo: float | None = None
    hi: float | None = None
    optional: bool = False


@dataclass(frozen=True)
class Int:
    lo: int = -I64
    hi: int = I64


@dataclass(frozen=True)
class Str:
    pass


@dataclass(frozen=True)
class OneOf:
    choices: tuple[str, ...]


@dataclass(frozen=True)
class Bool:
    pass


@dataclass(frozen=True)
class Map:
    pass


@dataclass(frozen=True)
class Costs:  # PathRequest.class_costs: {class id: cost}
    pass


@dataclass(frozen=True)
class Arr:
    dtypes: tuple[str, ...]
    shapes: tuple[tuple[int | None, ...], ...]  # None: the group's length (or free)
    group: str | None = None
    limit: float | None = None


STAMP_S, SEQ = Num(0.0, STAMP), Int(0, I64)
F4, F8, U1, U2, I4 = "<f4", "<f8", "|u1", "<u2", "<i4"

SCHEMA: dict[str, dict[str, object]] = {
    "Pose": {
        "stamp_s": STAMP_S,
        "seq": SEQ,
        "position": Arr((F8,), ((3,),), limit=COORD),
        "orientation_xyzw": Arr((F8,), ((4,),)),
        "frame_id": Str(),
    },
    "SemanticCloud": {
        "stamp_s": STAMP_S,
        "seq": SEQ,
        "points": Arr((F4,), ((None, 3),), "n", COORD),
        "labels": Arr((U1, U2), ((None,),), "n"),
        "confidences": Arr((F4,), ((None,),), "n"),
        "sensor_position": Arr((F8,), ((3,),), limit=COORD),
        "sensor_orientation_xyzw": Arr((F8,), ((4,),)),
        "frame_id": Str(),
        "source": Str(),
    },
    "VelocityCommand": {
        "stamp_s": STAMP_S,
        "seq": SEQ,
        "linear_mps": Num(-100, 100),
        "angular_radps": Num(-100, 100),
        "source": Str(),
    },
    "MapDelta": {
        "stamp_s": STAMP_S,
        "seq": SEQ,
        "cloud_seq": SEQ,
        "backend": Str(),
        "resolution_m": Num(1e-3, 100),
        "centres": Arr((F4,), ((None, 3),), "m", COORD),
        "labels": Arr((U2,), ((None,),), "m"),
        "confidences": Arr((F4,), ((None,),), "m"),
        "occupied": Arr((U1,), ((None,),), "m"),
        "values": Arr((F4,), ((None,),), "m", COORD),
        "producer": Str(),
        "values_kind": OneOf(("log_odds", "signed_distance")),
        "alt_labels": Arr((U2,), ((None,),), "m"),
        "alt_confidences": Arr((F4,), ((None,),), "m"),
    },
    "GraphPatch": {
        "stamp_s": STAMP_S,
        "seq": SEQ,
        "resolution_m": Num(1e-3, 100),
        "origin_xy": Arr((F8,), ((2,),), limit=COORD),
        "cells": Arr((I4,), ((None, 2),), "k"),
        "labels": Arr((U2,), ((None,),), "k"),
        "heights": Arr((F4,), ((None,),), "k", COORD),
        "flags": Arr((U1,), ((None,),), "k"),
        "producer": Str(),
        "alt_labels": Arr((U2,), ((None,),), "k"),
        "p_label": Arr((U1,), ((None,),), "k"),
        "p_alt": Arr((U1,), ((None,),), "k"),
    },
    "PathRequest": {
        "request_id": Str(),
        "start": Arr((F8,), ((2,), (3,)), limit=COORD),
        "goal": Arr((F8,), ((2,), (3,)), limit=COORD),
        "h_f": Num(0, 1e6, True),
        "t_f": Num(0, 1e6, True),
        "class_costs": Costs(),
        "allow_unknown": Bool(),
        "unknown_cost": Num(0, 1e6),
        "max_step_m": Num(0, 1e6, True),
    },
    "PathReply": {
        "request_id": Str(),
        "ok": Bool(),
        "error": Str(),
        "message": Str(),
        "path": Arr((F4,), ((None, 3),)),
        "cost_total": Num(),
        "cost_distance": Num(),
        "cost_height": Num(),
        "cost_traversability": Num(),
        "label_share": Map(),
        "nodes_expanded": Int(),
        "time_ms": Num(),
        "nearest_free": Arr((F8,), ((None,),)),
    },
    "ServiceStatus": {
        "stamp_s": Num(),
        "seq": Int(),
        "robot": Str(),
        "service": Str(),
        "pid": Int(),
        "uptime_s": Num(),
        "state": Str(),
        "msgs_in": Int(),
        "msgs_out": Int(),
        "accepted": Int(),
        "dropped": Map(),
        "rejected": Map(),
        "pending": Int(),
        "events": Map(),
        "details": Map(),
    },
}
QUATERNIONS = {"Pose": "orientation_xyzw", "SemanticCloud": "sensor_orientation_xyzw"}
# Types at a version above 1 (docs/architecture.md): the fields each added. A message of an older
# version must not carry them; a newer one may leave all of them empty (no distribution: certain).
VERSIONS = {"MapDelta": 2, "GraphPatch": 2}
ADDED = {
    ("MapDelta", 2): ("alt_labels", "alt_confidences"),
    ("GraphPatch", 2): ("alt_labels", "p_label", "p_alt"),
}
# what each added field reads as when a message does not carry it: certain, no second class
CERTAIN = {
    ("MapDelta", "alt_labels"): (U2, 0),
    ("MapDelta", "alt_confidences"): (F4, 0.0),
    ("GraphPatch", "alt_labels"): (U2, 0),
    ("GraphPatch", "p_label"): (U1, 255),
    ("GraphPatch", "p_alt"): (U1, 0),
}


def _is_real(v) -> bool:
    return type(v) in (int, float)


def _nonfinite_inside(v) -> bool:
    """A NaN or inf anywhere in a map's values (nested maps included)."""
    if isinstance(v, float):
        return not math.isfinite(v)
    if isinstance(v, dict):
        return any(_nonfinite_inside(x) for x in v.values())
    return False


def _scalar(rule, v) -> set[str]:
    if isinstance(rule, Num):
        if v is None and rule.optional:
            return set()
        if not _is_real(v):
            return {"value"}
        if isinstance(v, float) and not math.isfinite(v):
            return {"nonfinite"}
        if (rule.lo is not None and v < rule.lo) or (rule.hi is not None and v > rule.hi):
            return {"value"}
        return set()
    if isinstance(rule, Int):
        return set() if type(v) is int and rule.lo <= v <= rule.hi else {"value"}
    if isinstance(rule, Str):
        return set() if type(v) is str else {"value"}
    if isinstance(rule, OneOf):
        return set() if type(v) is str and v in rule.choices else {"value"}
    if isinstance(rule, Bool):
        return set() if type(v) is bool else {"value"}
    if isinstance(rule, Map):
        if type(v) is not dict:
            return {"value"}
        return {"nonfinite"} if _nonfinite_inside(v) else set()
    if isinstance(rule, Costs):
        if type(v) is not dict:
            return {"value"}
        if _nonfinite_inside(v):
            return {"nonfinite"}
        bad = set()
        for k, c in v.items():
            # a class id (an int, or digits in JSON) from 0 to 65535, to a finite cost >= 0
            key = int(k) if type(k) is str and k.isdigit() else k
            key_ok = type(key) is int and 0 <= key <= 65535
            if not (key_ok and _is_real(c) and math.isfinite(c) and c >= 0):
                bad.add("value")
        return bad
    raise AssertionError(rule)


def _array(rule: Arr, v) -> tuple[set[str], np.ndarray | None]:
    """The violations of one array's wire form, and the array when it has none."""
    if type(v) is not dict or set(v) != {"dtype", "shape", "data"}:
        return {"malformed"}, None
    try:
        dt = np.dtype(v["dtype"])
    except (TypeError, ValueError):
        return {"dtype"}, None
    except Exception:  # noqa: BLE001 - numpy raises odd things for odd dtype specs
        return {"dtype", "malformed"}, None
    if dt.str not in rule.dtypes:
        return {"dtype"}, None
    shape = v["shape"]
    if type(shape) is not list or not all(type(s) is int and 0 <= s <= MAX_BYTES for s in shape):
        return {"shape"}, None
    if len(shape) not in {len(s) for s in rule.shapes}:
        return {"shape"}, None
    data = v["data"]
    if type(data) is not bytes:
        return {"malformed"}, None
    size = 1
    for s in shape:
        size *= s
    if size * dt.itemsize != len(data):
        return {"shape"}, None
    if not any(
        all(w is None or s == w for s, w in zip(shape, want))
        for want in rule.shapes
        if len(want) == len(shape)
    ):
        return {"shape"}, None
    return set(), np.frombuffer(data, dt).reshape(shape)


def _bad_rows(rule: Arr, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row: holds a NaN/inf; holds a value beyond the rule's limit."""
    if len(a) == 0 or a.dtype.kind != "f":
        z = np.zeros(len(a), bool)
        return z, z
    rows = a.reshape(len(a), -1)
    nonfinite = np.array([any(not math.isfinite(float(x)) for x in r) for r in rows], bool)
    beyond = np.array(
        [
            rule.limit is not None
            and any(math.isfinite(float(x)) and abs(float(x)) > rule.limit for x in r)
            for r in rows
        ],
        bool,
    )
    return nonfinite, beyond


@dataclass
class Verdict:
    kinds: set[str]  # what a correct codec may report; empty: it must accept
    arrays: dict[str, np.ndarray]  # the arrays as sent (before rows are dropped)
    dropped: dict[str, np.ndarray]  # per group: the rows a drop_nonfinite decode removes


def violations(raw, expect: str | None, drop_nonfinite: bool = False) -> Verdict:
    """Every rule the decoded map `raw` breaks, for a message of type `expect` (None: any)."""
    if type(raw) is not dict or type(raw.get("_type")) is not str:
        return Verdict({"malformed"}, {}, {})
    tname = raw["_type"]
    if tname not in SCHEMA or (expect is not None and tname != expect):
        return Verdict({"type"}, {}, {})
    top = VERSIONS.get(tname, 1)
    if not (type(raw.get("_v")) is int and 1 <= raw["_v"] <= top):  # True and 1.0 are not
        return Verdict({"version"}, {}, {})
    newer = [n for (t, v), names in ADDED.items() if t == tname and v > raw["_v"] for n in names]
    fields = {k: r for k, r in SCHEMA[tname].items() if k not in newer}
    kinds: set[str] = set()
    if set(raw) - set(fields) - {"_type", "_v"}:
        kinds.add("unknown_field")
    arrays: dict[str, np.ndarray] = {}
    for name, rule in fields.items():
        if name not in raw:
            kinds.add("missing_field")
            continue
        if isinstance(rule, Arr):
            bad, a = _array(rule, raw[name])
            kinds |= bad
            if a is not None:
                arrays[name] = a
                if rule.group is None:  # checked on its own, like any single field
                    nonfinite, beyond = _bad_rows(rule, a.reshape(1, -1))
                    kinds |= {"nonfinite"} if nonfinite.any() else set()
                    kinds |= {"value"} if beyond.any() else set()
        else:
            kinds |= _scalar(rule, raw[name])
    if kinds:  # every field on its own must pass before arrays are compared across fields
        return Verdict(kinds, arrays, {})
    dropped: dict[str, np.ndarray] = {}
    groups: dict[str, list[str]] = {}
    for name, rule in fields.items():
        if isinstance(rule, Arr) and rule.group is not None:
            groups.setdefault(rule.group, []).append(name)
    filled = list(newer)
    for (t, _), added in ADDED.items():
        if t == tname and all(n in arrays and len(arrays[n]) == 0 for n in added):
            filled += added  # left out whole: read as certain
    for names in groups.values():
        names[:] = [n for n in names if n not in filled]
    for group, names in groups.items():
        if len({len(arrays[n]) for n in names}) > 1:
            kinds.add("length")
            continue
        n = len(arrays[names[0]])
        nonfinite, beyond = np.zeros(n, bool), np.zeros(n, bool)
        for name in names:
            nf, far = _bad_rows(fields[name], arrays[name])
            nonfinite |= nf
            beyond |= far
        if drop_nonfinite:
            dropped[group] = nonfinite | beyond
        elif nonfinite.any():
            kinds.add("nonfinite")
        elif beyond.any():
            kinds.add("value")
    for name in filled:  # what the message reads as: certain, one row per row of its group
        dtype, fill = CERTAIN[(tname, name)]
        n = len(arrays[groups[SCHEMA[tname][name].group][0]])
        arrays[name] = np.full(n, fill, dtype)
    q = QUATERNIONS.get(tname)
    if q and q in arrays and not kinds:
        norm = math.sqrt(sum(float(x) ** 2 for x in arrays[q]))
        if not 0.9 <= norm <= 1.1:
            kinds.add("value")
    return Verdict(kinds, arrays, dropped)


def check_decoded(msg, drop_nonfinite: bool = False) -> list[str]:
    """What is wrong with a message the codec accepted (empty: nothing)."""
    tname = type(msg).__name__
    fields = SCHEMA[tname]
    problems = []
    groups: dict[str, set[int]] = {}
    for name, rule in fields.items():
        v = getattr(msg, name)
        if isinstance(rule, Arr):
            if not isinstance(v, np.ndarray):
                problems.append(f"{name}: not an array")
                continue
            if v.dtype.str not in rule.dtypes:
                problems.append(f"{name}: dtype {v.dtype.str}")
            if not any(
                len(w) == v.ndim and all(x is None or s == x for s, x in zip(v.shape, w))
                for w in rule.shapes
            ):
                problems.append(f"{name}: shape {v.shape}")
            if v.dtype.kind == "f" and v.size:
                flat = [float(x) for x in v.reshape(-1)]
                if not all(math.isfinite(x) for x in flat):
                    problems.append(f"{name}: NaN or inf")
                if rule.limit is not None and any(abs(x) > rule.limit for x in flat):
                    problems.append(f"{name}: beyond {rule.limit}")
            if rule.group is not None:
                groups.setdefault(rule.group, set()).add(len(v))
        elif isinstance(rule, Costs):
            if not all(type(k) is int and type(c) is float for k, c in v.items()):
                problems.append(f"{name}: {v!r}")
            if not all(math.isfinite(c) and c >= 0 and 0 <= k <= 65535 for k, c in v.items()):
                problems.append(f"{name} holds NaN/inf, negative costs or ids: {v!r}")
        else:
            bad = _scalar(rule, v)
            if bad:
                problems.append(f"{name}: {v!r} ({bad})")
    problems += [f"group {g}: lengths {sorted(n)}" for g, n in groups.items() if len(n) > 1]
    q = QUATERNIONS.get(tname)
    if q is not None:
        norm = float(np.linalg.norm(getattr(msg, q)))
        if not 0.9 <= norm <= 1.1:
            problems.append(f"{q}: norm {norm}")
    return problems
