"""An in-process stand-in for zenoh, so that a service's handlers run in the test's process.

`FakeNetwork` is the router: every `FakeSession` opened on it sees the others' publications,
queryables and liveliness tokens, matched with zenoh's own key-expression semantics
(`zenoh.KeyExpr.intersects`). It offers the part of the zenoh-python 1.x session API that smana
uses: `put` / `delete`, `declare_publisher`, `declare_subscriber` (a callback, a `(callback,
drop)` pair, or a channel: the default FIFO, `zenoh.handlers.FifoChannel` / `RingChannel` or
this module's `FifoChannel(n)` / `RingChannel(n)`), `declare_queryable`, `get` (replies through a
channel that ends when every queryable reached has finished with its query, or at the timeout),
`liveliness()` (tokens, `get`, subscribers with `history`), `zid()`, `info.zid()` and `close()`.
Payloads, encodings, key expressions, parameters and sample kinds are zenoh's own types.

Delivery is synchronous: `put` returns once every matching subscriber's callback has run in the
caller's thread (a service's callback only queues the message for its main loop, as with real
zenoh). So a message put before a query reaches a FIFO-fed service before that query does, and
nothing is ever lost on the way: tests that need loss, congestion, access control or real
transport keep a real router (`tests/conftest.py::ZenohStack`).

`FakeStack` runs smana services on a `FakeNetwork` the way `ZenohStack` runs them as processes:
each one's real `cli(argv)` (argument parsing, config, `main(config)`, the `Service` lifecycle with
its starting token, heartbeat, books and stop) on a thread of its own, with a fake session handed
to it through `smana.common.service.session_factory`. Its API follows `ZenohStack` (`service`,
`wait_alive`, `stop`, `log`, `session`, `publisher`, `subscriber`), so a process test becomes an
in-process one by changing its fixture; `status`, `query` and `books` read a service's state
directly. The model
is dora's `MockNode`: feed a node its inputs, capture its outputs, no middleware.
"""

from __future__ import annotations

import collections
import importlib
import itertools
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

log = logging.getLogger("fake_zenoh")

GET_TIMEOUT_S = 10.0  # zenoh's default query timeout


# -- key expressions ----------------------------------------------------------------------------


_KEYS: dict[str, zenoh.KeyExpr] = {}


def key_expr(key) -> zenoh.KeyExpr:
    """A zenoh.KeyExpr (validated by zenoh, cached: tests match the same few keys again and
    again)."""
    if isinstance(key, zenoh.KeyExpr):
        return key
    k = _KEYS.get(key)
    if k is None:
        k = _KEYS[key] = zenoh.KeyExpr(str(key))
    return k


def _zbytes(payload) -> zenoh.ZBytes:
    if payload is None:
        return zenoh.ZBytes(b"")
    return payload if isinstance(payload, zenoh.ZBytes) else zenoh.ZBytes(payload)


def _encoding(encoding) -> zenoh.Encoding | None:
    if encoding is None or isinstance(encoding, zenoh.Encoding):
        return encoding
    return zenoh.Encoding(str(encoding))


# -- what handlers receive ------------------------------------------------------------------------


class Sample:
    """zenoh.Sample's fields that smana reads."""

    def __init__(self, key, payload, kind=zenoh.SampleKind.PUT, encoding=None, attachment=None):
        self.key_expr = key_expr(key)
        self.payload = _zbytes(payload)
        self.kind = kind
        self.encoding = _encoding(encoding) or zenoh.Encoding.ZENOH_BYTES
        self.attachment = None if attachment is None else _zbytes(attachment)
        self.timestamp = None

    def __repr__(self) -> str:
        return f"Sample({self.key_expr}, {self.kind}, {len(self.payload)} bytes)"


class ReplyError:
    def __init__(self, payload, encoding=None):
        self.payload = _zbytes(payload)
        self.encoding = _encoding(encoding) or zenoh.Encoding.ZENOH_BYTES


class Reply:
    """zenoh.Reply: `ok` (a Sample) or `err` (a ReplyError), the other None."""

    def __init__(self, ok: Sample | None = None, err: ReplyError | None = None, replier=None):
        self.ok, self.err, self.replier_id = ok, err, replier

    @property
    def result(self):
        return self.ok if self.ok is not None else self.err


