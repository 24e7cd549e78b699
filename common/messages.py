"""Message contracts: every schema that crosses a process, and its validating codec.

Wire format: one msgpack map per message, `{"_type": "SemanticCloud", "_v": 1, <fields>}`. A numpy
array travels as `{"dtype": "<f4", "shape": [N, 3], "data": <raw bytes>}`, so a 131k-point cloud is
three memcpys, not 131k Python objects. The same messages also have a JSON form (arrays as nested
lists) for queries from any zenoh tool.

Decoded arrays are read-only views of the payload (no copy); copy before modifying them.
Decoding validates everything and raises one error type, `MessageError`, whose `kind` names what was
wrong (services count errors by kind). Nothing a remote peer sends can crash a decoder.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

import msgpack
import numpy as np

SCHEMA_VERSION = 1
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024  # a 131k-point cloud is ~2.2 MB; 64 MB leaves room for maps

# Bounds on values no robot can produce: refused as `value` by the decoder, so no service ever
# computes with them. Coordinates: 1000 km from the world origin. Stamps: seconds (simulated,
# dataset or Unix time) up to the year 2286. Sequence numbers and every integer: int64.
COORD_LIMIT_M = 1.0e6
STAMP_LIMIT_S = 1.0e10
INT_LIMIT = 2**63 - 1
RESOLUTION_RANGE_M = (1.0e-3, 100.0)

ERROR_KINDS = (
    "oversize",  # payload larger than the limit
    "malformed",  # not msgpack/JSON, or not a map with a type tag
    "type",  # a message of another type than expected
    "version",  # schema version this build does not speak
    "missing_field",
    "unknown_field",
    "dtype",  # array of a dtype the schema does not allow
    "shape",  # array of the wrong rank or inner dimensions, or data of the wrong byte size
    "length",  # arrays that must have the same length do not
    "nonfinite",  # NaN or inf where a finite number is required
    "value",  # a scalar of the wrong type or outside its range
)


class MessageError(ValueError):
    """A payload that is not a valid message. `kind` is one of ERROR_KINDS."""

    def __init__(self, kind: str, message: str):
        assert kind in ERROR_KINDS, kind
        super().__init__(f"{kind}: {message}")
        self.kind = kind


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may hold. `shape` uses None for a free dimension; dimensions that share a
    `group` name must agree across the fields of one message (e.g. every per-point array has N)."""

    dtypes: tuple[str, ...]
    shape: tuple[int | None, ...]
    group: str | None = None
    finite: bool = True
    shapes: tuple[tuple[int | None, ...], ...] = ()  # alternatives to `shape` (e.g. 2 or 3 coords)
    limit: float | None = None  # largest magnitude a value may have (coordinates: COORD_LIMIT_M)

    def allowed_shapes(self) -> tuple[tuple[int | None, ...], ...]:
        return (self.shape, *self.shapes)


def array(dtypes, shape, group=None, finite=True, shapes=(), default=None, limit=None):
    """A dataclass field holding a numpy array with the given spec."""
    spec = ArraySpec(
        tuple(np.dtype(d).str for d in dtypes), tuple(shape), group, finite, shapes, limit
    )
    if default is None:

        def empty():
            return np.zeros(tuple(0 if s is None else s for s in shape), spec.dtypes[0])

        return field(default_factory=empty, metadata={"array": spec})
    return field(default_factory=default, metadata={"array": spec})


# -- the messages ---------------------------------------------------------------------------------

REGISTRY: dict[str, type[Message]] = {}


@dataclass
class Message:
    """Base of every message. Subclasses are registered by class name."""

    TYPE: ClassVar[str] = ""
    # Fields a JSON query may leave out (they take their defaults). The msgpack wire form always
    # carries every field, so there a missing field is an error.
    JSON_OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        cls.TYPE = cls.__name__
        REGISTRY[cls.__name__] = cls

    def check(self) -> None:
        """Checks across fields, after each field passed its own (raise MessageError)."""


def scalar(default, lo=None, hi=None):
    """A scalar field whose value must lie in [lo, hi] (either end may be open: None)."""
    return field(default=default, metadata={"range": (lo, hi)})


def _stamp_field():
    return scalar(0.0, 0.0, STAMP_LIMIT_S)


def _seq_field():
    return scalar(0, 0, INT_LIMIT)


def _quat_identity():
    return np.array([0.0, 0.0, 0.0, 1.0])


def _check_quaternion(where: str, q: np.ndarray) -> None:
    n = float(np.linalg.norm(q))
    if not 0.9 <= n <= 1.1:
        raise MessageError("value", f"{where}: quaternion of norm {n:.3g}, expected a unit one")


