"""Structured fuzzing inputs for smana: valid, hostile and broken payloads for every message type of
`common/messages.py` and every query a service answers.

The generators never call a random module themselves: they take a `Draw` (fuzz_values.py), a
small source of choices. `RandomDraw` (a seeded `random.Random`) drives `smana bench fuzz`; the test
suite wraps a hypothesis `data` object in the same interface, so the suite shrinks a failing input
and the bench runs without hypothesis. Bulk contents (array values) come from a numpy generator
seeded by one draw, so an example stays a few dozen choices long.

What is generated, per message type (`message_payload`):
- `valid`: a plausible message, as a robot would send it (`plausible`);
- `hostile`: a message the codec must accept, with values at the edges of what it allows: stamps
  at 0 or the limit or jumping, sequence numbers at 0 / int64 max / going back, foreign or huge
  producer names, coordinates near 1000 km, labels 65535, confidences far outside [0, 1],
  unknown backends, non-unit quaternions within tolerance, large clouds (`hostile`);
- `wire`: structural mutations of the msgpack map: `_type`, `_v`, missing and unknown fields,
  scalars of the wrong type or out of range (NaN, inf, 1e300, 2**64-1, bool for int, strings for
  numbers), arrays with wrapping or negative shapes, other dtypes and byte orders, data of the
  wrong length, rows with NaN, mismatched group lengths, deep nesting, old-style raw strings;
- `bytes`: truncated, bit-flipped, extended or random payloads;
- `oversize`: over `MAX_PAYLOAD_BYTES` (64 MiB; only where the caller allows it: it costs memory).
The JSON form (`json_payload`) gets the same treatment at the JSON level, plus NaN/Infinity
tokens, 1e400, integers beyond any machine type, deep nesting and invalid UTF-8.

Queries (`query_case`): for each queryable, plausible bodies with wild values in msgpack or JSON,
in the payload or as selector parameters, and random payloads, encodings and parameters.

`predict` says what the codec makes of a payload (None: accepted, else the MessageError kind), as a
service would decode it: the multi-process campaign (`lab/bench/fuzz.py`) compares the
services' books with it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from smana.common import messages as m
from smana.common.messages import (
    COORD_LIMIT_M,
    INT_LIMIT,
    MAX_PAYLOAD_BYTES,
    STAMP_LIMIT_S,
    MessageError,
    decode,
    encode,
    from_json,
    to_json,
)
from smana.lab.fuzz_values import (
    DTYPES,
    INF,
    NAN,
    SHAPES,
    WILD_MAPS,
    WILD_SCALARS,
    WILD_STRINGS,
    Draw,
    wild_float,
    wild_scalar,
    wild_value,
)
from smana.services.mapper.backends import BACKENDS, backend_class

MESSAGE_TYPES: tuple[type[m.Message], ...] = (
    m.Pose,
    m.SemanticCloud,
    m.VelocityCommand,
    m.MapDelta,
    m.GraphPatch,
    m.PathRequest,
    m.PathReply,
    m.ServiceStatus,
)


# -- what the generators know about the stack under test ------------------------------------------


@dataclass
class Context:
    """The stream state a hostile message plays with: the genuine clock and numbering, the genuine
    producers, the graph geometry, where plausible points lie, the class ids."""

    stamp_s: float = 100.0  # the genuine streams' clock (seconds)
    seq: int = 10  # the genuine streams' last sequence number
    producers: dict[str, str] = field(default_factory=dict)  # "mapper"/"navgraph" -> session id
    map_resolution_m: float = 0.1
    graph_resolution_m: float = 0.2
    graph_origin_xy: tuple[float, float] = (-50.0, -50.0)
    graph_shape: tuple[int, int] = (500, 500)
    area: tuple[float, float, float, float] = (-3.0, -3.0, 3.0, 3.0)  # x0, y0, x1, y1 (metres)
    labels: tuple[int, ...] = (0, 1, 2, 4, 5, 6, 7, 8)
    traversable: tuple[int, ...] = (1, 2)
    max_points: int = 2048  # plausible clouds; hostile ones may be much larger
    big_points: int = 200_000  # a hostile "large" cloud (~3.4 MB)


def _fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("local")]


# -- plausible messages ---------------------------------------------------------------------------


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def _points(rng: np.random.Generator, ctx: Context, n: int) -> np.ndarray:
    x0, y0, x1, y1 = ctx.area
    p = np.empty((n, 3), np.float32)
    p[:, 0] = rng.uniform(x0, x1, n)
    p[:, 1] = rng.uniform(y0, y1, n)
    p[:, 2] = rng.uniform(-0.5, 1.5, n)
    return p


def plausible(cls: type[m.Message], d: Draw, ctx: Context) -> m.Message:
    """A message of type `cls` as a working robot would send it."""
    rng = d.rng()
    stamp = ctx.stamp_s + d.choice((0.0, 0.05, 0.5, 1.0))
    seq = ctx.seq + 1
    x0, y0, x1, y1 = ctx.area
    yaw = float(rng.uniform(-math.pi, math.pi))
    if cls is m.Pose:
        pos = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1), 0.1])
        return m.Pose(stamp, seq, pos, _yaw_quat(yaw), "world")
    if cls is m.SemanticCloud:
        n = d.choice((0, 1, 3, 16, 64, 256, ctx.max_points))
        lab_dt = d.choice((np.uint8, np.uint16))
        return m.SemanticCloud(
            stamp,
            seq,
            _points(rng, ctx, n),
            rng.choice(np.array(ctx.labels), n).astype(lab_dt),
            rng.uniform(0.3, 1.0, n).astype(np.float32),
            np.array([(x0 + x1) / 2, (y0 + y1) / 2, 1.0]),
            _yaw_quat(yaw),
            "world",
            d.choice(("camera", "lidar")),
        )
    if cls is m.VelocityCommand:
        return m.VelocityCommand(
            stamp, seq, float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), "explorer"
        )
    if cls is m.MapDelta:
        k = d.choice((0, 1, 8, 64, 512))
        r = ctx.map_resolution_m
        centres = ((np.floor(_points(rng, ctx, k) / r) + 0.5) * r).astype(np.float32)
        backend = d.choice(tuple(BACKENDS))
        kind = backend_class(backend).values_kind
        occ = rng.integers(0, 2, k).astype(np.uint8)
        if kind == "signed_distance":
            values = rng.uniform(-0.3, 0.3, k).astype(np.float32)
        else:
            values = np.where(occ > 0, 0.85, -0.4).astype(np.float32)
        return m.MapDelta(
            stamp,
            seq,
            seq,
            backend,
            r,
            centres,
            rng.choice(np.array(ctx.labels), k).astype("u2"),
            rng.uniform(0.3, 1, k).astype(np.float32),
            occ,
            values,
            ctx.producers.get("mapper", "fuzz-mapper"),
            values_kind=kind,
        )
    if cls is m.GraphPatch:
        k = d.choice((0, 1, 8, 64, 256))
        ox, oy = ctx.graph_origin_xy
        res = ctx.graph_resolution_m
        cx = np.clip(
            ((rng.uniform(x0, x1, k) - ox) / res).astype(np.int64), 0, ctx.graph_shape[0] - 1
        )
        cy = np.clip(
            ((rng.uniform(y0, y1, k) - oy) / res).astype(np.int64), 0, ctx.graph_shape[1] - 1
        )
        return m.GraphPatch(
            stamp,
            seq,
            res,
            np.array([ox, oy], np.float64),
            np.stack([cx, cy], axis=1).astype(np.int32).reshape(k, 2),
            rng.choice(np.array(ctx.labels), k).astype("u2"),
            rng.uniform(-0.2, 0.5, k).astype(np.float32),
            rng.choice(np.array([0, 1, 3, 5], np.uint8), k),
            ctx.producers.get("navgraph", "fuzz-navgraph"),
        )
    if cls is m.PathRequest:
        dims = d.choice((2, 3))
        start = rng.uniform([x0, y0, -1], [x1, y1, 1])[:dims]
        goal = rng.uniform([x0, y0, -1], [x1, y1, 1])[:dims]
        costs = {int(c): float(rng.uniform(0, 10)) for c in ctx.traversable if d.boolean(0.3)}
        return m.PathRequest(
            f"fuzz{seq}",
            start,
            goal,
            d.choice((None, 0.1, 1.0)),
            d.choice((None, 0.8, 0.0)),
            costs,
            d.boolean(),
            float(rng.uniform(0, 5)),
            d.choice((None, 0.3, 2.0)),
        )
    if cls is m.PathReply:
        k = d.choice((0, 2, 30))
        return m.PathReply(
            f"fuzz{seq}",
            d.boolean(),
            d.choice(("", "unreachable", "malformed")),
            "msg",
            _points(rng, ctx, k),
            1.5,
            1.0,
            0.2,
            0.3,
            {"grass": 0.5, "terrain": 0.5},
            12,
            0.4,
            np.zeros(d.choice((0, 2))),
        )
    if cls is m.ServiceStatus:
        return m.ServiceStatus(
            stamp,
            seq,
            "r1",
            d.choice(("mapper", "sim")),
            1234,
            5.0,
            "running",
            10,
            5,
            8,
            {"stale": 1},
            {"shape": 1},
            0,
            {"gap": 2},
            {"voxels": 100, "rate": 0.5},
        )
    raise TypeError(f"no generator for {cls.__name__}")


# -- hostile messages (the codec must accept them) ------------------------------------------------


def _hostile_stamp(d: Draw, ctx: Context) -> float:
    w = 5.0  # the default stamp window
    return max(
        0.0,
        d.choice(
            (
                0.0,
                STAMP_LIMIT_S,
                ctx.stamp_s,
                ctx.stamp_s - w - 0.001,
                ctx.stamp_s - w + 0.001,
                ctx.stamp_s + w + 0.001,
                ctx.stamp_s + 1e6,
                ctx.stamp_s - 1e3,
                1e9,
                1e9 + 1.0,
                5e-324,
                ctx.stamp_s + d.unit() * 100,
            )
        ),
    )


def _hostile_seq(d: Draw, ctx: Context) -> int:
    return d.choice(
        (
            0,
            1,
            INT_LIMIT,
            INT_LIMIT - 1,
            ctx.seq,
            ctx.seq - 1,
            ctx.seq + 1,
            ctx.seq + 2,
            ctx.seq + 1000,
            ctx.seq + 1001,
            2**53 + 1,
        )
    )


def _hostile_producer(d: Draw, ctx: Context, who: str) -> str:
    real = ctx.producers.get(who, "")
    return d.choice((real, "", "f" * 32, "stranger", "\U0001f916", "p" * 10_000, real[:8]))


def _far(rng: np.random.Generator, shape, edge: float = COORD_LIMIT_M) -> np.ndarray:
    """Values within the codec's coordinate limit, many of them at its edge."""
    v = rng.uniform(-edge, edge, shape)
    pick = rng.random(shape) < 0.3
    v[pick] = np.sign(v[pick]) * edge
    return v