# -- channels -------------------------------------------------------------------------------------


class FifoChannel:
    """A FIFO of `capacity` items (None: unbounded, the default handler). zenoh's FifoChannel
    blocks the sender when full; here the newest item is dropped instead, as nothing may block a
    synchronous delivery."""

    ring = False

    def __init__(self, capacity: int | None = 256):
        self.capacity = capacity


class RingChannel(FifoChannel):
    """Latest wins: a full channel drops its oldest item."""

    ring = True

    def __init__(self, capacity: int = 1):
        super().__init__(capacity)


class _Channel:
    """The receiving end: `recv` (blocking), `try_recv`, iteration (ends once closed and empty,
    or at `deadline`)."""

    def __init__(self, capacity: int | None = None, ring: bool = False, deadline=None):
        self.items: collections.deque = collections.deque()
        self.capacity, self.ring, self.deadline = capacity, ring, deadline
        self.closed = False
        self.cv = threading.Condition()

    def push(self, item) -> None:
        with self.cv:
            if self.capacity is not None and len(self.items) >= self.capacity:
                if not self.ring:
                    return
                self.items.popleft()
            self.items.append(item)
            self.cv.notify_all()

    def close(self) -> None:
        with self.cv:
            self.closed = True
            self.cv.notify_all()

    def try_recv(self):
        """The next item, None when there is none yet; ZError once empty and closed (as zenoh's:
        a query's channel closes when the query is over)."""
        with self.cv:
            if self.items:
                return self.items.popleft()
            if self.deadline is not None and self.deadline <= time.monotonic():
                self.closed = True
            if self.closed:
                raise zenoh.ZError("fake zenoh: channel is empty and closed")
            return None

    def recv(self):
        with self.cv:
            while not self.items:
                if self.closed:
                    raise zenoh.ZError("fake zenoh: channel closed")
                left = None if self.deadline is None else self.deadline - time.monotonic()
                if left is not None and left <= 0:
                    self.closed = True
                    continue
                self.cv.wait(left)
            return self.items.popleft()

    def __iter__(self):
        return self

    def __next__(self):
        try:
            return self.recv()
        except zenoh.ZError:
            raise StopIteration from None


def _handler(handler) -> tuple[Callable[[Any], None], Callable[[], None], _Channel | None]:
    """(deliver, drop, channel) for what zenoh accepts as a handler."""
    if handler is None:
        handler = FifoChannel(None)  # zenoh's default handler loses nothing either
    if isinstance(handler, zenoh.handlers.RingChannel):
        handler = RingChannel(1)  # zenoh's channels do not say their capacity; smana uses 1
    elif isinstance(handler, zenoh.handlers.FifoChannel | zenoh.handlers.DefaultHandler):
        handler = FifoChannel()
    if isinstance(handler, FifoChannel):
        ch = _Channel(handler.capacity, handler.ring)
        return ch.push, ch.close, ch
    if isinstance(handler, tuple):  # (callback, drop)
        callback, drop = handler
        return callback, drop, None
    if callable(handler):
        return handler, lambda: None, None
    raise TypeError(f"fake zenoh: unsupported handler {handler!r}")


def _call(deliver, item) -> None:
    """Run a user callback; like zenoh, an exception in it is logged, not raised at the sender."""
    try:
        deliver(item)
    except Exception:
        log.exception("fake zenoh: a callback raised")


# -- declared entities ----------------------------------------------------------------------------


class _Entity:
    def __init__(self, session: FakeSession, key, handler=None):
        self.session = session
        self.key_expr = key_expr(key)
        self.deliver, self._drop, self.handler = _handler(handler)
        self.undeclared = False
        with session.network.lock:
            session._entities.append(self)

    def matches(self, key: zenoh.KeyExpr) -> bool:
        return not self.undeclared and self.key_expr.intersects(key)

    def undeclare(self) -> None:
        if self.undeclared:
            return
        self.undeclared = True
        self.session._forget(self)
        self._drop()

    # channel access, for entities declared without a callback
    def try_recv(self):
        return self.handler.try_recv()

    def recv(self):
        return self.handler.recv()

    def __iter__(self):
        return iter(self.handler)

    def __enter__(self):
        return self

    def __exit__(self, *_exc):
        self.undeclare()


