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

    def allowed_shapes(self) -> tuple[tuple[int | None, ...], ...]:
        return (self.shape, *self.shapes)


def array(dtypes, shape, group=None, finite=True, shapes=(), default=None):
    """A dataclass field holding a numpy array with the given spec."""
    spec = ArraySpec(tuple(np.dtype(d).str for d in dtypes), tuple(shape), group, finite, shapes)
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


def _quat_identity():
    return np.array([0.0, 0.0, 0.0, 1.0])


@dataclass
class Pose(Message):
    """A rigid pose in `frame_id` (REP-103: x forward, y left, z up; metres)."""

    stamp_s: float = 0.0
    seq: int = 0
    position: np.ndarray = array(["f8"], [3])
    orientation_xyzw: np.ndarray = array(["f8"], [4], default=_quat_identity)
    frame_id: str = "world"

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

    stamp_s: float = 0.0
    seq: int = 0
    points: np.ndarray = array(["f4"], [None, 3], group="n")
    labels: np.ndarray = array(["u1", "u2"], [None], group="n")
    confidences: np.ndarray = array(["f4"], [None], group="n")
    sensor_position: np.ndarray = array(["f8"], [3])
    sensor_orientation_xyzw: np.ndarray = array(["f8"], [4], default=_quat_identity)
    frame_id: str = "world"
    source: str = "camera"
    # Set by decode(drop_nonfinite=True); never sent.
    n_dropped_nonfinite: int = field(default=0, metadata={"local": True})


@dataclass
class VelocityCommand(Message):
    """A velocity command for a differential-drive base (body frame)."""

    stamp_s: float = 0.0
    seq: int = 0
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    source: str = ""


@dataclass
class MapDelta(Message):
    """The voxels whose state changed in one integration (one voxel at most once).

    Octree back-ends: `values` is the occupancy log-odds and `occupied` is `values > 0`.
    TSDF: `values` is the signed distance in metres and `occupied` marks surface voxels
    (|distance| < resolution with weight > 0)."""

    stamp_s: float = 0.0
    seq: int = 0
    cloud_seq: int = 0
    backend: str = "octree-max"
    resolution_m: float = 0.1
    centres: np.ndarray = array(["f4"], [None, 3], group="m")
    labels: np.ndarray = array(["u2"], [None], group="m")
    confidences: np.ndarray = array(["f4"], [None], group="m")
    occupied: np.ndarray = array(["u1"], [None], group="m")
    values: np.ndarray = array(["f4"], [None], group="m")


# GraphPatch / navgrid flag bits
FLAG_KNOWN = 1
FLAG_OBSTACLE = 2
FLAG_SAFETY_ZONE = 4


@dataclass
class GraphPatch(Message):
    """Navigation-graph nodes that changed: grid indices from `origin_xy` at `resolution_m`, and the
    nodes' label, height and flags (FLAG_KNOWN | FLAG_OBSTACLE | FLAG_SAFETY_ZONE)."""

    stamp_s: float = 0.0
    seq: int = 0
    resolution_m: float = 0.2
    origin_xy: np.ndarray = array(["f8"], [2])
    cells: np.ndarray = array(["i4"], [None, 2], group="k")
    labels: np.ndarray = array(["u2"], [None], group="k")
    heights: np.ndarray = array(["f4"], [None], group="k")
    flags: np.ndarray = array(["u1"], [None], group="k")