def hostile(cls: type[m.Message], d: Draw, ctx: Context) -> m.Message:
    """A message the codec must accept, with wild values: stamps, numbering, producers, sizes,
    coordinates, labels, confidences at the edges of what is allowed."""
    msg = plausible(cls, d, ctx)
    rng = d.rng()
    for _ in range(d.integer(1, 3)):
        what = d.integer(0, 9)
        if hasattr(msg, "stamp_s") and what == 0:
            msg.stamp_s = _hostile_stamp(d, ctx)
        elif hasattr(msg, "seq") and what == 1:
            msg.seq = _hostile_seq(d, ctx)
        elif isinstance(msg, m.MapDelta | m.GraphPatch) and what == 2:
            msg.producer = _hostile_producer(d, ctx, "mapper" if cls is m.MapDelta else "navgraph")
        elif what == 3:
            _hostile_strings(msg, d)
        else:
            _hostile_values(msg, d, ctx, rng)
    return msg


def _hostile_strings(msg: m.Message, d: Draw) -> None:
    names = [f.name for f in _fields(type(msg)) if f.type in ("str", str)]
    if names:
        setattr(msg, d.choice(names), d.choice(WILD_STRINGS))


def _hostile_values(msg: m.Message, d: Draw, ctx: Context, rng: np.random.Generator) -> None:
    k = d.integer(0, 7)
    if isinstance(msg, m.Pose):
        if k < 3:
            msg.position = _far(rng, 3)
        elif k < 5:
            q = rng.normal(size=4)
            # at the codec's bounds (0.9 .. 1.1), a hair inside: a norm of exactly 0.9 comes out
            # of the division a rounding error under it about one time in three
            edge = d.choice((0.9 + 1e-9, 1.1 - 1e-9, 0.9000001))
            msg.orientation_xyzw = q / np.linalg.norm(q) * edge
        else:  # within the limit still: a pose moved to its edge before may be moved again
            moved = msg.position + rng.normal(0, d.choice((0.5, 5.0, 50.0)), 3)
            msg.position = np.clip(moved, -COORD_LIMIT_M, COORD_LIMIT_M)
    elif isinstance(msg, m.SemanticCloud):
        n = len(msg.points)
        if k == 0:
            n = d.choice((ctx.big_points, 65_536, 1))
            msg.points = _points(rng, ctx, n)
            msg.labels = rng.integers(0, 2**16, n).astype("u2")
            msg.confidences = rng.uniform(0, 1, n).astype("f4")
        elif k == 1:
            msg.points = _far(rng, (n, 3)).astype("f4")
        elif k == 2:
            msg.labels = rng.integers(0, 2**16, n).astype("u2")
        elif k == 3:
            msg.confidences = rng.choice(np.array([-1e30, -1, 0, 1, 2, 1e30, -0.0], "f4"), n)
        elif k == 4:
            msg.sensor_position = _far(rng, 3)
        elif k == 5 and n:
            msg.points = np.repeat(msg.points[:1], n, axis=0)  # every point in one voxel
        elif k == 6:
            msg.points = (msg.points + rng.normal(0, 1e-3, msg.points.shape)).astype("f4")
            msg.points[:, 2] = d.choice((-1e5, 1e5, 0.0))
        else:
            msg.sensor_orientation_xyzw = np.array([0.0, 0.0, 0.0, d.choice((0.9, 1.1))])
    elif isinstance(msg, m.VelocityCommand):
        msg.linear_mps = d.choice((-100.0, 100.0, 0.0, -0.0, 1e-300, 99.999))
        msg.angular_radps = d.choice((-100.0, 100.0, 0.0, 1e-300))
    elif isinstance(msg, m.MapDelta):
        n = len(msg.centres)
        if k == 0:
            msg.backend = d.choice(("octree", "TSDF", "", "tsdf ", "x" * 1000, "octree-max"))
        elif k == 1:
            msg.resolution_m = d.choice((1e-3, 100.0, 0.1 + 1e-12, 0.0010001, 99.99))
        elif k == 2:
            msg.centres = _far(rng, (n, 3)).astype("f4")
        elif k == 3:
            msg.labels = rng.integers(0, 2**16, n).astype("u2")
        elif k == 4:
            msg.occupied = rng.integers(0, 256, n).astype("u1")
        elif k == 5:
            msg.values = _far(rng, n).astype("f4")
        elif k == 6:
            msg.confidences = rng.choice(np.array([-1e30, 2.0, 1e30, -0.0], "f4"), n)
        else:
            msg.cloud_seq = _hostile_seq(d, ctx)
    elif isinstance(msg, m.GraphPatch):
        n = len(msg.cells)
        if k == 0:
            msg.cells = rng.choice(np.array([-(2**31), -1, 0, 2**31 - 1, 499, 500], "i4"), (n, 2))
        elif k == 1:
            msg.resolution_m = d.choice((1e-3, 100.0, 0.2 + 1e-9, 0.2 + 1e-12))
        elif k == 2:
            msg.origin_xy = d.choice((_far(rng, 2), np.array(ctx.graph_origin_xy) + 1e-7))
        elif k == 3:
            msg.labels = rng.integers(0, 2**16, n).astype("u2")
        elif k == 4:
            msg.heights = _far(rng, n).astype("f4")
        elif k == 5:
            msg.flags = rng.integers(0, 256, n).astype("u1")
        else:
            msg.cells = np.repeat(msg.cells[:1], n, axis=0)  # one node, many times
    elif isinstance(msg, m.PathRequest):
        if k == 0:
            msg.start = _far(rng, d.choice((2, 3)))
        elif k == 1:
            msg.goal = msg.start.copy()
        elif k == 2:
            # extreme but valid: the codec takes class ids 0..65535 and finite costs >= 0 (an id
            # of 2**40 or a cost of -1 here was refused by the codec, which a hostile message
            # must not be: hypothesis 6.100 drew one, tests/test_fuzz_codec.py)
            msg.class_costs = {
                d.choice((0, 3, 4, 255, 65535, 1, 2)): d.choice((0.0, 1e300, 1e-300, 2.0))
            }
        elif k == 3:
            msg.h_f, msg.t_f = d.choice((0.0, 1e6)), d.choice((0.0, 1e6))
        elif k == 4:
            msg.unknown_cost, msg.allow_unknown = d.choice((0.0, 1e6)), True
        elif k == 5:
            msg.max_step_m = d.choice((0.0, 1e6, 1e-300))
        else:
            msg.goal = _far(rng, len(msg.goal), edge=60.0)  # just outside the graph's bounds
    else:  # PathReply, ServiceStatus: loosely typed maps
        if isinstance(msg, m.ServiceStatus):
            msg.details = {"deep": {"er": {"still": [1e300, -1e300, None, "x"]}}, "n": 2**63 - 1}
            msg.dropped = {"x" * 100: 2**63 - 1}
        else:
            msg.label_share = {str(i): 1e300 for i in range(d.integer(0, 50))}