class Subscriber(_Entity):
    pass


class LivelinessSubscriber(_Entity):
    pass


class Queryable(_Entity):
    pass


class LivelinessToken:
    def __init__(self, session: FakeSession, key):
        self.session, self.key_expr, self.undeclared = session, key_expr(key), False
        with session.network.lock:
            session._tokens.append(self)
        session.network._liveliness(self.key_expr, zenoh.SampleKind.PUT)

    def undeclare(self) -> None:
        if self.undeclared:
            return
        self.undeclared = True
        with self.session.network.lock:
            if self in self.session._tokens:
                self.session._tokens.remove(self)
        self.session.network._liveliness(self.key_expr, zenoh.SampleKind.DELETE)

    def __enter__(self):
        return self

    def __exit__(self, *_exc):
        self.undeclare()


class _Matching:
    def __init__(self, matching: bool):
        self.matching = matching


class Publisher:
    def __init__(self, session: FakeSession, key, encoding=None, **_qos):
        self.session, self.key_expr = session, key_expr(key)
        self.encoding = _encoding(encoding)
        self.undeclared = False

    def put(self, payload, *, encoding=None, attachment=None, **_qos) -> None:
        if not self.undeclared:
            self.session.put(
                self.key_expr, payload, encoding=encoding or self.encoding, attachment=attachment
            )

    def delete(self, **_qos) -> None:
        if not self.undeclared:
            self.session.delete(self.key_expr)

    @property
    def matching_status(self) -> _Matching:
        return _Matching(self.session.network._has_subscriber(self.key_expr))

    def undeclare(self) -> None:
        self.undeclared = True

    def __enter__(self):
        return self

    def __exit__(self, *_exc):
        self.undeclare()


class _GetState:
    """One `get`: how many queries are still open; the reply handler is dropped (a channel
    closes) when none is."""

    def __init__(self, deliver, drop, n: int):
        self.deliver, self.drop = deliver, drop
        self.open = n
        self.lock = threading.Lock()
        if n == 0:
            self._finish()

    def reply(self, reply: Reply) -> None:
        _call(self.deliver, reply)

    def finalized(self) -> None:
        with self.lock:
            self.open -= 1
            last = self.open == 0
        if last:
            self._finish()

    def _finish(self) -> None:
        self.drop()


class Query:
    """What a queryable's callback receives. Zenoh ends a query when the queryable drops it; the
    fake ends it at its first reply (every smana queryable answers once), at `drop()`, or when
    nothing holds it any more (a callback that neither replies nor keeps it)."""

    def __init__(self, selector: zenoh.Selector, payload, encoding, attachment, state: _GetState):
        self.selector = selector
        self.key_expr = selector.key_expr
        self.parameters = selector.parameters
        self.payload = None if payload is None else _zbytes(payload)
        self.encoding = _encoding(encoding) if (payload is not None or encoding) else None
        self.attachment = None if attachment is None else _zbytes(attachment)
        self._state: _GetState | None = state

    def _check_open(self) -> _GetState:
        if self._state is None:
            raise zenoh.ZError("fake zenoh: this query is finished (already answered or dropped)")
        return self._state

    def reply(self, key, payload, *, encoding=None, attachment=None, **_qos) -> None:
        state = self._check_open()
        k = key_expr(key)
        if not k.intersects(self.key_expr):
            raise zenoh.ZError(f"fake zenoh: reply key {k} does not match query {self.key_expr}")
        state.reply(Reply(ok=Sample(k, payload, encoding=encoding, attachment=attachment)))
        self.drop()

    def reply_err(self, payload, *, encoding=None) -> None:
        state = self._check_open()
        state.reply(Reply(err=ReplyError(payload, encoding)))
        self.drop()

    def reply_del(self, key, **_qos) -> None:
        state = self._check_open()
        state.reply(Reply(ok=Sample(key, b"", kind=zenoh.SampleKind.DELETE)))
        self.drop()

    def drop(self) -> None:
        state, self._state = self._state, None
        if state is not None:
            state.finalized()

    def __del__(self):
        self.drop()

    def __enter__(self):
        return self

    def __exit__(self, *_exc):
        self.drop()


