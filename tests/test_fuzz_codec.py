"""In-process fuzz of the codec (issue 11): hypothesis drives the generators of
`lab/fuzz_messages.py` over every message type, in msgpack and JSON. Whatever the payload, `decode`
and `from_json` raise nothing but `MessageError`; a naive second statement of the schemas
(`support/schema_oracle.py`) says which error kinds a payload deserves, and checks every message the
codec lets through."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smana.common import messages as m
from smana.common.messages import MessageError, decode, encode, from_json
from smana.lab import fuzz_messages as fuzz
from smana.lab.fuzz_values import RandomDraw
from tests.support import schema_oracle as oracle

# Small "large" clouds: the suite runs many examples; the bench sends the big ones.
CTX = fuzz.Context(big_points=20_000)
SETTINGS = settings(
    max_examples=100,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
FEWER = settings(SETTINGS, max_examples=50)
TYPES = fuzz.MESSAGE_TYPES


class HypothesisDraw(fuzz.Draw):
    """The generators' choices, drawn (and shrunk) by hypothesis."""

    def __init__(self, data):
        self.data = data

    def integer(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi))

    def choice(self, options):
        return self.data.draw(st.sampled_from(options))


def test_every_message_type_is_fuzzed():
    assert {c.TYPE for c in TYPES} == set(m.REGISTRY)


def test_the_oracle_states_the_same_fields():
    for cls in TYPES:
        names = [f.name for f in dataclasses.fields(cls) if not f.metadata.get("local")]
        assert names == list(oracle.SCHEMA[cls.TYPE]), cls.TYPE


def _raw(payload: bytes):
    """The payload as the codec's msgpack reader sees it, or None when it is not msgpack."""
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # noqa: BLE001
        return None


def _same_scalar(a, b) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return float(a) == float(b) or (math.isnan(float(a)) and math.isnan(float(b)))
    return a == b


def problems(msg, drop_nonfinite: bool = False) -> list[str]:
    """The oracle's complaints about a decoded message."""
    return oracle.check_decoded(msg, drop_nonfinite)


def judge_wire(payload: bytes, cls, drop_nonfinite: bool) -> None:
    """The codec's verdict on a msgpack payload against the oracle's."""
    try:
        msg = decode(payload, cls, drop_nonfinite=drop_nonfinite)
        kind = None
    except MessageError as exc:
        msg, kind = None, exc.kind
    assert kind is None or kind in m.ERROR_KINDS
    if len(payload) > m.MAX_PAYLOAD_BYTES:
        assert kind == "oversize"
        return
    raw = _raw(payload)
    if raw is None:
        assert kind == "malformed", "not msgpack, yet decoded"
        return
    verdict = oracle.violations(raw, cls.TYPE, drop_nonfinite)
    if kind is not None:
        assert kind in verdict.kinds, f"codec says {kind!r}, oracle {verdict.kinds or 'valid'}"
        return
    assert not verdict.kinds, f"codec accepted a payload the oracle refuses: {verdict.kinds}"
    assert problems(msg, drop_nonfinite) == []
    # What came out is what went in (minus the rows a drop_nonfinite decode removes).
    spec = oracle.SCHEMA[cls.TYPE]
    for name, rule in spec.items():
        got = getattr(msg, name)
        if isinstance(rule, oracle.Arr):
            sent = verdict.arrays[name]
            if rule.group in verdict.dropped:
                sent = sent[~verdict.dropped[rule.group]]
            assert got.dtype.str == sent.dtype.str and got.shape == sent.shape, name
            assert got.tobytes() == sent.tobytes(), name
        elif isinstance(rule, oracle.Costs):
            want = {int(k): float(v) for k, v in raw[name].items()}
            assert got.keys() == want.keys() and all(_same_scalar(got[k], want[k]) for k in got)
        else:
            assert _same_scalar(got, raw[name]), name
    if cls is m.SemanticCloud:
        n = verdict.dropped.get("n")
        assert msg.n_dropped_nonfinite == (0 if n is None else int(n.sum()))


@pytest.mark.parametrize("cls", TYPES, ids=lambda c: c.TYPE)
@SETTINGS
@given(data=st.data(), drop=st.booleans())
def test_decode_fuzz(cls, data, drop):
    mutant = fuzz.message_payload(cls, HypothesisDraw(data), CTX)
    judge_wire(mutant.payload, cls, drop)