@dataclass
class Pose(Message):
    """A rigid pose in `frame_id` (REP-103: x forward, y left, z up; metres)."""

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    position: np.ndarray = array(["f8"], [3], limit=COORD_LIMIT_M)
    orientation_xyzw: np.ndarray = array(["f8"], [4], default=_quat_identity)
    frame_id: str = "world"

    def check(self) -> None:
        _check_quaternion("Pose.orientation_xyzw", self.orientation_xyzw)

    @classmethod
    def from_xyz_yaw(cls, x, y, z, yaw, stamp_s=0.0, seq=0, frame_id="world") -> Pose:
        q = np.array([0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)])
        return cls(float(stamp_s), int(seq), np.array([x, y, z], float), q, frame_id)

    @property
    def yaw(self) -> float:
        x, y, z, w = self.orientation_xyzw
        return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))

    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.orientation_xyzw)

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation()
        m[:3, 3] = self.position
        return m


@dataclass
class SemanticCloud(Message):
    """A labelled point cloud in the world frame, with the pose of the sensor that took it.
    `labels` are class ids of the class table in use; `confidences` in [0, 1]."""

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    points: np.ndarray = array(["f4"], [None, 3], group="n", limit=COORD_LIMIT_M)
    labels: np.ndarray = array(["u1", "u2"], [None], group="n")
    confidences: np.ndarray = array(["f4"], [None], group="n")
    sensor_position: np.ndarray = array(["f8"], [3], limit=COORD_LIMIT_M)
    sensor_orientation_xyzw: np.ndarray = array(["f8"], [4], default=_quat_identity)
    frame_id: str = "world"
    source: str = "camera"
    # Set by decode(drop_nonfinite=True): points with NaN/inf or beyond COORD_LIMIT_M; never sent.
    n_dropped_nonfinite: int = field(default=0, metadata={"local": True})

    def check(self) -> None:
        _check_quaternion("SemanticCloud.sensor_orientation_xyzw", self.sensor_orientation_xyzw)


@dataclass
class VelocityCommand(Message):
    """A velocity command for a differential-drive base (body frame)."""

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    linear_mps: float = scalar(0.0, -100.0, 100.0)
    angular_radps: float = scalar(0.0, -100.0, 100.0)
    source: str = ""


# what MapDelta.values holds
VALUES_KINDS = ("log_odds", "signed_distance")


@dataclass
class MapDelta(Message):
    """The voxels whose state changed in one integration (one voxel at most once).

    `values_kind` says what `values` holds, so that a consumer needs no back-end names:
    "log_odds" (occupancy back-ends; `occupied` is `values > 0`) or "signed_distance" (metres;
    `occupied` marks the extracted surface: the voxel nearer zero of a pair of face neighbours of
    opposite sign, both of weight >= `mapper.tsdf.min_weight`; since that depends on neighbours, a
    delta also carries the neighbours of updated voxels whose status flipped). `backend` names
    the back-end for people and files.

    `producer` names the mapper session that numbered the stream (`seq` counts per producer): a
    consumer follows one producer's sequence and resynchronises from its snapshot when it
    changes (a restarted mapper) or jumps."""

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    cloud_seq: int = _seq_field()
    backend: str = "octree-max"
    resolution_m: float = scalar(0.1, *RESOLUTION_RANGE_M)
    centres: np.ndarray = array(["f4"], [None, 3], group="m", limit=COORD_LIMIT_M)
    labels: np.ndarray = array(["u2"], [None], group="m")
    confidences: np.ndarray = array(["f4"], [None], group="m")
    occupied: np.ndarray = array(["u1"], [None], group="m")
    values: np.ndarray = array(["f4"], [None], group="m", limit=COORD_LIMIT_M)
    producer: str = ""
    values_kind: str = "log_odds"

    def check(self) -> None:
        if self.values_kind not in VALUES_KINDS:
            raise MessageError(
                "value",
                f"MapDelta.values_kind: one of {list(VALUES_KINDS)}, got {self.values_kind!r}",
            )


@dataclass
class GraphPatch(Message):
    """Navigation-graph nodes that changed: grid indices from `origin_xy` at `resolution_m`, and the
    nodes' label, height and flags (FLAG_KNOWN | FLAG_OBSTACLE | FLAG_SAFETY_ZONE).
    `producer` names the navgraph session that numbered the stream (see MapDelta)."""

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    resolution_m: float = scalar(0.2, *RESOLUTION_RANGE_M)
    origin_xy: np.ndarray = array(["f8"], [2], limit=COORD_LIMIT_M)
    cells: np.ndarray = array(["i4"], [None, 2], group="k")
    labels: np.ndarray = array(["u2"], [None], group="k")
    heights: np.ndarray = array(["f4"], [None], group="k", limit=COORD_LIMIT_M)
    flags: np.ndarray = array(["u1"], [None], group="k")
    producer: str = ""


