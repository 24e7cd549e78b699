"""The fake zenoh (tests/support/fake_zenoh.py) behaves as zenoh does for what smana uses: the same
scenarios run on two real zenoh sessions over loopback (no router, multicast and gossip off) and
on two fake ones, and must give the same results."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from smana.common.zenoh_config import free_loopback_port
from tests.conftest import wait_for
from tests.support.fake_zenoh import FakeNetwork, RingChannel


def real_pair():
    port = free_loopback_port()

    def conf(**kw):
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("scouting/gossip/enabled", "false")
        for k, v in kw.items():
            c.insert_json5(k, json.dumps(v))
        return c

    a = zenoh.open(conf(**{"listen/endpoints": [f"tcp/127.0.0.1:{port}"]}))
    b = zenoh.open(conf(**{"connect/endpoints": [f"tcp/127.0.0.1:{port}"]}))
    return a, b


def fake_pair():
    net = FakeNetwork()
    return net.open(), net.open()


@pytest.fixture(params=["zenoh", "fake"])
def pair(request):
    a, b = real_pair() if request.param == "zenoh" else fake_pair()
    yield a, b
    b.close()
    a.close()


def known_to(session, key: str, timeout_s: float = 5.0) -> bool:
    """Whether `session` learns of a subscriber to `key` (a publisher of its own matches it).
    Real zenoh propagates declarations asynchronously, in the order they were made (the fake at
    once): a later declaration known means the earlier ones are too."""
    pub = session.declare_publisher(key)
    try:
        return wait_for(lambda: pub.matching_status.matching, timeout_s)
    finally:
        pub.undeclare()


def test_wildcard_subscriptions_get_what_matches(pair):
    a, b = pair
    got = []
    sub = b.declare_subscriber(
        "t/*/x", lambda s: got.append((str(s.key_expr), s.payload.to_bytes()))
    )
    deep = b.declare_subscriber("t/**")
    assert known_to(a, "t/b/y")  # only t/** matches: the one declared last
    # the last put ends the sequence: samples of one session arrive in order, so once it is in,
    # everything put before it that was going to arrive has
    for key in ("t/a/x", "t/b/y", "t/c/x", "u/a/x", "t/end/x"):
        a.put(key, key.encode())
    assert wait_for(lambda: got and got[-1][0] == "t/end/x", 5)
    assert got == [("t/a/x", b"t/a/x"), ("t/c/x", b"t/c/x"), ("t/end/x", b"t/end/x")]
    keys = []

    def drain_deep() -> bool:
        while (s := deep.try_recv()) is not None:
            keys.append(str(s.key_expr))
        return bool(keys) and keys[-1] == "t/end/x"

    assert wait_for(drain_deep, 5)
    assert keys == ["t/a/x", "t/b/y", "t/c/x", "t/end/x"]
    sub.undeclare()
    deep.undeclare()


def test_queries_get_replies_errors_and_parameters(pair):
    a, b = pair

    def on_query(q):
        params = dict(q.parameters)
        body = q.payload.to_bytes() if q.payload is not None else b""
        if params.get("fail"):
            q.reply_err(b"refused")
        else:
            q.reply(q.key_expr, json.dumps([str(q.key_expr), params, body.decode()]).encode())

    ignored = b.declare_queryable("t/silent", lambda q: None)  # keeps no query: ends at once
    qb = b.declare_queryable("t/q/**", on_query)
    # the one declared last answers: both are known (declarations arrive in order)
    assert wait_for(lambda: list(a.get("t/q/probe", timeout=1)), 5)
    replies = list(a.get("t/q/a?format=json;x=1", payload=b"hi", timeout=5))
    assert len(replies) == 1 and replies[0].err is None
    assert json.loads(replies[0].ok.payload.to_bytes()) == [
        "t/q/a",
        {"format": "json", "x": "1"},
        "hi",
    ]
    assert str(replies[0].ok.key_expr) == "t/q/a"
    replies = list(a.get("t/q/b?fail=1", timeout=5))
    assert replies[0].ok is None and replies[0].err.payload.to_bytes() == b"refused"
    t0 = time.monotonic()
    assert list(a.get("t/silent", timeout=5)) == []
    assert list(a.get("t/nobody", timeout=5)) == []
    assert time.monotonic() - t0 < 4
    qb.undeclare()
    ignored.undeclare()


def test_liveliness_tokens_history_and_departure(pair):
    a, b = pair
    token = a.liveliness().declare_token("t/alive/a")
    assert wait_for(lambda: list(b.liveliness().get("t/alive/a", timeout=1)), 5)
    seen = []
    sub = b.liveliness().declare_subscriber(
        "t/alive/*", lambda s: seen.append((str(s.key_expr), s.kind)), history=True
    )
    assert wait_for(lambda: seen, 5)
    assert seen == [("t/alive/a", zenoh.SampleKind.PUT)]
    assert [str(r.ok.key_expr) for r in b.liveliness().get("t/alive/**", timeout=2)] == [
        "t/alive/a"
    ]
    token.undeclare()
    assert wait_for(lambda: len(seen) == 2, 5)
    assert seen[1] == ("t/alive/a", zenoh.SampleKind.DELETE)
    assert not list(b.liveliness().get("t/alive/**", timeout=1))
    late = a.liveliness().declare_token("t/alive/b")  # held: zenoh may undeclare it when dropped
    assert wait_for(lambda: len(seen) == 3, 5)
    assert seen[2] == ("t/alive/b", zenoh.SampleKind.PUT)
    a.close()  # a session that goes takes its tokens with it
    assert wait_for(lambda: len(seen) == 4, 10)
    assert seen[3] == ("t/alive/b", zenoh.SampleKind.DELETE)
    sub.undeclare()
    late.undeclare()


def test_a_ring_channel_keeps_the_latest():
    a, b = fake_pair()
    for handler in (RingChannel(2), zenoh.handlers.RingChannel(1)):
        sub = b.declare_subscriber("t/x", handler)
        for i in range(5):
            a.put("t/x", bytes([i]))
        got = []
        while (s := sub.try_recv()) is not None:
            got.append(s.payload.to_bytes()[0])
        assert got == ([3, 4] if isinstance(handler, RingChannel) else [4])
        sub.undeclare()


def test_a_service_on_the_fake_stack_is_fed_queried_and_read(fake_stack):
    from smana.common import keys
    from smana.common.messages import Pose
    from tests.support import echo_service

    fake_stack.start("echo", echo_service.cli, "--robot", fake_stack.robot)
    fake_stack.wait_alive("echo")
    for i in range(3):
        fake_stack.publish(keys.key("test", "echo", "pose"), Pose.from_xyz_yaw(i, 0, 0, 0))
    fake_stack.publish(keys.key("test", "echo", "pose"), b"garbage")
    assert fake_stack.drained("echo")
    assert fake_stack.query("echo", "count") == {"poses": 3, "clouds": 0, "points": 0}
    books = fake_stack.books("echo")
    assert books.accepted >= 3 and books.rejected == {"malformed": 1}
    st = fake_stack.status("echo")
    assert st.state == "running" and st.books_add_up()
