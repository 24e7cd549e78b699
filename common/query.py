"""Asking a service over zenoh: `request()` sends a query and returns the decoded reply, or raises
`QueryError` with a clear reason (nobody answered, the service replied an error, the reply was bad).
Used by the CLIs (`smana status`, `smana plan`) and by services that query others (explorer ->
planner)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import msgpack

from smana.common.messages import (
    REGISTRY,
    Message,
    MessageError,
    decode,
    encode,
    from_json,
    to_json,
)


class QueryError(RuntimeError):
    """A query that got no usable answer. `kind`: no_reply, error reply kind, or malformed."""

    def __init__(self, kind: str, message: str, body: dict | None = None):
        super().__init__(message)
        self.kind = kind
        self.body = body or {}


def request(
    session,
    key: str,
    body: Message | dict | None = None,
    timeout_s: float = 5.0,
    as_json: bool = False,
    while_waiting: Callable[[], None] | None = None,
):
    """Query `key` once and return the first reply: a Message when the reply is a typed message,
    else the decoded map. `while_waiting`, when given, is called every few tens of milliseconds
    until the query is over, on the caller's thread (the explorer keeps its goal feedback going
    while the planner thinks)."""
    import zenoh

    kw = {}
    if body is not None:
        if isinstance(body, Message):
            kw["payload"] = to_json(body) if as_json else encode(body)
        elif as_json:
            kw["payload"] = json.dumps(body).encode()
        else:
            kw["payload"] = msgpack.packb(body, use_bin_type=True)
        kw["encoding"] = (
            zenoh.Encoding.APPLICATION_JSON if as_json else zenoh.Encoding("application/msgpack")
        )
    handler = session.get(key, timeout=timeout_s, **kw)
    replies = list(handler) if while_waiting is None else _gather(handler, while_waiting)
    if not replies:
        raise QueryError("no_reply", f"no service answered {key} (is it running?)")
    r = replies[0]
    if r.ok is None:
        data = parse_reply(r.err.payload.to_bytes())
        kind = data.get("error", "error") if isinstance(data, dict) else "error"
        msg = data.get("message", str(data)) if isinstance(data, dict) else str(data)
        raise QueryError(kind, f"{key}: {msg}", data if isinstance(data, dict) else None)
    return parse_reply(r.ok.payload.to_bytes())


def _gather(handler, while_waiting: Callable[[], None]) -> list:
    """Every reply of a query, calling `while_waiting` between polls until the query is over
    (zenoh closes the channel then)."""
    import zenoh

    replies = []
    while True:
        try:
            r = handler.try_recv()
        except zenoh.ZError:  # empty and closed: the query is over
            return replies
        if r is not None:
            replies.append(r)
            continue
        while_waiting()
        time.sleep(0.02)


def parse_reply(payload: bytes):
    """A reply in either encoding: a typed message when it carries `_type`, else a plain map.
    JSON starts with `{` or `[`, which no msgpack map does (0x7b is a msgpack integer)."""
    is_json = payload[:1] in (b"{", b"[")
    try:
        data = json.loads(payload) if is_json else msgpack.unpackb(payload, strict_map_key=False)
    except Exception as exc:
        raise QueryError("malformed", f"reply is neither msgpack nor JSON: {exc}") from None
    if isinstance(data, dict) and data.get("_type") in REGISTRY:
        try:
            return from_json(payload) if is_json else decode(payload)
        except MessageError as exc:
            raise QueryError("malformed", f"bad reply: {exc}") from None
    return data


def ready(session, robot: str, service: str, timeout_s: float = 1.0) -> bool:
    """Whether `service` of `robot` is live and serves: its alive token is up and its status says
    its kernels are loaded. A service that compiles them in the background is live at once and
    answers `warming_up` until then (`common/service.py`), so a harness that times or fuzzes it
    waits for both, as it did when live meant compiled."""
    from smana.common import keys

    if not list(session.liveliness().get(keys.alive(robot, service), timeout=timeout_s)):
        return False
    try:
        st = request(session, keys.status(robot, service), None, max(timeout_s, 2.0))
    except QueryError:
        return False
    return st.details.get("kernels", "ready") == "ready"