@dataclass
class PathRequest(Message):
    """A path query to the planner. Start and goal are (x, y) or (x, y, z) in metres; optional
    fields left as None take the planner's configured defaults."""

    request_id: str = ""
    start: np.ndarray = array(["f8"], [2], shapes=((3,),), limit=COORD_LIMIT_M)
    goal: np.ndarray = array(["f8"], [2], shapes=((3,),), limit=COORD_LIMIT_M)
    h_f: float | None = scalar(None, 0.0, 1e6)
    t_f: float | None = scalar(None, 0.0, 1e6)
    class_costs: dict = field(default_factory=dict)
    allow_unknown: bool = False
    unknown_cost: float = scalar(2.0, 0.0, 1e6)
    max_step_m: float | None = scalar(None, 0.0, 1e6)

    def __post_init__(self):
        # JSON object keys are strings: accept {"1": 4.0} as well as {1: 4.0}; nothing else
        # (no "nan" strings, bools, fractional or negative ids).
        msg = "PathRequest.class_costs must map class ids (>= 0) to finite costs >= 0"
        if not isinstance(self.class_costs, dict):
            raise MessageError("value", msg)
        costs = {}
        for k, v in self.class_costs.items():
            if isinstance(k, str) and k.isdigit():
                k = int(k)
            if type(k) is not int or k < 0 or k > 65535:
                raise MessageError("value", f"{msg}: id {k!r}")
            if type(v) not in (int, float) or not math.isfinite(v) or v < 0:
                raise MessageError("value", f"{msg}: cost {v!r} for class {k}")
            costs[k] = float(v)
        self.class_costs = costs

    JSON_OPTIONAL: ClassVar[tuple[str, ...]] = (
        "request_id",
        "h_f",
        "t_f",
        "class_costs",
        "allow_unknown",
        "unknown_cost",
        "max_step_m",
    )


@dataclass
class PathReply(Message):
    """The planner's answer: a path with its cost breakdown, or `ok=False` with an error code
    (`out_of_bounds`, `start_blocked`, `goal_blocked`, `unreachable`, `no_graph`, `malformed`)."""

    request_id: str = ""
    ok: bool = False
    error: str = ""
    message: str = ""
    path: np.ndarray = array(["f4"], [None, 3])
    cost_total: float = 0.0
    cost_distance: float = 0.0
    cost_height: float = 0.0
    cost_traversability: float = 0.0
    label_share: dict = field(default_factory=dict)
    nodes_expanded: int = 0
    time_ms: float = 0.0
    nearest_free: np.ndarray = array(["f8"], [None])


@dataclass
class ServiceStatus(Message):
    """What a service publishes periodically and answers on its status key.

    `state`: starting (loading, compiling; `details.startup_step` says what), running,
    stopping. The books add up: every message received (`msgs_in`) is `accepted`, `dropped` by
    reason, `rejected` by kind, or still `pending`. `events` counts what is not a message's fate
    (gaps, points dropped inside accepted clouds, timeouts). A status query counts itself
    accepted."""

    stamp_s: float = 0.0
    seq: int = 0
    robot: str = ""
    service: str = ""
    pid: int = 0
    uptime_s: float = 0.0
    state: str = "running"
    msgs_in: int = 0
    msgs_out: int = 0
    accepted: int = 0
    dropped: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    pending: int = 0
    events: dict = field(default_factory=dict)
    details: dict = field(default_factory=dict)

    def books_add_up(self) -> bool:
        """msgs_in == accepted + dropped + rejected + pending."""
        settled = self.accepted + sum(self.dropped.values()) + sum(self.rejected.values())
        return self.msgs_in == settled + self.pending


# -- codec ----------------------------------------------------------------------------------------


def _fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("local")]


def _array_to_wire(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def encode(msg: Message) -> bytes:
    """Serialise a message to msgpack bytes."""
    out: dict[str, Any] = {"_type": msg.TYPE, "_v": SCHEMA_VERSION}
    for f in _fields(type(msg)):
        v = getattr(msg, f.name)
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
    out: dict[str, Any] = {"_type": msg.TYPE, "_v": SCHEMA_VERSION}
    for f in _fields(type(msg)):
        out[f.name] = _plain(getattr(msg, f.name))
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
        raw.setdefault("_v", SCHEMA_VERSION)
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
    if type(raw.get("_v")) is not int or raw["_v"] != SCHEMA_VERSION:  # True == 1 == 1.0
        got = raw.get("_v")
        raise MessageError("version", f"{tname} v{got!r}, this build speaks v{SCHEMA_VERSION}")

    fields = {f.name: f for f in _fields(cls)}
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


# -- small geometry helpers used by several services -----------------------------------------------


def quat_to_matrix(q_xyzw) -> np.ndarray:
    x, y, z, w = (float(c) for c in q_xyzw)
    n = x * x + y * y + z * z + w * w
    if n < 1e-12:
        return np.eye(3)
    s = 2.0 / n
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix to quaternion (x, y, z, w), Shepperd's method."""
    m = np.asarray(r, float)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)