# -- sessions ------------------------------------------------------------------------------------


class _Zid:
    def __init__(self):
        self.hex = uuid.uuid4().hex

    def __str__(self) -> str:
        return self.hex

    __repr__ = __str__


class _Info:
    def __init__(self, session: FakeSession):
        self._session = session

    def zid(self) -> _Zid:
        return self._session._zid

    def routers_zid(self) -> list:
        return []

    def peers_zid(self) -> list:
        return [s._zid for s in self._session.network.sessions if s is not self._session]


class Liveliness:
    def __init__(self, session: FakeSession):
        self._session = session

    def declare_token(self, key) -> LivelinessToken:
        self._session._check_open()
        return LivelinessToken(self._session, key)

    def declare_subscriber(self, key, handler=None, *, history: bool | None = None):
        self._session._check_open()
        sub = LivelinessSubscriber(self._session, key, handler)
        if history:
            for token in self._session.network._tokens(sub.key_expr):
                _call(sub.deliver, Sample(token.key_expr, b""))
        return sub

    def get(self, key, handler=None, *, timeout=None, **_kw):
        k = key_expr(key)
        deliver, drop, channel = _handler(handler)
        for token in self._session.network._tokens(k):
            _call(deliver, Reply(ok=Sample(token.key_expr, b"")))
        drop()
        return channel


class FakeSession:
    """A session on a `FakeNetwork` (see the module's docstring for what it models)."""

    def __init__(self, network: FakeNetwork):
        self.network = network
        self._zid = _Zid()
        self._entities: list[_Entity] = []
        self._tokens: list[LivelinessToken] = []
        self._closed = False
        self.info = _Info(self)

    def zid(self) -> _Zid:
        return self._zid

    def _check_open(self) -> None:
        if self._closed:
            raise zenoh.ZError("fake zenoh: session closed")

    def _forget(self, entity: _Entity) -> None:
        with self.network.lock:
            if entity in self._entities:
                self._entities.remove(entity)

    # -- publishing
    def put(self, key, payload, *, encoding=None, attachment=None, **_qos) -> None:
        if self._closed:
            return  # a closed (or killed) session sends nothing
        self.network._publish(Sample(key, payload, encoding=encoding, attachment=attachment))

    def delete(self, key, **_qos) -> None:
        if not self._closed:
            self.network._publish(Sample(key, b"", kind=zenoh.SampleKind.DELETE))

    def declare_publisher(self, key, **kw) -> Publisher:
        self._check_open()
        return Publisher(self, key, **kw)

    # -- receiving
    def declare_subscriber(self, key, handler=None, **_kw) -> Subscriber:
        self._check_open()
        return Subscriber(self, key, handler)

    def declare_queryable(self, key, handler=None, **_kw) -> Queryable:
        self._check_open()
        return Queryable(self, key, handler)

    def get(
        self,
        selector,
        handler=None,
        *,
        timeout=None,
        payload=None,
        encoding=None,
        attachment=None,
        **_kw,
    ):
        """Ask every matching queryable (this session's too, as zenoh does). With a channel
        (the default) the replies come as they are sent; iteration ends once every queryable
        reached has finished with its query, or `timeout` seconds from now."""
        self._check_open()
        sel = zenoh.Selector(str(selector))
        deliver, drop, channel = _handler(handler)
        if channel is not None:
            channel.deadline = time.monotonic() + (GET_TIMEOUT_S if timeout is None else timeout)
        targets = self.network._queryables(sel.key_expr)
        state = _GetState(deliver, drop, len(targets))
        for q in targets:
            query = Query(sel, payload, encoding, attachment, state)
            _call(q.deliver, query)
            del query  # a callback that keeps no reference has finished with it
        return channel

    def liveliness(self) -> Liveliness:
        return Liveliness(self)

    # -- closing
    def close(self) -> None:
        """Undeclare everything (the tokens' DELETE reaches liveliness subscribers)."""
        if self._closed:
            return
        self._closed = True
        for token in list(self._tokens):
            token.undeclare()
        for e in list(self._entities):
            e.undeclare()
        self.network._left(self)

    def is_closed(self) -> bool:
        return self._closed

    def __enter__(self):
        return self

    def __exit__(self, *_exc):
        self.close()