@dataclass
class PathRequest(Message):
    """A path query to the planner. Start and goal are (x, y) or (x, y, z) in metres; optional
    fields left as None take the planner's configured defaults."""

    request_id: str = ""
    start: np.ndarray = array(["f8"], [2], shapes=((3,),))
    goal: np.ndarray = array(["f8"], [2], shapes=((3,),))
    h_f: float | None = None
    t_f: float | None = None
    class_costs: dict = field(default_factory=dict)
    allow_unknown: bool = False
    unknown_cost: float = 2.0
    max_step_m: float | None = None

    def __post_init__(self):
        # JSON object keys are strings: accept {"1": 4.0} as well as {1: 4.0}.
        try:
            self.class_costs = {int(k): float(v) for k, v in self.class_costs.items()}
        except (TypeError, ValueError, AttributeError):
            msg = "PathRequest.class_costs must map class ids to costs"
            raise MessageError("value", msg) from None

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
    """What a service publishes periodically and answers on its status key."""

    stamp_s: float = 0.0
    seq: int = 0
    robot: str = ""
    service: str = ""
    pid: int = 0
    uptime_s: float = 0.0
    state: str = "running"
    msgs_in: int = 0
    msgs_out: int = 0
    errors: dict = field(default_factory=dict)
    queue_drops: int = 0
    details: dict = field(default_factory=dict)


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
    """Parse and validate msgpack bytes. With `drop_nonfinite`, per-point rows holding NaN/inf are
    removed (a SemanticCloud records how many in `n_dropped_nonfinite`) instead of rejected."""
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
    except (ValueError, UnicodeDecodeError) as exc:
        raise MessageError("malformed", f"not JSON: {exc}") from None
    if isinstance(raw, dict) and isinstance(expect, type):
        raw.setdefault("_type", expect.TYPE)
        raw.setdefault("_v", SCHEMA_VERSION)
    return from_dict(raw, expect, drop_nonfinite=drop_nonfinite, wire=False)


def from_dict(raw, expect=None, *, drop_nonfinite=False, wire=True) -> Message:
    """Validate a decoded map (msgpack wire form, or JSON form with `wire=False`)."""
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
    if raw.get("_v") != SCHEMA_VERSION:
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
            values[name] = _check_scalar(tname, name, raw[name], hints[name])
    msg = cls(**values)
    _check_groups(tname, msg, drop_nonfinite)
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
        if not isinstance(shape, list) or not all(isinstance(s, int) and s >= 0 for s in shape):
            raise MessageError("shape", f"{where}: shape must be a list of non-negative ints")
        data = v["data"]
        if not isinstance(data, bytes | bytearray):
            raise MessageError("malformed", f"{where}: data must be bytes")
        if len(data) != int(np.prod(shape, dtype=np.int64)) * dt.itemsize:
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
    if spec.finite and a.dtype.kind == "f" and spec.group is None and not np.isfinite(a).all():
        raise MessageError("nonfinite", f"{where}: NaN or inf")
    return a


def _shape_ok(shape, want) -> bool:
    if len(shape) != len(want):
        return False
    return all(w is None or s == w for s, w in zip(shape, want, strict=True))


def _fmt(spec: ArraySpec) -> str:
    return " or ".join(str([("N" if d is None else d) for d in s]) for s in spec.allowed_shapes())


def _check_groups(tname, msg: Message, drop_nonfinite: bool) -> None:
    """Arrays of one group must share their first dimension; their float rows must be finite."""
    groups: dict[str, list[tuple[str, ArraySpec]]] = {}
    for f in _fields(type(msg)):
        spec = f.metadata.get("array")
        if spec is not None and spec.group is not None:
            groups.setdefault(spec.group, []).append((f.name, spec))
    for members in groups.values():
        lengths = {name: len(getattr(msg, name)) for name, _ in members}
        if len(set(lengths.values())) > 1:
            raise MessageError("length", f"{tname}: array lengths disagree {lengths}")
        bad = None
        for name, spec in members:
            a = getattr(msg, name)
            if spec.finite and a.dtype.kind == "f":
                rows = (
                    ~np.isfinite(a).all(axis=tuple(range(1, a.ndim)))
                    if a.ndim > 1
                    else ~np.isfinite(a)
                )
                bad = rows if bad is None else bad | rows
        if bad is None or not bad.any():
            continue
        if not drop_nonfinite:
            raise MessageError("nonfinite", f"{tname}: {int(bad.sum())} rows hold NaN or inf")
        keep = ~bad
        for name, _ in members:
            setattr(msg, name, getattr(msg, name)[keep])
        if hasattr(msg, "n_dropped_nonfinite"):
            msg.n_dropped_nonfinite = int(bad.sum())


_SCALARS = {float: (int, float), int: (int,), str: (str,), bool: (bool,), dict: (dict,)}


def _check_scalar(tname, name, v, hint):
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