def pose_track(d: Draw, ctx: Context, n: int | None = None) -> list[m.Pose]:
    """A short, self-consistent run of poses (stamps 0.1 s apart, a few centimetres each) at a
    hostile place: inside the wall, on the graph's edge, far outside it, at the coordinate
    limit. Consistent poses pass the stamp and pose gates, so the consumer acts on them (the
    explorer plans from there); lone wild poses never would."""
    n = n or d.integer(4, 8)
    x0, y0, x1, y1 = ctx.area
    ox, oy = ctx.graph_origin_xy
    edge_x = ox + ctx.graph_shape[0] * ctx.graph_resolution_m
    place = d.choice(
        (
            ((x0 + x1) / 2, (y0 + y1) / 2),
            (0.0, -1.0),
            (x0, y0),
            (x1, y1),
            (ox, oy),
            (edge_x - 1e-6, oy + 1.0),
            (edge_x + 5.0, 0.0),
            (1e5, -1e5),
            (COORD_LIMIT_M, 0.0),
            (-COORD_LIMIT_M, COORD_LIMIT_M),
        )
    )
    t0 = d.choice((ctx.stamp_s, ctx.stamp_s + 1.0, 1e9, 0.0))
    yaw = d.unit() * 2 * math.pi
    out = []
    for i in range(n):
        x = min(max(place[0] + 0.02 * i, -COORD_LIMIT_M), COORD_LIMIT_M)
        out.append(
            m.Pose.from_xyz_yaw(x, place[1], 0.1, yaw, stamp_s=t0 + 0.1 * i, seq=ctx.seq + 1 + i)
        )
    return out


