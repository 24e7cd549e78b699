"""The service lifecycle every smana process shares.

A service subclasses `Service`, declares its inputs and outputs in `setup()` and does its periodic
work in `tick()`. The base class does the rest:

- opens the zenoh session (`with zenoh.open(conf) as session`) and declares the liveliness token
  `smana/<robot>/alive/<service>`;
- publishes a `ServiceStatus` every `general.status_period_s` on `smana/<robot>/<service>/status`
  and answers queries on the same key (uptime, messages in/out, errors by kind, queue drops);
- runs every handler on ONE thread, the service's main loop, so service code needs no locks. Zenoh
  callbacks only copy the payload into a queue and return (never block inside a zenoh callback):
    * `subscribe(key, handler)`: FIFO, for light messages (poses, patches, commands);
    * `subscribe_latest(key, handler)`: latest wins, for heavy inputs (point clouds). A scan that
      arrives while the previous one is still waiting is dropped and counted in `queue_drops`;
    * `queryable(key, handler)`: the query waits in the FIFO and is answered from the main loop;
- decodes and validates payloads; a bad one is counted by its `MessageError.kind`, logged (rate
  limited) and dropped: a service never dies of bad input, and its state stays as it was;
- stops on SIGINT/SIGTERM: stops the loop, calls `on_stop()` (flush state), undeclares everything,
  closes the session. It exits well within 5 s unless `on_stop` itself takes longer. A stop that
  hangs outside `on_stop` (leaving the loop, or closing zenoh) for `STOP_DEADLINE_S` dumps every
  thread's stack to the log and exits with status 3: with its supervisor gone (killed -9), nobody
  else would end it.

A complete minimal example is `tests/support/echo_service.py`.

Query replies use the query's encoding: JSON when the query carries a JSON payload or the selector
has `?format=json`, msgpack otherwise. So `z_get -s 'smana/r1/mapper/stats?format=json'` works from
any zenoh tool.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack

from smana.common import keys
from smana.common.config import SmanaConfig
from smana.common.messages import (
    Message,
    MessageError,
    ServiceStatus,
    decode,
    encode,
    from_json,
    json_default,
    to_json,
)
from smana.common.zenoh_config import open_session

try:  # Linux: a child can ask to be signalled when its parent dies, even by SIGKILL
    import ctypes

    _LIBC = ctypes.CDLL(None, use_errno=True)
    _PR_SET_PDEATHSIG = 1
except OSError:  # pragma: no cover - not Linux
    _LIBC = None


def on_stop_signals(callback: Callable[[int], Any], signals=(signal.SIGINT, signal.SIGTERM)):
    """Call `callback(signum)` on a helper thread whenever one of `signals` arrives.

    A Python signal handler runs on the main thread between two bytecodes, possibly while that
    thread holds a lock (inside `Event.wait`, say). A handler that takes the same lock (`Event.set`
    does) deadlocks the process for good: a planner once ignored SIGTERM that way. So the handler
    only writes the signal's number to a pipe; a daemon thread reads it and does the work."""
    r, w = os.pipe()
    os.set_blocking(w, False)

    def handler(signum, _frame) -> None:
        try:
            os.write(w, bytes([signum]))
        except OSError:  # the pipe is full: stops are already on their way
            pass

    def watch() -> None:
        while data := os.read(r, 64):
            for signum in data:
                callback(signum)

    threading.Thread(target=watch, name="stop-signals", daemon=True).start()
    for sig in signals:
        signal.signal(sig, handler)


def die_with_parent() -> None:
    """For child processes (a `preexec_fn`, a pool's initializer): SIGTERM them when the process
    that started them dies, so a parent killed with -9 leaves nothing behind. Async-signal-safe:
    one system call."""
    if _LIBC is not None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


STOP_DEADLINE_S = 5.0  # after a stop signal: to leave the loop, and to close zenoh after on_stop
FIFO_LIMIT = 10_000  # light messages waiting for the main loop before new ones are dropped


