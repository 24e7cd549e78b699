"""A service's inputs and outputs and the books that count them (`smana.common.service.Service`'s
inbox, latest-wins slots and publishers; "books" are counters).

Zenoh callbacks only copy a sample into a queue and return; the main loop takes it off, hands it
to its handler and settles its fate in the books: every sample and query received ends in exactly
one counter (`accepted`, `dropped` by reason, `rejected` by kind) or is still `pending`. Events
that are not a message's fate are counted with `note`.
"""

from __future__ import annotations

import collections
import threading
import traceback
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import msgpack

from smana.common.messages import Message, MessageError, decode, encode, json_default
from smana.common.service_queries import Reject, Request

if TYPE_CHECKING:
    from smana.common.service import Service

FIFO_LIMIT = 10_000  # light messages waiting for the main loop before new ones are dropped


class Books:
    """Where every message a service received went. Zenoh callbacks (their own threads) and the
    main loop both write, so every change is made under one lock; `snapshot()` adds up:
    received == accepted + sum(dropped) + sum(rejected) + pending."""

    def __init__(self):
        self.lock = threading.Lock()
        self.received = 0
        self.accepted = 0
        self.in_flight = 0  # taken off a queue by the main loop, its fate not yet known
        self.dropped: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()

    def settle(self, outcome: str, kind: str = "") -> None:
        """The fate of a message taken with `Service._take` (in flight): `accepted`,
        `dropped` (kind = reason) or `rejected` (kind)."""
        with self.lock:
            self.in_flight -= 1
            if outcome == "accepted":
                self.accepted += 1
            elif outcome == "dropped":
                self.dropped[kind] += 1
            else:
                self.rejected[kind] += 1


class LatestSlot:
    """A one-slot mailbox: put() replaces what was there (and says so), take() empties it and
    says how many items were replaced since the last take."""

    def __init__(self):
        self.item = None
        self.replaced = 0

    def put(self, item) -> bool:
        replaced = self.item is not None
        self.replaced += replaced
        self.item = item
        return replaced

    def take(self):
        item, self.item = self.item, None
        n, self.replaced = self.replaced, 0
        return item, n


class Publisher:
    """A declared zenoh publisher that encodes messages and counts what it sends."""

    def __init__(self, service: Service, zpub, key: str):
        self._service, self._zpub, self.key = service, zpub, key

    def put(self, msg: Message | dict | bytes) -> None:
        if isinstance(msg, Message):
            payload = encode(msg)
        elif isinstance(msg, dict):
            payload = msgpack.packb(msg, use_bin_type=True, default=json_default)
        else:
            payload = msg
        self._zpub.put(payload)
        with self._service._counter_lock:  # action workers publish beside the main loop
            self._service.msgs_out += 1

    def undeclare(self):
        self._zpub.undeclare()