@pytest.mark.parametrize("cls", TYPES, ids=lambda c: c.TYPE)
@FEWER
@given(data=st.data())
def test_decode_fuzz_any_type(cls, data):
    """Decoding without an expected type: a payload of any type is judged as what it says."""
    payload = fuzz.message_payload(cls, HypothesisDraw(data), CTX).payload
    try:
        msg = decode(payload)
    except MessageError:
        return
    assert problems(msg) == []


@pytest.mark.parametrize("cls", TYPES, ids=lambda c: c.TYPE)
@SETTINGS
@given(data=st.data(), drop=st.booleans())
def test_from_json_fuzz(cls, data, drop):
    """JSON queries: only MessageError, and what is accepted satisfies the schema."""
    mutant = fuzz.json_payload(cls, HypothesisDraw(data), CTX)
    try:
        msg = from_json(mutant.payload, cls, drop_nonfinite=drop)
    except MessageError as exc:
        assert exc.kind in m.ERROR_KINDS
        return
    assert isinstance(msg, cls)
    assert problems(msg, drop) == [], mutant.how


@pytest.mark.parametrize("cls", TYPES, ids=lambda c: c.TYPE)
@FEWER
@given(data=st.data())
def test_valid_and_hostile_messages_round_trip(cls, data):
    """What the generators call valid or hostile, the codec must accept unchanged."""
    d = HypothesisDraw(data)
    msg = fuzz.plausible(cls, d, CTX) if d.boolean() else fuzz.hostile(cls, d, CTX)
    back = decode(encode(msg), cls)
    for f in dataclasses.fields(msg):
        a, b = getattr(msg, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            assert a.shape == b.shape and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name


def test_oversize_is_refused_before_parsing():
    payload = fuzz.oversize_payload(m.SemanticCloud)
    assert len(payload) > m.MAX_PAYLOAD_BYTES
    assert fuzz.predict(payload, m.SemanticCloud) == "oversize"
    assert fuzz.predict(payload, m.PathRequest, as_json=True) == "oversize"
    assert fuzz.predict(payload[: m.MAX_PAYLOAD_BYTES], m.SemanticCloud) == "malformed"


@pytest.mark.parametrize(
    "shape", [[2**32, 2**32], [2**63, 0], [2**64 - 1], [-1, 3], [0, 2**40], [2**31, 2**31, 0]]
)
def test_wrapping_and_negative_shapes(shape):
    raw = fuzz.wire(m.SemanticCloud())
    raw["points"] = {"dtype": "<f4", "shape": shape, "data": b""}
    assert fuzz.predict(fuzz.pack(raw), m.SemanticCloud) == "shape"


def test_query_cases_are_sendable():
    """Every query case the bench sends is well-formed enough to leave this process."""
    d = RandomDraw(3)
    for service, name in [
        ("mapper", "snapshot"),
        ("mapper", "save"),
        ("mapper", "point"),
        ("navgraph", "graph"),
        ("navgraph", "node"),
        ("planner", "path"),
        ("planner", "stats"),
        ("explorer", "state"),
    ]:
        for _ in range(50):
            case = fuzz.query_case(service, name, d)
            assert case.payload is None or isinstance(case.payload, bytes)
            assert "?" not in case.params and "#" not in case.params


# -- what the fuzz found in the codec (common/messages.py), fixed since ---------------------------


@pytest.mark.parametrize("version", [True, 1.0])
def test_version_must_be_an_int(version):
    raw = fuzz.wire(m.Pose())
    raw["_v"] = version
    assert fuzz.predict(fuzz.pack(raw), m.Pose) == "version"


@pytest.mark.parametrize("costs", [{"1": "nan"}, {"1": "inf"}, {1: True}, {1.5: 2.0}, {-5: 1.0}])
def test_class_costs_must_be_finite_numbers_by_class_id(costs):
    raw = fuzz.wire(m.PathRequest(start=np.zeros(2), goal=np.ones(2)))
    raw["class_costs"] = costs
    assert fuzz.predict(fuzz.pack(raw), m.PathRequest) in ("value", "nonfinite")


def test_a_hostile_pose_stays_within_the_coordinate_limit():
    """A hostile pose may be moved twice (to the limit's edge, then by noise), and its
    quaternion is scaled to the codec's bounds: it stays a pose the codec accepts, as every
    hostile message must be (3000 seeded draws; each once failed in some of them)."""
    from smana.lab.fuzz_values import RandomDraw

    for seed in range(3000):
        msg = fuzz.hostile(m.Pose, RandomDraw(seed), CTX)
        assert np.abs(msg.position).max() <= m.COORD_LIMIT_M, seed
        decode(encode(msg), m.Pose)