@dataclass
class Request:
    """A query as a handler sees it: its parameters, its payload (if any) and its encoding."""

    key: str
    params: dict[str, str]
    payload: bytes | None
    json: bool  # the query asked in JSON, so the reply goes in JSON

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


class ReplyError(Exception):
    """Raise from a query handler to answer with an error reply: `kind` and a message."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


class _Latest:
    """A one-slot mailbox: put() replaces what was there (and says so), take() empties it."""

    def __init__(self):
        self._item = None
        self._lock = threading.Lock()

    def put(self, item) -> bool:
        with self._lock:
            replaced = self._item is not None
            self._item = item
            return replaced

    def take(self):
        with self._lock:
            item, self._item = self._item, None
            return item


class Publisher:
    """A declared zenoh publisher that encodes messages and counts what it sends."""

    def __init__(self, service: Service, zpub, key: str):
        self._service, self._zpub, self.key = service, zpub, key

    def put(self, msg: Message | dict | bytes) -> None:
        if isinstance(msg, Message):
            payload = encode(msg)
        elif isinstance(msg, dict):
            payload = msgpack.packb(msg, use_bin_type=True)
        else:
            payload = msg
        self._zpub.put(payload)
        self._service.msgs_out += 1

    def undeclare(self):
        self._zpub.undeclare()


class Service:
    """Base of every smana service. Subclasses set `name` and override `setup`, `tick`, `on_stop`
    and `status_details` as they need."""

    name = "service"
    tick_period_s = 0.1  # how often tick() runs

    def __init__(self, config: SmanaConfig):
        self.config = config
        self.robot = config.general.robot
        self.log = logging.getLogger(f"smana.{self.name}")
        self.session = None
        self.msgs_in = 0
        self.msgs_out = 0
        self.errors: collections.Counter[str] = collections.Counter()
        self.queue_drops = 0
        self.state = "starting"
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._signalled = False  # a stop signal came: the stop watchdog is armed
        self._watchdog: threading.Timer | None = None
        self._wake = threading.Event()
        self._fifo: collections.deque = collections.deque()
        self._latest: list[tuple[_Latest, Callable]] = []
        self._declared: list[Any] = []
        self._status_seq = 0

    # -- what subclasses override ----------------------------------------------------------------

    def setup(self) -> None:
        """Declare subscriptions, queryables and publishers (self.session is open)."""

    def tick(self) -> None:
        """Periodic work, every `tick_period_s` on the main loop."""

    def on_stop(self) -> None:
        """Flush state before the session closes (save the map, ...)."""

    def status_details(self) -> dict:
        """Service-specific figures for the status message (plain values only)."""
        return {}

    # -- declarations ------------------------------------------------------------------------------

    def subscribe(self, key: str, handler: Callable, expect: type[Message] | None = None) -> None:
        """Light input: every sample is queued (FIFO) and handled in order on the main loop.
        With `expect`, the handler gets a decoded message; without, the raw bytes."""

        def on_sample(sample, _h=handler, _e=expect):
            self._push(("sample", _h, _e, sample.payload.to_bytes(), False))

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def subscribe_latest(
        self,
        key: str,
        handler: Callable,
        expect: type[Message] | None = None,
        drop_nonfinite: bool = False,
    ) -> None:
        """Heavy input: only the newest unhandled sample is kept; older ones are dropped and counted
        in `queue_drops` (a slow mapper skips stale scans instead of falling behind)."""
        slot = _Latest()
        self._latest.append((slot, lambda payload: self._handle_payload(
            handler, expect, payload, drop_nonfinite)))  # fmt: skip

        def on_sample(sample, _slot=slot):
            if _slot.put(sample.payload.to_bytes()):
                self.queue_drops += 1
            self._wake.set()

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def queryable(self, key: str, handler: Callable[[Request], Any]) -> None:
        """Answer queries on `key`. The handler gets a `Request` and returns a Message, a dict (sent
        as a map) or bytes; raising `ReplyError` or `MessageError` sends an error reply."""

        def on_query(query, _h=handler):
            self._push(("query", _h, None, query, False))

        self._declared.append(self.session.declare_queryable(key, on_query))

    def publisher(self, key: str, reliable_block: bool = False, express: bool = False) -> Publisher:
        """Declare a publisher. `reliable_block=True` makes zenoh block instead of dropping when the
        link is congested: for data that must not be lost (map deltas, graph patches). Sensor
        streams keep the default DROP, so a slow link loses stale scans, not the process."""
        import zenoh

        cc = zenoh.CongestionControl.BLOCK if reliable_block else zenoh.CongestionControl.DROP
        zpub = self.session.declare_publisher(key, congestion_control=cc, express=express)
        self._declared.append(zpub)
        return Publisher(self, zpub, key)

    # -- errors ----------------------------------------------------------------------------------

    def count_error(self, kind: str, message: str) -> None:
        """Count an error by kind and log it: the first few of a kind, then one in a hundred."""
        self.errors[kind] += 1
        n = self.errors[kind]
        if n <= 5 or n % 100 == 0:
            self.log.warning("%s (%s #%d)", message, kind, n)

    # -- the loop ----------------------------------------------------------------------------------

    def run(self) -> int:
        """Open the session, run until SIGINT/SIGTERM (or `stop()`), then shut down cleanly."""
        self._install_signal_handlers()
        with open_session(self.config.zenoh) as session:
            self.session = session
            try:
                self.setup()
                self._status_pub = self.publisher(keys.status(self.robot, self.name))
                self.queryable(keys.status(self.robot, self.name), lambda req: self.status())
                token = session.liveliness().declare_token(keys.alive(self.robot, self.name))
                self._declared.append(token)
                self.state = "running"
                self.log.info("%s up (robot %s, pid %d)", self.name, self.robot, os.getpid())
                self._loop()
            finally:
                self.state = "stopping"
                self._disarm()  # on_stop may take its time (a large map to save)
                try:
                    self.on_stop()
                except Exception:
                    self.log.exception("on_stop failed")
                if self._signalled:
                    self._arm("undeclaring and closing the zenoh session")
                for d in reversed(self._declared):
                    try:
                        d.undeclare()
                    except Exception:  # already gone with a closing session: nothing to do
                        pass
                self._declared.clear()
                self.session = None
        self._disarm()
        self.log.info("%s stopped", self.name)
        return 0

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # in-process tests run services in threads and call stop()
        on_stop_signals(lambda _sig: self._on_signal())

    def _on_signal(self) -> None:
        if not self._signalled:
            self._signalled = True
            self._arm("leaving the main loop")
        self.stop()

    def _arm(self, phase: str) -> None:
        """Exit hard if `phase` of a signalled stop takes longer than STOP_DEADLINE_S."""
        self._disarm()
        self._watchdog = threading.Timer(STOP_DEADLINE_S, self._hung, (phase,))
        self._watchdog.daemon = True
        self._watchdog.start()

    def _disarm(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
            self._watchdog = None

    def _hung(self, phase: str) -> None:
        import faulthandler
        import sys

        self.log.error("stopping hung %.0f s %s: exiting (stacks follow)", STOP_DEADLINE_S, phase)
        for h in logging.getLogger().handlers:
            h.flush()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        os._exit(3)

    def _push(self, item) -> None:
        if len(self._fifo) >= FIFO_LIMIT:
            self.queue_drops += 1
            return
        self._fifo.append(item)
        self._wake.set()

    def _loop(self) -> None:
        next_tick = next_status = time.monotonic()
        period = self.config.general.status_period_s
        while not self._stop.is_set():
            now = time.monotonic()
            timeout = max(0.0, min(next_tick, next_status) - now)
            if not self._fifo:
                self._wake.wait(timeout)
            self._wake.clear()
            # Light messages first, all of them; then at most one heavy item per input, so that
            # queries and poses are never stuck behind a backlog of scans.
            while self._fifo and not self._stop.is_set():
                self._dispatch(self._fifo.popleft())
            for slot, handle in self._latest:
                payload = slot.take()
                if payload is not None:
                    handle(payload)
                    while self._fifo and not self._stop.is_set():
                        self._dispatch(self._fifo.popleft())
            now = time.monotonic()
            if now >= next_tick:
                next_tick = now + self.tick_period_s
                self._guard(self.tick)
            if now >= next_status:
                next_status = now + period
                self._guard(lambda: self._status_pub.put(self.status()))

    def _dispatch(self, item) -> None:
        what, handler, expect, data, _ = item
        if what == "sample":
            self._handle_payload(handler, expect, data, False)
        else:
            # Even a reply that cannot be sent (the querier left) must not stop the loop.
            self._guard(lambda: self._answer(handler, data))

    def _handle_payload(self, handler, expect, payload: bytes, drop_nonfinite: bool) -> None:
        self.msgs_in += 1
        if expect is None:
            self._guard(lambda: handler(payload))
            return
        try:
            msg = decode(payload, expect, drop_nonfinite=drop_nonfinite)
        except MessageError as exc:
            self.count_error(exc.kind, f"rejected {expect.TYPE}: {exc}")
            return
        self._guard(lambda: handler(msg))

    def _guard(self, fn) -> None:
        """Run service code; bad input is counted, a bug is logged with its traceback, and the
        service keeps running either way."""
        try:
            fn()
        except MessageError as exc:
            self.count_error(exc.kind, str(exc))
        except ValueError as exc:
            self.count_error("value", f"{type(exc).__name__}: {exc}")
        except Exception as exc:
            self.count_error("internal", f"{type(exc).__name__}: {exc}")
            self.log.debug("%s", traceback.format_exc())
            if self.errors["internal"] <= 5:
                self.log.error("%s", traceback.format_exc())

    def _answer(self, handler, query) -> None:
        self.msgs_in += 1
        payload = query.payload.to_bytes() if query.payload is not None else None
        params = dict(query.parameters) if query.parameters else {}
        enc = str(query.encoding) if query.encoding is not None else ""
        as_json = enc.startswith(("application/json", "text/")) or params.get("format") == "json"
        req = Request(str(query.key_expr), params, payload, as_json)
        try:
            result = handler(req)
            query.reply(query.key_expr, _reply_bytes(result, as_json), encoding=_encoding(as_json))
            self.msgs_out += 1
        except (ReplyError, MessageError) as exc:
            self.count_error(exc.kind, f"query {req.key}: {exc}")
            body = {"ok": False, "error": exc.kind, "message": str(exc)}
            query.reply_err(_reply_bytes(body, as_json), encoding=_encoding(as_json))
        except Exception as exc:
            self.count_error("internal", f"query {req.key}: {type(exc).__name__}: {exc}")
            self.log.error("%s", traceback.format_exc())
            body = {"ok": False, "error": "internal", "message": f"{type(exc).__name__}: {exc}"}
            query.reply_err(_reply_bytes(body, as_json), encoding=_encoding(as_json))

    def status(self) -> ServiceStatus:
        self._status_seq += 1
        return ServiceStatus(
            stamp_s=time.time(),
            seq=self._status_seq,
            robot=self.robot,
            service=self.name,
            pid=os.getpid(),
            uptime_s=time.monotonic() - self._t0,
            state=self.state,
            msgs_in=self.msgs_in,
            msgs_out=self.msgs_out,
            errors=dict(self.errors),
            queue_drops=self.queue_drops,
            details=self.status_details(),
        )


def _encoding(as_json: bool):
    import zenoh

    return zenoh.Encoding.APPLICATION_JSON if as_json else zenoh.Encoding("application/msgpack")


def _reply_bytes(result, as_json: bool) -> bytes:
    if isinstance(result, bytes):
        return result
    if isinstance(result, Message):
        return to_json(result) if as_json else encode(result)
    if as_json:
        return json.dumps(result, default=json_default).encode()
    return msgpack.packb(result, use_bin_type=True, default=json_default)


def run_service(cls: type[Service], config: SmanaConfig) -> int:
    """What every service's `main(config)` calls."""
    return cls(config).run()