class Inbox:
    """The part of `Service` that declares inputs and outputs, queues what arrives, hands it to
    its handler on the main loop and keeps the books. It uses the state `Service.__init__` sets
    (`books`, `events`, `_fifo`, `_latest`, `_wake`, `_stop`, `session`, `log`, ...)."""

    # -- declarations ------------------------------------------------------------------------------

    def _received(self, sample) -> bytes | None:
        """Count a sample in; None (and rejected `oversize`) when it is too large to copy."""
        n = len(sample.payload)
        if n > self.max_payload_bytes:
            with self.books.lock:
                self.books.received += 1
                self.books.rejected["oversize"] += 1
            self._log_kind("oversize", f"{sample.key_expr}: {n} bytes > {self.max_payload_bytes}")
            return None
        return sample.payload.to_bytes()

    def subscribe(self, key: str, handler: Callable, expect: type[Message] | None = None) -> None:
        """Light input: every sample is queued (FIFO) and handled in order on the main loop.
        With `expect`, the handler gets a decoded message; without, the raw bytes."""

        def on_sample(sample, _h=handler, _e=expect):
            payload = self._received(sample)
            if payload is not None:
                self._push(("sample", _h, _e, payload))

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def subscribe_latest(
        self,
        key: str,
        handler: Callable,
        expect: type[Message] | None = None,
        drop_nonfinite: bool = False,
    ) -> None:
        """Heavy input: only the newest unhandled sample is kept; older ones are dropped as
        `stale` (a slow mapper skips old scans instead of falling behind)."""
        slot = LatestSlot()
        self._latest.append(
            (slot, lambda payload: self._handle_payload(handler, expect, payload, drop_nonfinite))
        )

        def on_sample(sample, _slot=slot):
            payload = self._received(sample)
            if payload is None:
                return
            with self.books.lock:
                self.books.received += 1
                if _slot.put(payload):
                    self.books.dropped["stale"] += 1
            self._wake.set()

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def queryable(
        self, key: str, handler: Callable[[Request], Any], complete: bool = False
    ) -> None:
        """Answer queries on `key`. The handler gets a `Request` and returns a Message, a dict (sent
        as a map), bytes or a `Reply`; raising `Reject`/`ReplyError` or `MessageError` sends an
        error reply. `complete`: this queryable answers for all of `key` (queries that target
        complete queryables only, as ROS 2 service clients do, reach it)."""

        def on_query(query, _h=handler, _k=key):
            self._push(("query", _h, _k, query))

        kw = {"complete": True} if complete else {}
        self._declared.append(self.session.declare_queryable(key, on_query, **kw))

    def publisher(self, key: str, reliable_block: bool = False, express: bool = False) -> Publisher:
        """Declare a publisher. `reliable_block=True` makes zenoh block instead of dropping when the
        link is congested: for data that must not be lost (map deltas, graph patches). Sensor
        streams keep the default DROP, so a slow link loses stale scans, not the process."""
        import zenoh

        cc = zenoh.CongestionControl.BLOCK if reliable_block else zenoh.CongestionControl.DROP
        zpub = self.session.declare_publisher(key, congestion_control=cc, express=express)
        self._declared.append(zpub)
        return Publisher(self, zpub, key)

    # -- counting ----------------------------------------------------------------------------------

    def note(self, kind: str, message: str, n: int = 1) -> None:
        """Count an event that is not a message's fate (points dropped inside an accepted cloud,
        a gap in a sequence, a timeout) and log it: the first few of a kind, then one in 100."""
        with self._counter_lock:
            self.events[kind] += n
            count = self.events[kind]
        self._log_kind(kind, message, count)

    def _log_kind(self, kind: str, message: str, n: int | None = None) -> None:
        if n is None:
            n = self.books.rejected[kind] + self.events[kind]
        if n <= 5 or n % 100 == 0:
            self.log.warning("%s (%s #%d)", message, kind, n)

    def _rejected(self, kind: str, message: str) -> None:
        """Settle the message in flight as rejected, and log it."""
        self.books.settle("rejected", kind)
        self._log_kind(kind, message, self.books.rejected[kind])

    def _internal(self, exc: BaseException, where: str) -> None:
        """A bug met while handling one message: rejected `internal`; the first traceback of each
        (exception type, place) is logged whole, later ones as one line."""
        self.books.settle("rejected", "internal")
        tb = traceback.extract_tb(exc.__traceback__)
        place = f"{tb[-1].filename}:{tb[-1].lineno}" if tb else "?"
        sig = f"{type(exc).__name__}@{place}"
        if sig not in self._tracebacks_logged and len(self._tracebacks_logged) < 100:
            self._tracebacks_logged.add(sig)
            self.log.error(
                "%s: %s, message dropped, service goes on:\n%s",
                where,
                type(exc).__name__,
                traceback.format_exc(),
            )
        else:
            n = self.books.rejected["internal"]
            self._log_kind("internal", f"{where}: {type(exc).__name__}: {exc}", n)

    def _push(self, item) -> None:
        with self.books.lock:
            self.books.received += 1
            if len(self._fifo) >= FIFO_LIMIT:
                self.books.dropped["queue_full"] += 1
                return
            self._fifo.append(item)
        self._wake.set()

    def _take(self):
        """The next queued light item, now in flight (None when the queue is empty)."""
        with self.books.lock:
            if not self._fifo:
                return None
            self.books.in_flight += 1
            return self._fifo.popleft()

    def _take_latest(self, slot: LatestSlot):
        with self.books.lock:
            payload, self.stale_before = slot.take()
            if payload is not None:
                self.books.in_flight += 1
            return payload

    def _pending_locked(self) -> int:
        slots = sum(1 for slot, _ in self._latest if slot.item is not None)
        return len(self._fifo) + slots + self.books.in_flight

    def _drain_fifo(self) -> None:
        while not self._stop.is_set() and (item := self._take()) is not None:
            self._dispatch(item)

    def _settle_leftovers(self, drain: bool) -> None:
        """At stop: handle what is queued (`drain`) or count it dropped as `stopping`."""
        if drain:
            while (item := self._take()) is not None:
                self._dispatch(item)
            for slot, handle in self._latest:
                if (payload := self._take_latest(slot)) is not None:
                    handle(payload)
        with self.books.lock:
            left = len(self._fifo) + sum(1 for slot, _ in self._latest if slot.item is not None)
            self._fifo.clear()
            for slot, _ in self._latest:
                slot.take()
            if left:
                self.books.dropped["stopping"] += left

    def _dispatch(self, item) -> None:
        what, handler, expect_or_key, data = item
        if what == "sample":
            self._handle_payload(handler, expect_or_key, data, False)
        else:
            self._answer(handler, data, expect_or_key)

    def _handle_payload(self, handler, expect, payload: bytes, drop_nonfinite: bool) -> None:
        """Decode, hand over, settle: whatever happens, the message ends in one counter and the
        loop goes on."""
        try:
            msg = (
                payload
                if expect is None
                else decode(
                    payload, expect, drop_nonfinite=drop_nonfinite, max_bytes=self.max_payload_bytes
                )
            )
        except MessageError as exc:
            self._rejected(exc.kind, f"rejected {expect.TYPE}: {exc}")
            return
        except Exception as exc:  # noqa: BLE001 - the decoder's own bug: still one message
            self._internal(exc, f"decoding {getattr(expect, 'TYPE', 'bytes')}")
            return
        try:
            outcome = handler(msg)
        except (Reject, MessageError) as exc:
            what = getattr(expect, "TYPE", "message")
            self._rejected(exc.kind, f"rejected {what}: {exc}")
        except ValueError as exc:
            self._rejected("value", f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - a bug: counted, logged, the service goes on
            self._internal(exc, f"handling {getattr(expect, 'TYPE', 'a sample')}")
        else:
            # A handler may say a message was dropped for a reason of its own (already covered
            # by a snapshot, say) by returning ("dropped", reason); anything else is accepted.
            if isinstance(outcome, tuple) and outcome and outcome[0] == "dropped":
                self.books.settle("dropped", outcome[1])
            else:
                self.books.settle("accepted")

    def _guard(self, fn, where: str) -> None:
        """Run periodic service code; a failure is logged and the service keeps running."""
        try:
            fn()
        except Exception as exc:  # noqa: BLE001
            self.note("internal_" + where, f"{where}: {type(exc).__name__}: {exc}")
            sig = f"{where}:{type(exc).__name__}"
            if sig not in self._tracebacks_logged:
                self._tracebacks_logged.add(sig)
                self.log.error("%s", traceback.format_exc())
