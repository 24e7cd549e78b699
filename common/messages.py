"""Message contracts: every schema that crosses a process, and its validating codec.

Wire format: one msgpack map per message, `{"_type": "SemanticCloud", "_v": 1, <fields>}`. A numpy
array travels as `{"dtype": "<f4", "shape": [N, 3], "data": <raw bytes>}`, so a 131k-point cloud is
three memcpys, not 131k Python objects. The same messages also have a JSON form (arrays as nested
lists) for queries from any zenoh tool.

Decoded arrays are read-only views of the payload (no copy); copy before modifying them.
Decoding validates everything and raises one error type, `MessageError`, whose `kind` names what was
wrong (services count errors by kind). Nothing a remote peer sends can crash a decoder.

This module holds the schemas; the base class, field kinds and bounds are in `message_schema.py`,
the codec in `codec.py`. Import all of it from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from smana.common.codec import decode, encode, from_dict, from_json, json_default, to_json
from smana.common.message_schema import (
    COORD_LIMIT_M,
    ERROR_KINDS,
    INT_LIMIT,
    MAX_PAYLOAD_BYTES,
    REGISTRY,
    RESOLUTION_RANGE_M,
    SCHEMA_VERSION,
    STAMP_LIMIT_S,
    ArraySpec,
    Message,
    MessageError,
    array,
    scalar,
)

# The message API, whichever module holds each part: the base and bounds (message_schema.py), the
# schemas (here), the codec (codec.py).
__all__ = [
    "COORD_LIMIT_M",
    "ERROR_KINDS",
    "INT_LIMIT",
    "MAX_PAYLOAD_BYTES",
    "REGISTRY",
    "RESOLUTION_RANGE_M",
    "SCHEMA_VERSION",
    "STAMP_LIMIT_S",
    "VALUES_KINDS",
    "ArraySpec",
    "GraphPatch",
    "MapDelta",
    "Message",
    "MessageError",
    "PathReply",
    "PathRequest",
    "Pose",
    "SemanticCloud",
    "ServiceStatus",
    "VelocityCommand",
    "array",
    "decode",
    "encode",
    "from_dict",
    "from_json",
    "json_default",
    "matrix_to_quat",
    "quat_to_matrix",
    "scalar",
    "to_json",
]

# -- the messages ---------------------------------------------------------------------------------


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
    changes (a restarted mapper) or jumps.

    The label distribution a voxel holds (version 2): `labels` with its probability
    `confidences`, the second most likely class `alt_labels` (0: none) with its probability
    `alt_confidences`; the rest of the mass is "other or unknown". octree-bayes sends its top 2,
    the TSDF the top 2 of its normalised label vector, octree-max its label and confidence with
    no second class. A version-1 delta, or one whose two alt arrays are empty, carries no
    distribution: it reads as certain (`has_distribution` False, a local field that never
    travels)."""

    VERSION: ClassVar[int] = 2

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
    alt_labels: np.ndarray = array(["u2"], [None], group="m", since=2)
    alt_confidences: np.ndarray = array(["f4"], [None], group="m", since=2)
    has_distribution: bool = field(default=True, metadata={"local": True})

    def __post_init__(self):
        # Made without a distribution (version 1, or a writer that has none: both alt arrays
        # empty while there are voxels): certain.
        if len(self.labels) and len(self.alt_labels) == 0 and len(self.alt_confidences) == 0:
            self.upgrade(1)

    def upgrade(self, version: int) -> None:
        if version < 2:
            n = len(self.labels)
            self.alt_labels = np.zeros(n, np.uint16)
            self.alt_confidences = np.zeros(n, np.float32)
            self.has_distribution = False

    def wire_overrides(self) -> dict:
        if self.has_distribution:
            return {}
        return {"alt_labels": np.zeros(0, np.uint16), "alt_confidences": np.zeros(0, np.float32)}

    def check(self) -> None:
        if self.values_kind not in VALUES_KINDS:
            raise MessageError(
                "value",
                f"MapDelta.values_kind: one of {list(VALUES_KINDS)}, got {self.values_kind!r}",
            )


@dataclass
class GraphPatch(Message):
    """Navigation-graph nodes that changed: grid indices from `origin_xy` at `resolution_m`, and the
    nodes' label, height and flags (FLAG_KNOWN | FLAG_OBSTACLE | FLAG_SAFETY_ZONE |
    FLAG_DOUBTFUL).
    `producer` names the navgraph session that numbered the stream (see MapDelta).

    Version 2 adds each node's label distribution (`common/navgrid.py` RISK_LAYERS): `p_label`,
    the probability of `labels` x 255, the second most likely class `alt_labels` (0: none) and
    its probability x 255 `p_alt`. A version-1 patch, or one whose three distribution arrays are
    empty, reads as certain (255, 0, 0)."""

    VERSION: ClassVar[int] = 2

    stamp_s: float = _stamp_field()
    seq: int = _seq_field()
    resolution_m: float = scalar(0.2, *RESOLUTION_RANGE_M)
    origin_xy: np.ndarray = array(["f8"], [2], limit=COORD_LIMIT_M)
    cells: np.ndarray = array(["i4"], [None, 2], group="k")
    labels: np.ndarray = array(["u2"], [None], group="k")
    heights: np.ndarray = array(["f4"], [None], group="k", limit=COORD_LIMIT_M)
    flags: np.ndarray = array(["u1"], [None], group="k")
    producer: str = ""
    alt_labels: np.ndarray = array(["u2"], [None], group="k", since=2)
    p_label: np.ndarray = array(["u1"], [None], group="k", since=2)
    p_alt: np.ndarray = array(["u1"], [None], group="k", since=2)

    def __post_init__(self):
        # Made without a distribution (a version-1 patch, or a writer that has none): certain.
        n = len(self.cells)
        if n and len(self.p_label) == 0 and len(self.alt_labels) == 0 and len(self.p_alt) == 0:
            self.upgrade(1)

    def upgrade(self, version: int) -> None:
        if version < 2:
            n = len(self.cells)
            self.alt_labels = np.zeros(n, np.uint16)
            self.p_label = np.full(n, 255, np.uint8)
            self.p_alt = np.zeros(n, np.uint8)

    def risk(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(alt_labels, p_label, p_alt), what `NavGrid.apply_patch(risk=...)` takes."""
        return self.alt_labels, self.p_label, self.p_alt


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
