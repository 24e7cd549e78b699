"""The coordinator's handlers under the fuzz generators of `lab/fuzz_messages.py` (issue 25), in
process (no zenoh: its handlers are plain methods): claims and members' states, sane and wild, never
raise anything but a refusal, a state is refused exactly when `fuzz.predict_explorer_state` says so
(what `smana bench fuzz` books against), and every claims snapshot still encodes."""

from __future__ import annotations

import json
import time

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smana.common import keys
from smana.common.config import SmanaConfig
from smana.common.messages import MessageError
from smana.common.service import Reject
from smana.lab import fuzz_messages as fuzz
from smana.services.coordinator.service import CoordinatorService

SETTINGS = settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


class HypothesisDraw(fuzz.Draw):
    def __init__(self, data):
        self.data = data

    def integer(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi))

    def choice(self, options):
        return self.data.draw(st.sampled_from(options))


class _Pub:
    def __init__(self):
        self.sent = []

    def put(self, obj):
        self.sent.append(msgpack.packb(obj))  # what the service's publisher would encode


class _Req:
    """A claim query on a member's key (`keys.claim`), as the coordinator's queryable gets it."""

    def __init__(self, body, key: str):
        self._body = body
        self.key = key

    def body(self):
        return self._body


def coordinator() -> CoordinatorService:
    cfg = SmanaConfig.load(None, [f"fleet.robots={json.dumps(list(fuzz.FLEET_MEMBERS))}"])
    s = CoordinatorService(cfg)
    s.claims_pub = _Pub()
    return s


def _claim_body(case: fuzz.QueryCase):
    """The body the service would hand its handler, or None when `Request.body` refuses it."""
    if not case.payload:
        return {}
    as_json = (case.encoding or "").startswith(("application/json", "text/"))
    try:
        body = json.loads(case.payload) if as_json else msgpack.unpackb(case.payload)
    except Exception:  # noqa: BLE001 - Request.body refuses these as malformed
        return None
    return body if isinstance(body, dict) else None


@SETTINGS
@given(data=st.data())
def test_claims_and_states_are_refused_or_taken_never_a_crash(data):
    d, ctx = HypothesisDraw(data), fuzz.Context()
    s = coordinator()
    # a member holding a claim: the states that follow are checked against it
    first = fuzz.FLEET_MEMBERS[0]
    s.on_claim(first, _Req({"robot": first, "goal": [1.0, 2.0]}, keys.claim(s.robot, first)))
    for _ in range(d.integer(1, 6)):
        if d.boolean():
            body = _claim_body(fuzz.query_case("coordinator", "claim", d, ctx))
            if body is not None:
                member = d.choice(fuzz.FLEET_MEMBERS)  # the key it came on; the body may differ
                try:
                    msgpack.packb(s.on_claim(member, _Req(body, keys.claim(s.robot, member))))
                except (Reject, MessageError):
                    pass
        else:
            payload, how = fuzz.explorer_state(d, ctx)
            kind = None
            try:
                s.on_state(d.choice(fuzz.FLEET_MEMBERS), payload)
            except Reject as exc:
                kind = exc.kind
            assert kind == fuzz.predict_explorer_state(payload), (how, payload)
        msgpack.packb(s._claims())


def test_a_state_with_a_one_number_goal_is_refused_while_a_claim_is_held():
    # found by the fuzz: an IndexError (an `internal` rejection) when the member held a claim
    s = coordinator()
    s.on_claim(
        "fuzzc1", _Req({"robot": "fuzzc1", "goal": [1.0, 2.0]}, keys.claim(s.robot, "fuzzc1"))
    )
    for xy in ([5.0], []):
        with pytest.raises(Reject) as info:
            s.on_state("fuzzc1", msgpack.packb({"goal": {"xy": xy}, "mode": "exploring"}))
        assert info.value.kind == "malformed"
    assert s.book.snapshot(time.monotonic()) == {"fuzzc1": [1.0, 2.0]}