class FakeNetwork:
    """The router every FakeSession of a test talks through."""

    def __init__(self):
        self.lock = threading.RLock()
        self.sessions: list[FakeSession] = []

    def open(self, _config=None) -> FakeSession:
        """A new session (what `zenoh.open(config)` gives; the config is not read)."""
        s = FakeSession(self)
        with self.lock:
            self.sessions.append(s)
        return s

    def _left(self, session: FakeSession) -> None:
        with self.lock:
            if session in self.sessions:
                self.sessions.remove(session)

    def _entities(self, cls: type, key: zenoh.KeyExpr) -> list:
        with self.lock:
            return [
                e for s in self.sessions for e in s._entities if type(e) is cls and e.matches(key)
            ]

    def _queryables(self, key: zenoh.KeyExpr) -> list[Queryable]:
        return self._entities(Queryable, key)

    def _has_subscriber(self, key: zenoh.KeyExpr) -> bool:
        return bool(self._entities(Subscriber, key))

    def _tokens(self, key: zenoh.KeyExpr) -> list[LivelinessToken]:
        with self.lock:
            return [
                t
                for s in self.sessions
                for t in s._tokens
                if not t.undeclared and t.key_expr.intersects(key)
            ]

    def _publish(self, sample: Sample) -> None:
        # delivered outside the lock: a callback may publish in turn
        for sub in self._entities(Subscriber, sample.key_expr):
            _call(sub.deliver, sample)

    def _liveliness(self, key: zenoh.KeyExpr, kind) -> None:
        for sub in self._entities(LivelinessSubscriber, key):
            _call(sub.deliver, Sample(key, b"", kind=kind))


# -- services in-process ------------------------------------------------------------------------


class ServiceRun:
    """A service running on a thread of the test process, looking like the `subprocess.Popen`
    that `ZenohStack` returns: `poll()`, `wait()`, `returncode`, `pid`, `log_name`; plus the
    `service` object itself (once constructed) and its `session`."""

    def __init__(self, name: str):
        self.log_name = name
        self.pid = os.getpid()  # what the service's status reports
        self.returncode: int | None = None
        self.service = None
        self.session: FakeSession | None = None
        self.started = threading.Event()  # the service has its session
        self.thread: threading.Thread | None = None

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int | None:
        self.thread.join(timeout)
        if self.thread.is_alive():
            raise subprocess.TimeoutExpired(self.log_name, timeout)
        return self.returncode


class _ThreadLog(logging.Handler):
    """A service's log, as its process's log file would hold it: its logger's lines, anything
    logged on its thread, and what its thread writes to stderr (`smana sim: ...` errors)."""

    def __init__(self, name: str, thread_name: str):
        super().__init__(logging.DEBUG)
        self.name_, self.thread_name = name, thread_name
        self.chunks: list[str] = []
        self.setFormatter(logging.Formatter(f"%(levelname)s {name}: %(message)s"))

    def filter(self, record) -> bool:
        return record.threadName == self.thread_name or record.name == f"smana.{self.name_}"

    def emit(self, record) -> None:
        self.chunks.append(self.format(record) + "\n")


class _StderrByThread:
    """sys.stderr while a FakeStack lives: a service thread's writes go to its log."""

    def __init__(self, original, logs: dict[str, _ThreadLog]):
        self.original, self.logs = original, logs

    def write(self, text: str) -> int:
        h = self.logs.get(threading.current_thread().name)
        if h is None:
            return self.original.write(text)
        h.chunks.append(text)
        return len(text)

    def flush(self) -> None:
        self.original.flush()

    def __getattr__(self, name):
        return getattr(self.original, name)


