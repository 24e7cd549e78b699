"""Queries and their replies, as a `smana.common.service.Service` answers them.

A query waits in the service's FIFO and is answered from the main loop. The reply uses the
query's encoding: JSON when the query carries a JSON (or text) payload or the selector has
`?format=json`, msgpack otherwise. A handler refuses with `Reject` (or `ReplyError`), which
becomes an error reply `{"ok": false, "error": kind, "message": ...}`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import msgpack

from smana.common.messages import (
    Message,
    MessageError,
    decode,
    encode,
    from_json,
    json_default,
    to_json,
)


@dataclass
class Request:
    """A query as a handler sees it: its parameters, its payload (if any) and its encoding."""

    key: str
    params: dict[str, str]
    payload: bytes | None
    json: bool  # the query asked in JSON, so the reply goes in JSON
    attachment: bytes | None = None  # e.g. rmw_zenoh's (sequence number, timestamp, gid)

    def decode(self, expect: type[Message]) -> Message:
        """The payload as a message of type `expect` (MessageError if it is not one)."""
        if not self.payload:
            raise MessageError("missing_field", f"{expect.TYPE} query needs a payload")
        return from_json(self.payload, expect) if self.json else decode(self.payload, expect)

    def body(self) -> dict:
        """The payload as a plain map (empty when there is none): for queries without a schema."""
        if not self.payload:
            return {}
        try:
            data = json.loads(self.payload) if self.json else msgpack.unpackb(self.payload)
        except Exception as exc:
            raise MessageError("malformed", f"query payload is not a map: {exc}") from None
        if not isinstance(data, dict):
            raise MessageError("malformed", "query payload is not a map")
        return data


@dataclass
class Reply:
    """A query handler's answer given as it goes on the wire: bytes, and an attachment (a ROS 2
    service reply carries the request's sequence number and client gid, `services/ros2`)."""

    payload: bytes
    attachment: bytes | None = None


class Reject(Exception):
    """Raise from a handler to refuse the message it was given: counted in `rejected[kind]`,
    logged, and the service's state stays as it was. From a query handler it becomes an error
    reply `{"ok": false, "error": kind, "message": ...}`, or `reply` (a Message or map) sent as an
    ordinary reply where the query's schema has its own error form (a PathReply with ok false)."""

    def __init__(self, kind: str, message: str, reply=None):
        super().__init__(message)
        self.kind = kind
        self.reply = reply


class ReplyError(Reject):
    """A query handler's refusal (the name query handlers have always used)."""


def end_query(query) -> None:
    """Send a query's final reply now (zenoh's `Query.drop`), not when its object is collected."""
    try:
        query.drop()
    except Exception:  # noqa: BLE001 - already ended, or a stand-in without drop()
        pass


class Answers:
    """The part of `Service` that answers a query on the main loop and settles it in the books
    (`Inbox`): a handler's result, its `Reject`, or a bug, each as one reply."""

    def _answer(self, handler, query, key: str) -> None:
        """Answer a query on the main loop, then end it: the querier's get() returns at once.
        Zenoh ends a query when its object is dropped; a handler that raised from inside an
        `except` block leaves a frame cycle that holds the query until the garbage collector runs
        (seconds: a refused explorer goal took 5 to 10 s), so it is dropped here explicitly."""
        try:
            self._answer_once(handler, query, key)
        finally:
            end_query(query)

    def _answer_once(self, handler, query, key: str) -> None:
        """Answer a query. Replies go out on the queryable's own key, which a wider query
        (`smana/r1/**`) matches and an access-control policy allows."""
        as_json = False
        try:
            params, as_json = query_form(query)
            size = len(query.payload) if query.payload is not None else 0
            if size > self.max_payload_bytes:  # refused before the payload is copied
                raise MessageError("oversize", f"{size} bytes > {self.max_payload_bytes}")
            payload = query.payload.to_bytes() if query.payload is not None else None
            att = query.attachment.to_bytes() if query.attachment is not None else None
            req = Request(str(query.key_expr), params, payload, as_json, att)
        except MessageError as exc:
            self._rejected(exc.kind, f"query: {exc}")
            self._reply_err(query, exc.kind, str(exc), as_json)
            return
        except Exception as exc:  # noqa: BLE001 - a query zenoh hands us that we cannot read
            self._internal(exc, "reading a query")
            return
        try:
            result = handler(req)
            if isinstance(result, Reply):
                self.books.settle("accepted")
                self._send_reply(query, key, result.payload, None, result.attachment)
                return
            body = reply_bytes(result, as_json)
        except (Reject, MessageError) as exc:
            self._rejected(exc.kind, f"query {req.key}: {exc}")
            if getattr(exc, "reply", None) is not None:
                self._send_reply(query, key, reply_bytes(exc.reply, as_json), as_json)
            else:
                self._reply_err(query, exc.kind, str(exc), as_json)
            return
        except Exception as exc:  # noqa: BLE001
            self._internal(exc, f"query {req.key}")
            self._reply_err(query, "internal", f"{type(exc).__name__}: {exc}", as_json)
            return
        self.books.settle("accepted")
        self._send_reply(query, key, body, as_json)

    def _send_reply(self, query, key: str, body: bytes, as_json, attachment=None) -> None:
        """`as_json` None: bytes as they are, with zenoh's default encoding."""
        try:
            if as_json is None:
                query.reply(key, body, attachment=attachment)
            else:
                query.reply(key, body, encoding=reply_encoding(as_json))
            with self._counter_lock:  # plan workers reply beside the main loop
                self.msgs_out += 1
        except Exception as exc:  # the querier left: the query was still handled
            self.note("reply_failed", f"query {key}: reply not sent: {exc}")

    def _reply_err(self, query, kind: str, message: str, as_json: bool) -> None:
        body = {"ok": False, "error": kind, "message": message}
        try:
            query.reply_err(reply_bytes(body, as_json), encoding=reply_encoding(as_json))
        except Exception as exc:
            self.note("reply_failed", f"error reply not sent: {exc}")


def query_form(query) -> tuple[dict[str, str], bool]:
    """A query's selector parameters, and whether it asked in JSON (a JSON or text payload, or
    `?format=json`)."""
    params = dict(query.parameters) if query.parameters else {}
    enc = str(query.encoding) if query.encoding is not None else ""
    return params, enc.startswith(("application/json", "text/")) or params.get("format") == "json"


def reply_encoding(as_json: bool):
    """The zenoh encoding of a reply in JSON or msgpack."""
    import zenoh

    return zenoh.Encoding.APPLICATION_JSON if as_json else zenoh.Encoding("application/msgpack")


def reply_bytes(result, as_json: bool) -> bytes:
    """A handler's result (bytes, a Message or a plain map) as the reply's payload."""
    if isinstance(result, bytes):
        return result
    if isinstance(result, Message):
        return to_json(result) if as_json else encode(result)
    if as_json:
        return json.dumps(result, default=json_default).encode()
    return msgpack.packb(result, use_bin_type=True, default=json_default)