# -- wire-level mutations -------------------------------------------------------------------------


def wire(msg: m.Message) -> dict:
    """The msgpack map a message travels as."""
    return msgpack.unpackb(encode(msg), raw=False, strict_map_key=False)


def _packable(v) -> bool:
    try:
        msgpack.packb(v, use_bin_type=True)
        return True
    except (OverflowError, ValueError, TypeError):
        return False


def _array_fields(cls) -> list[dataclasses.Field]:
    return [f for f in _fields(cls) if "array" in f.metadata]


def _scalar_fields(cls) -> list[dataclasses.Field]:
    return [f for f in _fields(cls) if "array" not in f.metadata]


def _rows(a: dict) -> int:
    s = a.get("shape") if isinstance(a, dict) else None
    return s[0] if isinstance(s, list) and s and isinstance(s[0], int) else 0


def mutate_array(a: dict, spec: m.ArraySpec, d: Draw, rng: np.random.Generator) -> tuple[Any, str]:
    """One mutation of an array's wire form {dtype, shape, data}."""
    a = dict(a)
    n = _rows(a)
    k = d.integer(0, 11)
    if k <= 1:
        a["dtype"] = d.choice(DTYPES)
        return a, f"dtype={a['dtype']!r}"
    if k == 2:  # the same bytes, the other byte order
        dt = np.dtype(a["dtype"])
        a["dtype"] = dt.newbyteorder("S").str if dt.itemsize > 1 else ">" + dt.str[1:]
        return a, "byteorder"
    if k <= 4:
        a["shape"] = d.choice(SHAPES)(n)
        return a, f"shape={str(a['shape'])[:40]}"
    if k == 5:
        data = a["data"]
        cut = d.choice((1, 2, 3, 4, 7, len(data) // 2 + 1, len(data)))
        a["data"] = data[: max(0, len(data) - cut)] if d.boolean() else data + d.blob(cut)
        return a, "data-length"
    if k == 6:
        a["data"] = d.choice(("", "abc", [], [1.0, 2.0], None, 0, {}, a["data"].hex()))
        return a, "data-type"
    if k == 7:
        key = d.choice(("dtype", "shape", "data"))
        if d.boolean():
            del a[key]
            return a, f"no-{key}"
        a["extra"] = 1
        return a, "extra-key"
    if k == 8:
        return d.choice(([], [[0.0, 0.0, 0.0]], 0, None, "x", b"\x00" * 12, [a])), "not-a-map"
    # contents: rows of NaN, inf, huge, tiny, beyond the limit (only where the shape is sane)
    try:
        arr = np.frombuffer(a["data"], np.dtype(a["dtype"])).copy()
    except (ValueError, TypeError):
        return a, "contents-skipped"
    if arr.size == 0 or arr.dtype.kind not in "fiu":
        a["shape"] = d.choice(SHAPES)(n)
        return a, f"shape={str(a['shape'])[:40]}"
    pick = rng.random(arr.size) < d.choice((0.01, 0.3, 1.0))
    if arr.dtype.kind == "f":
        v = d.choice(
            (
                NAN,
                INF,
                -INF,
                3.4e38,
                -3.4e38,
                1e-45,
                -0.0,
                COORD_LIMIT_M * 1.01,
                COORD_LIMIT_M,
                1e300,
            )
        )
        with np.errstate(over="ignore", invalid="ignore"):
            arr[pick] = v
        a["data"] = arr.tobytes()
        return a, f"contents={v!r}"
    info = np.iinfo(arr.dtype)
    arr[pick] = d.choice((info.min, info.max, 0))
    a["data"] = arr.tobytes()
    return a, "contents-int-extremes"


def mutate_wire(raw: dict, cls: type[m.Message], d: Draw) -> tuple[Any, str]:
    """One structural mutation of a message's msgpack map (returns the new map and a label)."""
    raw = dict(raw)
    rng = d.rng()
    k = d.integer(0, 12)
    if k == 0:
        raw["_type"] = d.choice(
            (
                *(t.TYPE for t in MESSAGE_TYPES if t is not cls),
                "Nope",
                "",
                5,
                None,
                ["Pose"],
                cls.TYPE.lower(),
            )
        )
        return raw, f"_type={raw['_type']!r}"
    if k == 1:
        if d.boolean(0.2):
            raw.pop("_v", None)
            return raw, "no-_v"
        raw["_v"] = d.choice((0, 2, -1, "1", 1.0, True, None, 2**64 - 1, [1]))
        return raw, f"_v={raw['_v']!r}"
    if k == 2:
        name = d.choice([f.name for f in _fields(cls)] + ["_type"])
        raw.pop(name, None)
        return raw, f"missing={name}"
    if k == 3:
        raw[d.choice(("extra", "Seq", "n_dropped_nonfinite", 1, "", "__class__"))] = wild_scalar(d)
        return raw, "unknown-field"
    if k <= 6 and _scalar_fields(cls):
        f = d.choice(_scalar_fields(cls))
        if f.type in ("dict", dict) and d.boolean(0.7):
            v = d.choice(WILD_MAPS)
        else:
            v = wild_scalar(d) if d.boolean(0.8) else wild_float(d)
        raw[f.name] = v
        return raw, f"{f.name}={str(v)[:20]}"
    arrays = _array_fields(cls)
    if k <= 9 and arrays:
        f = d.choice(arrays)
        if not isinstance(raw.get(f.name), dict):
            return raw, "skip"  # an earlier mutation took the array away
        try:
            raw[f.name], how = mutate_array(raw[f.name], f.metadata["array"], d, rng)
        except Exception:  # noqa: BLE001 - an earlier mutation left no array to work on
            return raw, "skip"
        return raw, f"{f.name}:{how}"
    if k == 10 and arrays:  # a group member with fewer or more rows than the others
        grouped = [f for f in arrays if f.metadata["array"].group]
        if grouped:
            f = d.choice(grouped)
            try:
                a = dict(raw[f.name])
                arr = np.frombuffer(a["data"], np.dtype(a["dtype"])).reshape(a["shape"])
            except (KeyError, TypeError, ValueError):
                return raw, "skip"
            arr = arr[:-1] if len(arr) and d.boolean() else np.concatenate([arr, arr[:1] + 0])
            a["shape"], a["data"] = list(arr.shape), arr.tobytes()
            raw[f.name] = a
            return raw, f"{f.name}:rows"
    if k == 11:
        return d.choice(([], [raw], 0, "map", None, b"\x80", {"_type": cls.TYPE})), "not-a-map"
    # a field nested very deep
    name = d.choice([f.name for f in _fields(cls)])
    depth = d.choice((10, 100, 600))
    v: Any = 1.0
    for _ in range(depth):
        v = [v] if d.boolean(0.9) else {"x": v}
    raw[name] = v
    return raw, f"{name}:nested{depth}"


def pack(raw: Any, old_spec: bool = False) -> bytes:
    """msgpack bytes of a (mutated) map. `old_spec` packs bytes as raw strings (msgpack before
    2013), so array data arrives as a string that is usually not UTF-8."""
    return msgpack.packb(raw, use_bin_type=not old_spec)


def deep_nesting(depth: int, json_form: bool = False) -> bytes:
    """A payload nested `depth` levels (beyond any recursion limit), built without recursion."""
    if json_form:
        return b"[" * depth + b"]" * depth
    return b"\x91" * depth + b"\xc0"  # fixarray of one element, `depth` times, then nil


def byte_mutation(payload: bytes, d: Draw) -> tuple[bytes, str]:
    """Truncate, flip, insert, append or replace bytes of a payload."""
    n = len(payload)
    k = d.integer(0, 6)
    if k == 0 or n == 0:
        cut = d.integer(0, max(n - 1, 0))
        return payload[:cut], f"truncated@{cut}"
    if k == 1:
        b = bytearray(payload)
        for _ in range(d.integer(1, 8)):
            i = d.integer(0, n - 1)
            b[i] ^= 1 << d.integer(0, 7)
        return bytes(b), "bitflips"
    if k == 2:
        i = d.integer(0, n)
        return payload[:i] + d.blob(d.integer(1, 16)) + payload[i:], "inserted"
    if k == 3:
        return payload + d.blob(d.integer(1, 64)), "trailing"
    if k == 4:
        i = d.integer(0, n - 1)
        return payload[:i] + bytes([d.choice((0xC1, 0xDD, 0xDF, 0xC6, 0xFF, 0x00))]) + payload[
            i + 1 :
        ], "bad-byte"
    if k == 5:
        return payload * 2, "twice"
    return d.blob(d.choice((0, 1, 2, 16, 1000))), "random-bytes"


def oversize_payload(cls: type[m.Message], extra: int = 1) -> bytes:
    """A message larger than MAX_PAYLOAD_BYTES: a valid envelope and one huge bin field."""
    head = msgpack.packb({"_type": cls.TYPE, "_v": m.SCHEMA_VERSION}, use_bin_type=True)
    assert head[0] == 0x82  # a fixmap of two entries: make it three
    size = MAX_PAYLOAD_BYTES + extra
    pad = msgpack.packb("pad") + b"\xc6" + size.to_bytes(4, "big")
    return bytes([0x83]) + head[1:] + pad + bytes(size)


@dataclass
class Mutant:
    """One generated payload. `mode`: valid | hostile | wire | bytes | oversize; `how` says what
    was done to it."""

    payload: bytes
    mode: str
    how: str


# valid 10 %, hostile 20 %, structural 55 %, bytes 10 %, nesting 5 %
MODES = (
    "valid",
    "valid",
    "hostile",
    "hostile",
    "hostile",
    "hostile",
    *("wire",) * 11,
    "bytes",
    "bytes",
    "nested",
)


def message_payload(
    cls: type[m.Message], d: Draw, ctx: Context | None = None, mode: str | None = None
) -> Mutant:
    """A msgpack payload of type `cls`: valid, hostile, mutated or broken (`mode`, or drawn)."""
    ctx = ctx or Context()
    mode = mode or d.choice(MODES)
    if mode == "oversize":
        return Mutant(oversize_payload(cls, d.integer(1, 4096)), mode, "over 64 MiB")
    if mode == "nested":
        return Mutant(deep_nesting(d.choice((100, 1000, 100_000))), mode, "deep nesting")
    if mode == "valid":
        return Mutant(encode(plausible(cls, d, ctx)), mode, "plausible")
    if mode == "hostile":
        return Mutant(encode(hostile(cls, d, ctx)), mode, "hostile values")
    base = plausible(cls, d, ctx) if d.boolean(0.7) else hostile(cls, d, ctx)
    if mode == "bytes":
        payload, how = byte_mutation(encode(base), d)
        return Mutant(payload, mode, how)
    raw: Any = wire(base)
    hows = []
    for _ in range(d.choice((1, 1, 1, 2, 3))):
        if not isinstance(raw, dict):
            break
        raw, how = mutate_wire(raw, cls, d)
        hows.append(how)
    old_spec = d.boolean(0.05)
    if old_spec:
        hows.append("raw-strings")
    if not _packable(raw):
        raw, hows = wire(base), ["unpackable-mutation-skipped"]
    return Mutant(pack(raw, old_spec), "wire", ";".join(hows))


# -- the JSON form ---------------------------------------------------------------------------------


def _json_dumps(obj) -> bytes:
    return json.dumps(
        obj, allow_nan=True, default=lambda o: o.hex() if isinstance(o, bytes) else str(o)
    ).encode()


def mutate_json(obj: dict, cls: type[m.Message], d: Draw) -> tuple[Any, str]:
    """One mutation of a message's JSON object (arrays are nested lists there)."""
    obj = dict(obj)
    names = [f.name for f in _fields(cls)]
    k = d.integer(0, 9)
    if k == 0:
        obj["_type"] = d.choice(("Nope", 5, None, *(t.TYPE for t in MESSAGE_TYPES)))
        return obj, "_type"
    if k == 1:
        obj["_v"] = d.choice((2, "1", 1.0, None, True))
        return obj, "_v"
    if k == 2:
        obj.pop(d.choice(names), None)
        return obj, "missing"
    if k == 3:
        obj["extra"] = 1
        return obj, "unknown-field"
    name = d.choice(names)
    v = obj.get(name)
    if k <= 5:
        obj[name] = d.choice(
            (
                *WILD_SCALARS[:30],
                10**400,
                1e400,
                -1e400,
                "1,2",
                [None],
                [[1, 2], [3]],
                [["1", "2", "3"]],
                [[NAN, 0, 0]],
                [[1e400] * 3],
                [[10**400, 0, 0]],
                [True, False],
                [[0, 0, 0]] * 3,
            )
        )
        return obj, f"{name}=wild"
    if k == 6 and isinstance(v, list) and v:  # one row of another length
        obj[name] = v + [v[0][:-1] if isinstance(v[0], list) else [v[0]]]
        return obj, f"{name}:ragged"
    if k == 7 and isinstance(v, list):
        obj[name] = [[INF] * 3 if isinstance(x, list) else NAN for x in v] or [NAN]
        return obj, f"{name}:nonfinite"
    if k == 8:
        obj[name] = {"dtype": "<f4", "shape": [1, 3], "data": "AAAA"}  # the wire form, in JSON
        return obj, f"{name}:wire-form"
    obj[name] = NESTED_JSON  # spliced in as text by `json_payload` (json.dumps would recurse)
    return obj, f"{name}:nested"


NESTED_JSON = "\x00nested\x00"


def json_payload(
    cls: type[m.Message], d: Draw, ctx: Context | None = None, mode: str | None = None
) -> Mutant:
    """A JSON payload of type `cls`: valid, hostile, mutated at the JSON level, or broken text."""
    # arrays as lists cost Python objects per value: keep hostile clouds small here
    ctx = dataclasses.replace(ctx or Context(), big_points=5000)
    mode = mode or d.choice(("valid", "hostile", "json", "json", "json", "text"))
    base = plausible(cls, d, ctx) if mode != "hostile" else hostile(cls, d, ctx)
    text = to_json(base)
    if mode in ("valid", "hostile"):
        obj = json.loads(text)
        if d.boolean(0.3):  # the short form a user types: no envelope, optional fields left out
            for k in ("_type", "_v", *cls.JSON_OPTIONAL):
                if d.boolean():
                    obj.pop(k, None)
        return Mutant(_json_dumps(obj), mode, "plausible" if mode == "valid" else "hostile")
    if mode == "text":
        k = d.integer(0, 7)
        if k == 0:
            return Mutant(text[: d.integer(0, len(text) - 1)], mode, "truncated")
        if k == 1:
            return Mutant(deep_nesting(d.choice((1000, 200_000)), json_form=True), mode, "nesting")
        if k == 2:
            return Mutant(b"\xff\xfe" + text, mode, "invalid-utf8")
        if k == 3:
            return Mutant(b"\xef\xbb\xbf" + text, mode, "bom")
        if k == 4:
            return Mutant(text + b" trailing", mode, "trailing")
        if k == 5:
            return Mutant(
                d.choice((b"", b"null", b"[]", b"1", b'"x"', b"NaN", b"{")), mode, "not-an-object"
            )
        if k == 6:
            return Mutant(text.replace(b"0.", b"1e400", 1), mode, "overflow")
        payload, how = byte_mutation(text, d)
        return Mutant(payload, mode, how)
    obj: Any = json.loads(text)
    hows = []
    for _ in range(d.choice((1, 1, 2))):
        if not isinstance(obj, dict):
            break
        obj, how = mutate_json(obj, cls, d)
        hows.append(how)
    try:
        payload = _json_dumps(obj)
    except (ValueError, RecursionError):
        payload, hows = text, ["unserialisable-mutation-skipped"]
    nested = json.dumps(NESTED_JSON).encode()
    if nested in payload:
        depth = d.choice((50, 5000, 100_000))
        payload = payload.replace(nested, b"[" * depth + b"0" + b"]" * depth)
    return Mutant(payload, "json", ";".join(hows))


# -- what the codec makes of a payload ------------------------------------------------------------


def predict(
    payload: bytes, expect: type[m.Message], *, drop_nonfinite: bool = False, as_json: bool = False
) -> str | None:
    """None when the codec accepts the payload as a `expect`, else the MessageError kind (what a
    service decoding it must count). Anything else escaping the codec propagates: a bug."""
    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # overflowing norms of wild values
            if as_json:
                from_json(payload, expect, drop_nonfinite=drop_nonfinite)
            else:
                decode(payload, expect, drop_nonfinite=drop_nonfinite)
    except MessageError as exc:
        return exc.kind
    return None


# -- queries --------------------------------------------------------------------------------------


@dataclass
class QueryCase:
    """One query: selector parameters (without '?'), payload, encoding and what was done."""

    params: str
    payload: bytes | None
    encoding: str | None
    how: str


# zenoh 1.10.2 panics in the *sending* process (DidntWrite, then a poisoned transport) when an
# encoding string exceeds 255 bytes: no smana process sends one, so the fuzz stops at 255.
ENCODINGS = (
    "application/json",
    "application/msgpack",
    "text/plain",
    "text/json",
    "",
    "application/octet-stream",
    "zenoh/bytes",
    "application/json;charset=utf-16",
    "x" * 255,
)
SAVE_NAMES_OK = ("fuzz.npz", "fuzz-2.npz")  # accepted saves overwrite these two only
SAVE_NAMES_BAD = (
    "../escape.npz",
    "/tmp/escape.npz",
    "sub/dir.npz",
    ".hidden.npz",
    "map.npz/",
    "x.npz\x00.txt",
    "n" * 300 + ".npz",
    "..",
    ".",
    "",
    "x.txt",
    "config.toml",
    "x.NPZ",
    " .npz",
    "\u2215x.npz",
    "\\escape.npz",
    "nul.npz\n",
    "a\x00b.npz",
    "n" * 248 + ".npz",
    5,
    None,
    ["a.npz"],
    {"a": 1},
)


def _number_text(d: Draw) -> str:
    return d.choice(
        (
            "0",
            "1.5",
            "-2",
            "nan",
            "inf",
            "-inf",
            "1e400",
            "1e308",
            "",
            " ",
            "x",
            "1,2",
            "0x10",
            "1_0",
            str(2**64),
            "-0",
            "\u0661",
        )
    )


def _numbers(d: Draw, n: int) -> list:
    return [
        d.choice(
            (
                0.0,
                1.0,
                -3.5,
                2.0,
                50.0,
                -50.0,
                NAN,
                INF,
                1e300,
                -1e300,
                2**64,
                "1",
                None,
                True,
                [1.0],
            )
        )
        for _ in range(n)
    ]


def _sane_numbers(d: Draw, ctx: Context, n: int) -> list[float]:
    x0, y0, x1, y1 = ctx.area
    return [round(d.unit() * (x1 - x0) + x0, 3) for _ in range(n)]


def _body(d: Draw, as_json: bool, obj) -> tuple[bytes | None, str | None]:
    if as_json:
        try:
            return _json_dumps(obj), "application/json"
        except (ValueError, TypeError, RecursionError):
            return b"{}", "application/json"
    if not _packable(obj):
        obj = {}
    return msgpack.packb(obj, use_bin_type=True), "application/msgpack"


def _box_case(d: Draw, ctx: Context, n: int) -> tuple[str, Any]:
    """A box query: in the body or the selector, sane or wild."""
    nums = (
        _sane_numbers(d, ctx, n) if d.boolean(0.4) else _numbers(d, d.choice((n, n, 0, 1, n + 1)))
    )
    if d.boolean(0.3):
        text = ",".join(_number_text(d) if d.boolean(0.3) else str(v) for v in nums)
        return "box=" + text, None
    return "", {"box": d.choice((nums, ",".join(map(str, nums)), 5, None, [nums]))}


def query_case(service: str, name: str, d: Draw, ctx: Context | None = None) -> QueryCase:
    """A query to `smana/<robot>/<service>/<name>`, as its handler expects it or not at all."""
    ctx = ctx or Context()
    as_json = d.boolean()
    if d.boolean(0.15):  # nothing like what the handler expects
        params = ";".join(
            f"{d.choice(('format', 'box', 'x', 'start', 'a'))}={_number_text(d)}"
            for _ in range(d.integer(0, 3))
        )
        k = d.integer(0, 3)
        if k == 0:
            payload = None
        elif k == 1:
            payload = d.blob(d.choice((1, 8, 100)))
        elif k == 2:
            payload = deep_nesting(d.choice((1000, 100_000)), json_form=as_json)
        else:
            payload = _body(d, as_json, wild_value(d))[0]
        return QueryCase(params, payload, d.choice(ENCODINGS), "random")
    params, obj, how = "", None, "plausible"
    if (service, name) == ("mapper", "snapshot"):
        params, obj = _box_case(d, ctx, 6) if d.boolean(0.7) else ("", None)
        how = "box"
    elif (service, name) == ("navgraph", "graph"):
        params, obj = _box_case(d, ctx, 4) if d.boolean(0.7) else ("", None)
        how = "box"
    elif service == "coordinator" and name.split("/")[0] == "claim":  # claim/<member>
        obj, how = coordinator_claim(d, ctx)
    elif (service, name) == ("mapper", "save"):
        good = d.boolean(0.3)
        nm = d.choice(SAVE_NAMES_OK if good else SAVE_NAMES_BAD)
        obj, how = ({"name": nm}, "name-ok" if good else "name-hostile")
    elif (service, name) == ("mapper", "point"):
        k = d.integer(0, 5)
        pts: Any
        if k == 0:
            pts = [_sane_numbers(d, ctx, 3) for _ in range(d.integer(1, 20))]
        elif k == 1:
            pts = _sane_numbers(d, ctx, 3)
        elif k == 2:
            pts = [_numbers(d, d.choice((2, 3, 4))) for _ in range(d.integer(1, 5))]
        elif k == 3:
            pts = [[0.0, 0.0, 0.0]] * d.choice((100_001, 100_000))
        elif k == 4:
            pts = d.choice((None, "1,2,3", 5, [], [[]], {"x": 1}, [[1, 2, 3], [4, 5]]))
        else:
            pts = [[1e300, -1e300, 1e-300]] * d.integer(1, 3)
        obj, how = {"points": pts}, f"points{k}"
    elif (service, name) == ("navgraph", "node"):
        if d.boolean(0.4):
            params = f"x={_number_text(d)};y={_number_text(d)}"
            how = "params"
        else:
            obj = {
                "x": d.choice(
                    (*_sane_numbers(d, ctx, 1), *_numbers(d, 1), 1e6, -1e6, -50.0, 49.99999)
                ),
                "y": d.choice((*_sane_numbers(d, ctx, 1), NAN, "2")),
            }
            if d.boolean(0.1):
                obj.pop("y")
    elif (service, name) == ("planner", "path"):
        k = d.integer(0, 3)
        if k == 0:
            params = (
                f"start={_number_text(d)},{_number_text(d)};"
                f"goal={','.join(map(str, _sane_numbers(d, ctx, 2)))}"
            )
            if d.boolean(0.3):
                params += f";h_f={_number_text(d)};allow_unknown={d.choice(('1', 'no', 'x'))}"
            return QueryCase(params, None, None, "params")
        mut = (
            json_payload(m.PathRequest, d, ctx)
            if as_json
            else message_payload(m.PathRequest, d, ctx)
        )
        enc = "application/json" if as_json else "application/msgpack"
        if as_json and d.boolean(0.2):
            return QueryCase("format=json", mut.payload, None, f"path-json-param:{mut.how}")
        return QueryCase("", mut.payload, enc, f"path:{mut.mode}:{mut.how}")
    else:  # stats, status, explorer state: no body expected; send one anyway sometimes
        if d.boolean(0.3):
            obj = wild_value(d)
            how = "unexpected-body"
    if obj is None:
        enc = "application/json" if as_json else None
        return QueryCase(
            params or ("format=json" if as_json and d.boolean() else ""), None, enc, how
        )
    payload, enc = _body(d, as_json, obj)
    return QueryCase(params, payload, enc, how)


# -- the coordinator (issue 25) -------------------------------------------------------------------

FLEET_MEMBERS = ("fuzzc1", "fuzzc2")  # the coordinator's members in the campaign


def _goal(d: Draw, ctx: Context) -> Any:
    k = d.integer(0, 5)
    if k <= 1:
        return _sane_numbers(d, ctx, 2)
    if k == 2:
        return _numbers(d, d.choice((2, 2, 1, 3)))
    if k == 3:
        return d.choice((None, "1,2", [], [[1, 2]], {"x": 1}, [True, False], ["1", "2"]))
    if k == 4:
        return [d.choice((1e308, -1e308, 2**64, -(2**63))), d.choice((0.0, 1e-300))]
    return wild_value(d)


def coordinator_claim(d: Draw, ctx: Context) -> tuple[Any, str]:
    """A `coordinator/claim` body: a member (or not) claiming a goal (sane or wild), releasing,
    or leaving a field out."""
    robot = d.choice((*FLEET_MEMBERS, *FLEET_MEMBERS, "stranger", "", 5, None, "x" * 300))
    k = d.integer(0, 5)
    if k <= 2:
        return {"robot": robot, "goal": _goal(d, ctx)}, "claim"
    if k == 3:
        return {"robot": robot, "goal": None}, "release"
    if k == 4:
        return d.choice(({"robot": robot}, {"goal": [0, 0]}, {}, [robot, [0, 0]])), "missing"
    return {"robot": robot, "goal": _goal(d, ctx), d.choice(("x", "goal2")): 1}, "extra-field"


def explorer_state(d: Draw, ctx: Context) -> tuple[bytes, str]:
    """A member's `explorer/state` as the coordinator reads it (msgpack of a map with `goal`
    {"xy": [x, y]}, `mode`, `distance_m`), plausible, wild or broken."""
    k = d.integer(0, 5)
    if k == 0:
        return d.blob(d.choice((0, 1, 7, 64))), "random bytes"
    if k == 1:
        obj = wild_value(d)
        return (msgpack.packb(obj, use_bin_type=True) if _packable(obj) else b"\xc1"), "wild"
    goal: Any = {"xy": _goal(d, ctx)} if d.boolean(0.8) else d.choice((None, {}, [], "x", 1))
    state = {
        "mode": d.choice(("exploring", "done", "idle", "", None, 5)),
        "goal": goal,
        "distance_m": d.choice((0.0, 1.5, NAN, INF, -1.0, 1e308, "1", None, True)),
    }
    if k == 2:
        del state[d.choice(sorted(state))]
    payload = msgpack.packb(state, use_bin_type=True) if _packable(state) else b"\xc1"
    if k == 3 and len(payload) > 1:
        payload = payload[: d.integer(1, len(payload) - 1)]
    return payload, f"state{k}"


def predict_explorer_state(payload: bytes) -> str | None:
    """What the coordinator counts a member's state under: None (accepted) or "malformed", as
    `CoordinatorService.on_state` decides it (a second statement of its rule)."""
    try:
        state = msgpack.unpackb(payload)
        goal = state.get("goal") if isinstance(state, dict) else None
        if goal and len([float(v) for v in goal["xy"]]) < 2:
            return "malformed"
        dist = state.get("distance_m") if isinstance(state, dict) else None
        if isinstance(dist, int | float):
            float(dist)
    except Exception:  # noqa: BLE001 - whatever the handler's try block turns into "malformed"
        return "malformed"
    return None