class FakeStack:
    """Services on one `FakeNetwork`, in this process, with `ZenohStack`'s API (see the module's
    docstring). Use it through the `fake_stack` fixture (tests/conftest.py), which closes it."""

    robot = "test"

    def __init__(self, tmp: Path):
        from smana.common import service as service_module

        self.tmp = Path(tmp)
        # what a [zenoh] section may name (as ZenohStack's router): nothing listens there, every
        # session of the stack is a fake one
        self.endpoint = "tcp/127.0.0.1:7447"
        self.network = FakeNetwork()
        self.runs: list[ServiceRun] = []
        self._session: FakeSession | None = None
        self._logs: dict[str, list[_ThreadLog]] = collections.defaultdict(list)
        self._by_thread: dict[threading.Thread, ServiceRun] = {}
        self._count = itertools.count(1)
        self._service_module = service_module
        self._saved_factory = service_module.session_factory
        service_module.session_factory = self._open_for
        self._smana_log = logging.getLogger("smana")
        self._saved_level = self._smana_log.level
        self._smana_log.setLevel(logging.INFO)
        self._by_thread_name: dict[str, _ThreadLog] = {}

    # ZenohStack compatibility: the processes a test started
    @property
    def procs(self) -> list[tuple[str, ServiceRun]]:
        return [(r.log_name, r) for r in self.runs]

    @procs.setter
    def procs(self, value) -> None:
        self.runs = [r for _, r in value]

    def _open_for(self, service) -> FakeSession:
        """`smana.common.service.session_factory` while the stack lives."""
        session = self.network.open()
        run = self._by_thread.get(threading.current_thread())
        if run is not None:
            run.service, run.session = service, session
            run.started.set()
        return session

    @property
    def session(self) -> FakeSession:
        """The test's own session on the network."""
        if self._session is None:
            self._session = self.network.open()
        return self._session

    def publisher(self, key: str, timeout_s: float = 10.0) -> Publisher:
        """A publisher that has seen a matching subscriber (as ZenohStack's)."""
        from tests.conftest import wait_for

        pub = self.session.declare_publisher(key)
        if not wait_for(lambda: pub.matching_status.matching, timeout_s):
            raise TimeoutError(f"no subscriber for {key} after {timeout_s} s")
        return pub

    def subscriber(self, key: str, handler, timeout_s: float = 10.0):
        """A subscriber on the test's session (as ZenohStack's). Declarations reach the fake
        network at once: there is nothing to wait for, and that is checked."""
        sub = self.session.declare_subscriber(key, handler)
        if not self.network._has_subscriber(key_expr(key)):
            raise AssertionError(f"the fake network does not see a subscriber to {key}")
        return sub

    # -- starting and stopping
    def start(self, name: str, cli: Callable[[list[str] | None], int | None], *argv: str):
        """Run `cli(argv)` (a command's entry, as `python -m` would) on a thread of its own;
        the services it runs open their sessions on this stack's network."""
        from smana.common.cli import run_command

        run = ServiceRun(name)
        thread_name = f"{name}-{next(self._count)}"
        handler = _ThreadLog(name, thread_name)
        self._logs[name].append(handler)
        self._by_thread_name[thread_name] = handler
        if not isinstance(sys.stderr, _StderrByThread):  # (pytest swaps it between phases)
            sys.stderr = _StderrByThread(sys.stderr, self._by_thread_name)
        logging.getLogger().addHandler(handler)

        def body() -> None:
            try:
                code = run_command(name, cli, list(argv))
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
            except BaseException:
                logging.getLogger(f"smana.{name}").exception("%s crashed", name)
                code = 1
            if run.returncode is None:
                run.returncode = code
            run.started.set()

        run.thread = threading.Thread(target=body, name=thread_name, daemon=True)
        self._by_thread[run.thread] = run
        self.runs.append(run)
        run.thread.start()
        return run

    def service(self, name: str, *args: str, module: str | None = None) -> ServiceRun:
        """Start a smana service (its `__main__.cli`) on this network, robot `test`."""
        mod = importlib.import_module(f"{module or f'smana.services.{name}'}.__main__")
        return self.start(name, mod.cli, "--robot", self.robot, *args)

    def stop(self, run: ServiceRun, sig=signal.SIGINT, timeout_s: float = 5.0) -> int | None:
        """SIGINT / SIGTERM: the service's own stop (what its signal handler does). SIGKILL: a
        crash, its session gone at once (tokens vanish), no on_stop, nothing saved."""
        if run.returncode is not None:
            return run.returncode
        run.started.wait(timeout_s)
        svc = run.service
        if sig == signal.SIGKILL or svc is None:
            if run.session is not None:
                run.session.close()
            if svc is not None:
                svc.on_stop = lambda: None
                svc.stop()
            run.returncode = -signal.SIGKILL
            run.thread.join(timeout_s)
            return run.returncode
        svc.stop()
        run.thread.join(timeout_s)
        if run.thread.is_alive():  # what ZenohStack would SIGKILL
            return self.stop(run, signal.SIGKILL, timeout_s)
        return run.returncode

    def wait_alive(self, service: str, timeout_s: float = 30.0, robot: str | None = None) -> None:
        from smana.common import keys
        from tests.conftest import kernels_ready

        key = keys.alive(robot or self.robot, service)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if list(self.session.liveliness().get(key)) and kernels_ready(
                self.session, robot or self.robot, service
            ):
                return
            for r in self.runs:
                if r.log_name == service and r.returncode is not None:
                    raise RuntimeError(f"{service} exited ({r.returncode}):\n{self.log(service)}")
            time.sleep(0.02)
        raise TimeoutError(f"{service} not alive after {timeout_s} s:\n{self.log(service)}")

    def log(self, run_or_name) -> str:
        name = run_or_name if isinstance(run_or_name, str) else run_or_name.log_name
        return "".join(chunk for h in self._logs.get(name, []) for chunk in h.chunks)

    # -- reading a service
    def running(self, name: str):
        """The `Service` object of the last started `name` (its books, counters, core)."""
        for r in reversed(self.runs):
            if r.log_name == name and r.service is not None:
                return r.service
        raise LookupError(f"no service {name} started")

    def publish(self, key: str, msg) -> None:
        """Put a Message (encoded), a map (msgpack) or bytes on `key` from the test's session:
        when this returns, every subscribed service has it queued."""
        import msgpack

        from smana.common.messages import Message, encode

        if isinstance(msg, Message):
            msg = encode(msg)
        elif isinstance(msg, dict):
            msg = msgpack.packb(msg, use_bin_type=True)
        self.session.put(key, msg)

    def books(self, name: str):
        """The service's `Books` (received, accepted, dropped, rejected, in flight)."""
        return self.running(name).books

    def drained(self, name: str, timeout_s: float = 10.0) -> bool:
        """Wait until the service has handled everything it was sent (nothing queued, nothing
        in flight); False after `timeout_s`."""
        from tests.conftest import wait_for

        svc = self.running(name)

        def idle() -> bool:
            with svc.books.lock:
                return svc._pending_locked() == 0

        return wait_for(idle, timeout_s, 0.005)

    def status(self, name: str):
        """The service's ServiceStatus, as a status query answers it."""
        from smana.common import keys
        from smana.common.query import request

        return request(self.session, keys.status(self.robot, name))

    def query(self, name: str, what: str, body=None, timeout_s: float = 5.0):
        """`request` on smana/<robot>/<name>/<what>."""
        from smana.common import keys
        from smana.common.query import request

        return request(self.session, keys.query(self.robot, name, what), body, timeout_s)

    def close(self) -> None:
        for r in reversed(self.runs):
            try:
                self.stop(r, timeout_s=5.0)
            except Exception:  # noqa: BLE001 - tear down the rest
                log.exception("stopping %s", r.log_name)
        if self._session is not None:
            self._session.close()
        for handlers in self._logs.values():
            for h in handlers:
                logging.getLogger().removeHandler(h)
        self._service_module.session_factory = self._saved_factory
        self._smana_log.setLevel(self._saved_level)
        if isinstance(sys.stderr, _StderrByThread):
            sys.stderr = sys.stderr.original
