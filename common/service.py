"""The service lifecycle every smana process shares.

A service subclasses `Service`, compiles or loads its kernels in `prepare()`, loads the run's
state in `warm_up()`, declares its inputs and outputs in `setup()` and does its periodic work in
`tick()`. The base class does the rest:

- with `prepare_in_background` (services whose `prepare()` only compiles numba kernels), runs
  `prepare()` on a thread of its own from the process's start, so the service is live (alive
  token, status answered) in seconds even on a cold numba cache, instead of after a minute of
  compiling. Its status says `details.kernels = "compiling"` until they are loaded (`"ready"`,
  with `kernels_s` from the process's start). Until then the main loop runs nothing that may call
  a kernel: samples wait in their queues, in order, and ticks wait; a query is answered the
  error `warming_up` (ask again; after `WARMING_UP_HOLD_S`, none by default); status queries are
  answered from the zenoh callback (as while starting). Only `warm_up()` and
  `setup()` (a map to resume, a graph to sync) may call a kernel meanwhile: numba compiles under
  one lock, so they wait for it, before the service is live.
  `SMANA_KERNELS=foreground` restores the old order (prepare, then live; `smana bench startup`
  compares both);
- opens the zenoh session (`with zenoh.open(conf) as session`) and at once declares the liveliness
  token `smana/<robot>/starting/<service>` and publishes a `ServiceStatus` in state `starting`
  every `general.status_period_s` (and answers it as a query), so that a supervisor and `smana
  status` see a service that is loading a map or compiling numba kernels (seconds to minutes on a
  cold cache) and never take it for a hung one;
- when `warm_up()` and `setup()` are done, declares `smana/<robot>/alive/<service>` (ready) and
  undeclares the starting token;
- runs every handler on ONE thread, the service's main loop, so service code needs no locks. Zenoh
  callbacks only copy the payload into a queue and return (never block inside a zenoh callback):
    * `subscribe(key, handler)`: FIFO, for light messages (poses, patches, commands);
    * `subscribe_latest(key, handler)`: latest wins, for heavy inputs (point clouds). A scan that
      arrives while the previous one is still waiting is dropped as `stale`;
    * `queryable(key, handler)`: the query waits in the FIFO and is answered from the main loop;
- keeps the books (`Books`): every sample and query it receives ends in exactly one counter:
  `accepted`, `dropped` by reason (`stale`, `queue_full`, `stopping`, `covered`) or `rejected` by
  kind (a `MessageError` kind, a handler's `Reject` kind, `oversize` before anything is copied,
  `internal` for a bug), or is still `pending`. The status carries them and adds up:
  `msgs_in == accepted + sum(dropped) + sum(rejected) + pending`. Things worth counting that are not
  a message's fate (points dropped inside an accepted cloud, a gap in a sequence) are `events`;
- a bad message is counted, logged (the first few of a kind, then one in a hundred; the first
  traceback of each internal error) and dropped: nothing a peer sends ends a service, and its state
  stays as it was (a handler checks before it changes anything, or raises `Reject`);
- stops on SIGINT/SIGTERM: stops the loop, calls `on_stop()` (flush state), undeclares everything,
  closes the session. It exits well within 5 s unless `on_stop` itself takes longer. A stop that
  hangs outside `on_stop` (leaving the loop, or closing zenoh) for `STOP_DEADLINE_S` dumps every
  thread's stack to the log and exits with status 3: with its supervisor gone (killed -9), nobody
  else would end it.

The class is put together by job: this module holds the lifecycle (run, the main loop, standby,
kernels, stop and its watchdog); `service_io.py` the inputs, outputs and books (`Inbox`);
`service_queries.py` queries and their replies (`Answers`); `service_liveliness.py` the status
and its heartbeat (`Liveliness`). Services import all of it from here.

A complete minimal example is `tests/support/echo_service.py`. Tests run services in-process on a
fake zenoh (`tests/support/fake_zenoh.py`), handed to `run` through `session_factory`.

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
from collections.abc import Callable
from typing import Any

from smana.common import keys
from smana.common.config import SmanaConfig
from smana.common.messages import MAX_PAYLOAD_BYTES
from smana.common.service_io import Books, Inbox, LatestSlot
from smana.common.service_liveliness import Liveliness, kernels_loaded
from smana.common.service_queries import (
    Answers,
    Reject,
    Reply,
    ReplyError,
    Request,
    query_form,
)
from smana.common.zenoh_config import make_zenoh_config, open_session

# What services and tools import from here: the service API, whichever module holds each part.
__all__ = [
    "Reject",
    "Reply",
    "ReplyError",
    "Request",
    "Service",
    "die_with_parent",
    "kernels_loaded",
    "on_stop_signals",
    "run_service",
]

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


def open_service_session(service: Service):
    """The zenoh session a service runs on: one opened from its [zenoh] section, plus what the
    service itself needs of zenoh (`Service.zenoh_settings`)."""
    if not service.zenoh_settings:
        return open_session(service.config.zenoh)
    conf = make_zenoh_config(service.config.zenoh)
    for key, value in service.zenoh_settings.items():
        conf.insert_json5(key, json.dumps(value))
    return open_session(conf)


# How `Service.run` opens its session. In-process tests put a fake zenoh's here
# (tests/support/fake_zenoh.py), so that a service runs its real lifecycle and handlers with no
# router and no process of its own.
session_factory: Callable[[Service], Any] = open_service_session

STOP_DEADLINE_S = 5.0  # after a stop signal: to leave the loop, and to close zenoh after on_stop
# Set by the supervisor for a hot spare (deploy/supervisor.py): prepare, write "ready" to the file
# descriptor it names, then wait for a line on stdin before starting for real.
STANDBY_ENV = "SMANA_STANDBY_FD"
# "foreground": prepare() before the service is live even where it may run in the background.
KERNELS_ENV = "SMANA_KERNELS"
# A query to a service still compiling its kernels waits this long, then is answered `warming_up`.
# None: a consumer's setup() may be the one asking (the planner's graph sync: held 1 s, it made the
# planner live 1 s later), and every consumer asks again (bench startup, 2026-11-26).
WARMING_UP_HOLD_S = 0.0


class Service(Inbox, Answers, Liveliness):
    """Base of every smana service. Subclasses set `name` and override `warm_up`, `setup`,
    `tick`, `on_stop` and `status_details` as they need."""

    name = "service"
    tick_period_s = 0.1  # how often tick() runs
    drain_on_stop = False  # handle what is still queued when a stop comes (the recorder does)
    max_payload_bytes = MAX_PAYLOAD_BYTES  # larger samples are rejected as `oversize`, uncopied
    zenoh_settings: dict[str, Any] = {}  # zenoh config keys this service needs set (json values)
    # prepare() only compiles kernels: run it on a thread, the service live meanwhile (see above)
    prepare_in_background = False

    def __init__(self, config: SmanaConfig):
        self.config = config
        self.robot = config.general.robot
        self.log = logging.getLogger(f"smana.{self.name}")
        self.session = None
        self.producer = ""  # this process's zenoh session id: names the streams it numbers
        self.books = Books()
        self.msgs_out = 0
        self.events: collections.Counter[str] = collections.Counter()
        # counters that worker threads bump beside the main loop (events, msgs_out): += is a read
        # and a write, so two threads can lose one without it
        self._counter_lock = threading.RLock()
        self.state = "starting"
        self.startup_step = "opening the zenoh session"  # what a starting service is doing
        self.ready_s: float | None = None  # seconds from process start to ready
        # CPU seconds of the process (every thread, imports included) when it got ready: what a
        # start costs whatever else runs on the machine
        self.ready_cpu_s = 0.0
        self.kernels = "ready"  # "compiling" while a background prepare() runs
        self.kernels_s: float | None = None  # seconds from process start to kernels loaded
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._ready = threading.Event()  # warmed up and declared: the starting heartbeat ends
        self._signalled = False  # a stop signal came: the stop watchdog is armed
        self._watchdog: threading.Timer | None = None
        self._wake = threading.Event()
        self._fifo: collections.deque = collections.deque()
        self._latest: list[tuple[LatestSlot, Callable]] = []
        # for a latest-wins handler: how many newer samples of its input were dropped as stale
        # just before the one it is given (a sender's numbering gap minus these was lost on the
        # way, before reaching this service)
        self.stale_before = 0
        self._declared: list[Any] = []
        self._status_seq = 0
        self._status_lock = threading.Lock()
        self._tracebacks_logged: set[str] = set()
        self._kernels_announce = False  # kernels just loaded: publish a status now
        self._held_since: dict[int, float] = {}  # query -> when first held while compiling

    # -- what subclasses override ----------------------------------------------------------------

    def prepare(self) -> None:
        """What the process needs whatever the run's state: compile or load numba kernels, build
        a simulated world. No session, no file of the run: a standby process does it ahead."""

    def warm_up(self) -> None:
        """Load the run's state (a map, a checkpoint) while the supervisor sees the service
        `starting`. The session is open; nothing is declared yet."""

    def setup(self) -> None:
        """Declare subscriptions, queryables and publishers (self.session is open)."""

    def tick(self) -> None:
        """Periodic work, every `tick_period_s` on the main loop."""

    def on_stop(self) -> None:
        """Flush state before the session closes (save the map, ...)."""

    def standing_by(self) -> None:
        """A hot spare, about every 0.2 s while it waits to take over (no session yet): keep
        what it will need current (the mapper follows its journal)."""

    def status_details(self) -> dict:
        """Service-specific figures for the status message (plain values only)."""
        return {}

    # -- the loop ----------------------------------------------------------------------------------

    def run(self) -> int:
        """Open the session, warm up, run until SIGINT/SIGTERM (or `stop()`), shut down cleanly.

        A standby process (`STANDBY_ENV` set by the supervisor) prepares first, with no session
        and no state of the run, then waits for one line on stdin before it starts for real:
        a hot spare that takes over a crashed service in a fraction of a second."""
        self._install_signal_handlers()
        standby_fd = os.environ.pop(STANDBY_ENV, "")
        standby = bool(standby_fd)
        background = (
            self.prepare_in_background
            and not standby
            and os.environ.get(KERNELS_ENV, "") != "foreground"
        )
        if background:  # from now: compiling overlaps opening zenoh and loading the run's state
            self.kernels = "compiling"
            threading.Thread(target=self._prepare_kernels, name="kernels", daemon=True).start()
        if standby:
            t0 = time.monotonic()
            self.prepare()
            self.log.info("standing by (prepared in %.1f s)", time.monotonic() - t0)
            try:  # tell the supervisor the spare is ready to take over
                os.write(int(standby_fd), b"ready\n")
                os.close(int(standby_fd))
            except (OSError, ValueError):
                pass
            if not self._wait_for_go():
                self.log.info("%s standby stopped", self.name)
                return 0
            self._t0 = time.monotonic()  # readiness counts from the take-over
            self.log.info("%s taking over", self.name)
        with session_factory(self) as session:
            self.session = session
            self.producer = str(session.zid())
            try:
                r = self.robot
                self._status_pub = self.publisher(keys.status(r, self.name))
                self._declared.append(
                    session.declare_queryable(keys.status(r, self.name), self._on_status_query)
                )
                starting = session.liveliness().declare_token(keys.starting(r, self.name))
                self._declared.append(starting)
                threading.Thread(
                    target=self._heartbeat, name="starting-status", daemon=True
                ).start()
                if not standby and not background:
                    self.startup_step = "preparing (compiling or loading kernels)"
                    self.prepare()
                self.startup_step = "warming up"
                if not self.stopping:
                    self.warm_up()
                self.startup_step = "declaring inputs and outputs"
                if not self.stopping:
                    self.setup()
                if not self.stopping:  # a stop while starting: never ready, straight to the end
                    self._declared.append(
                        session.liveliness().declare_token(keys.alive(r, self.name))
                    )
                    with self._status_lock:
                        self.state = "running"
                        self.ready_s = time.monotonic() - self._t0
                        self.ready_cpu_s = time.process_time()
                        self.startup_step = "compiling (or loading) the numba kernels"
                    self._ready.set()  # ends the heartbeat thread (unless kernels compile)
                    self._declared.remove(starting)
                    starting.undeclare()
                    self.log.info(
                        "%s ready in %.1f s (robot %s, pid %d)%s",
                        self.name,
                        self.ready_s,
                        r,
                        os.getpid(),
                        ", kernels still compiling" if self.kernels != "ready" else "",
                    )
                    self._loop()
            finally:
                with self._status_lock:
                    self.state = "stopping"
                self._disarm()  # on_stop may take its time (a large map to save)
                self._settle_leftovers(drain=self.drain_on_stop)
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
                self._settle_leftovers(drain=False)  # what came in during on_stop
                self.session = None
        self._disarm()
        self.log.info("%s stopped", self.name)
        return 0

    def _wait_for_go(self) -> bool:
        """Standby: wait for a line on stdin (go); False when stdin closes (the supervisor is
        gone) or a stop signal comes."""
        import select
        import sys

        while not self.stopping:
            ready, _, _ = select.select([sys.stdin], [], [], 0.2)
            if ready:
                return bool(sys.stdin.readline()) and not self.stopping
            self._guard(self.standing_by, "standing_by")
        return False

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._ready.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _prepare_kernels(self) -> None:
        """The background prepare(): compile or load the kernels, then say so at once (the main
        loop publishes a status as soon as it can)."""
        t0 = time.monotonic()
        try:
            self.prepare()
        except Exception:  # noqa: BLE001 - each kernel then compiles on its first use
            self.log.exception("preparing the kernels failed; they compile on first use")
        with self._status_lock:
            self.kernels = "ready"
            self.kernels_s = time.monotonic() - self._t0
        self.log.info("kernels ready (%.1f s in the background)", time.monotonic() - t0)
        self._kernels_announce = True
        self._ready.set()
        self._wake.set()

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

    def _loop(self) -> None:
        next_tick = next_status = time.monotonic()
        period = self.config.general.status_period_s
        while not self._stop.is_set():
            if self.kernels != "ready":
                self._hold_while_compiling(period)
                next_tick = next_status = time.monotonic()
                continue
            self._held_since.clear()
            now = time.monotonic()
            timeout = max(0.0, min(next_tick, next_status) - now)
            if not self._fifo:
                self._wake.wait(timeout)
            self._wake.clear()
            # Light messages first, all of them; then at most one heavy item per input, so that
            # queries and poses are never stuck behind a backlog of scans.
            self._drain_fifo()
            for slot, handle in self._latest:
                if self._stop.is_set():
                    break
                payload = self._take_latest(slot)
                if payload is not None:
                    handle(payload)
                    self._drain_fifo()
            now = time.monotonic()
            if now >= next_tick:
                next_tick = now + self.tick_period_s
                self._guard(self.tick, "tick")
            if now >= next_status or self._kernels_announce:
                next_status = now + period
                if self.kernels == "ready":  # until then the heartbeat thread publishes
                    self._kernels_announce = False
                    self._guard(self._publish_status, "status")

    def _hold_while_compiling(self, period: float) -> None:
        """The kernels are still compiling: run nothing that may call one. Everything waits in
        its queue, in order, and is handled once they are loaded; a query still waiting after
        `WARMING_UP_HOLD_S` is answered the error `warming_up` (ask again: counted dropped
        `warming_up`), not left to time out. The status is answered from the zenoh callback."""
        self._wake.wait(min(period, 0.2))
        self._wake.clear()
        now = time.monotonic()
        with self.books.lock:
            late = []
            for item in self._fifo:
                if item[0] == "query":
                    since = self._held_since.setdefault(id(item[3]), now)
                    if now - since >= WARMING_UP_HOLD_S:
                        late.append(item)
            if late:
                gone = {id(item) for item in late}
                kept = [item for item in self._fifo if id(item) not in gone]
                self._fifo.clear()
                self._fifo.extend(kept)
                self.books.in_flight += len(late)
        for _what, _handler, _key, query in late:
            self._held_since.pop(id(query), None)
            self.books.settle("dropped", "warming_up")
            try:
                as_json = query_form(query)[1]
            except Exception:  # noqa: BLE001 - unreadable: answered in msgpack
                as_json = False
            self._reply_err(
                query,
                "warming_up",
                f"{self.name} is compiling its numba kernels ({now - self._t0:.0f} s since its "
                "start); ask again in a few seconds",
                as_json,
            )


def run_service(cls: type[Service], config: SmanaConfig) -> int:
    """What every service's `main(config)` calls."""
    return cls(config).run()
