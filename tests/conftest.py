"""Shared fixtures: an isolated zenoh router on a free loopback port (multicast scouting and gossip
off), services started as subprocesses in their own process groups, and a client session for the
test to publish and query with (`zenoh_stack`, for lifecycle and transport tests); or the same
services on threads of the test's process over a fake zenoh (`fake_stack`, for handler logic:
tests/support/fake_zenoh.py). Everything is torn down even when the test fails."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from smana.common.zenoh_config import free_loopback_port, wait_port
from smana.deploy.supervisor import die_with_parent

REPO = Path(__file__).resolve().parents[1]
ROBOT = "test"


def pytest_configure(config):
    """Before the workers start (the controller of a parallel run only), compile the services'
    numba kernels once with `smana warmup`. On a fresh clone the cache is empty and the workers'
    services would otherwise compile the same kernels at once on the same cores; on a warm cache
    this loads them and takes a second or two. A failure here fails no test: every service still
    compiles what is missing itself (the cold start has its own test, test_resilience.py)."""
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None):
        return
    if config.option.collectonly:
        return
    t0 = time.monotonic()
    argv = [sys.executable, "-m", "smana.deploy.warmup"]
    try:
        done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired:
        sys.stderr.write("numba warm-up before the workers: gave up after 300 s\n")
        return
    tail = done.stdout.strip().splitlines()[-1:] or done.stderr.strip().splitlines()[-1:]
    sys.stderr.write(f"numba warm-up before the workers: {time.monotonic() - t0:.1f} s, ")
    sys.stderr.write(f"exit {done.returncode}: {tail[0] if tail else ''}\n")


@pytest.fixture(autouse=True)
def _signal_dispositions():
    """Each test leaves SIGINT and SIGTERM as it found them: a test that ran a command in
    process once left SIGINT ignored in its worker, and every child the worker started after it
    (`smana goto` under a Ctrl-C test) inherited the ignore."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in saved.items():
        if handler is not None and signal.getsignal(sig) is not handler:
            signal.signal(sig, handler)


def stop_group(proc: subprocess.Popen, sig=signal.SIGINT, timeout_s: float = 5.0) -> int:
    """Signal a process group; SIGKILL it if it has not exited within `timeout_s`."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def stop_together(procs, timeout_s: float = 5.0) -> None:
    """Every process group asked to stop at once (SIGINT), each killed if it has not exited by
    one shared deadline: a teardown waits for the slowest, not for the sum."""
    live = [p for p in procs if p.poll() is None]
    for p in live:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    for p in live:
        stop_group(p, timeout_s=max(0.0, deadline - time.monotonic()))


def free_port() -> int:
    return free_loopback_port()


def wait_for(pred, timeout_s: float = 20.0, step_s: float = 0.05) -> bool:
    """Poll `pred` until it is true (True) or `timeout_s` passes (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step_s)
    return False


def kernels_ready(session, robot: str, service: str) -> bool:
    """Whether a live service's kernels are loaded (`common.query.ready`, less the token)."""
    from smana.common import keys
    from smana.common.query import QueryError, request

    try:
        st = request(session, keys.status(robot, service), timeout_s=2.0)
    except QueryError:
        return False
    return st.details.get("kernels", "ready") == "ready"


class ZenohStack:
    """A router plus the processes a test starts against it."""

    def __init__(self, tmp: Path, router_args: tuple[str, ...] = ()):
        self.tmp = tmp
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.robot = ROBOT
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self._session = None
        self._probe = None
        self.router = self.start(
            "router", "-m", "smana.deploy.router", "--listen", self.endpoint, *router_args
        )
        wait_port(self.port)

    def zenoh_args(self) -> list[str]:
        return ["--mode", "client", "--connect", self.endpoint]

    def start(self, name: str, *argv: str, env: dict | None = None) -> subprocess.Popen:
        """Start `python <argv>` in its own process group; output goes to <tmp>/<name>.log."""
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - the child owns it
        full_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        proc = subprocess.Popen(
            [sys.executable, *argv],
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            env=full_env,
            cwd=self.tmp,
            preexec_fn=die_with_parent,  # a killed pytest leaves no service behind
        )
        log.close()
        proc.log_name = name
        self.procs.append((name, proc))
        return proc

    def service(self, name: str, *args: str, module: str | None = None) -> subprocess.Popen:
        """Start a smana service connected to this router, robot `test`."""
        module = module or f"smana.services.{name}"
        return self.start(name, "-m", module, *self.zenoh_args(), "--robot", self.robot, *args)

    def log(self, proc_or_name) -> str:
        name = proc_or_name if isinstance(proc_or_name, str) else proc_or_name.log_name
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    @property
    def session(self):
        if self._session is None:
            import zenoh

            from smana.common.config import ZenohConfig
            from smana.common.zenoh_config import make_zenoh_config

            zc = ZenohConfig(mode="client", connect=[self.endpoint])
            self._session = zenoh.open(make_zenoh_config(zc))
        return self._session

    def publisher(self, key: str, timeout_s: float = 10.0):
        """A publisher that blocks rather than drops (test messages must all arrive) and has
        seen a matching subscriber: puts made right after declaring are otherwise lost."""
        import zenoh

        pub = self.session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        if not wait_for(lambda: pub.matching_status.matching, timeout_s):
            raise TimeoutError(f"no subscriber for {key} after {timeout_s} s")
        return pub

    def subscriber(self, key: str, handler, timeout_s: float = 10.0):
        """A subscriber on the test's session that the router has passed on (the subscriber side
        of `publisher`): declared, then held until a publisher on `key` in another session of this
        stack sees it, so the router holds it and passes it on to the clients that publish on
        `key`. `tests/test_service.py` checks that a service then publishing on `key` reaches it.
        `key` must have no other subscriber: the probe cannot tell one subscriber from another."""
        sub = self.session.declare_subscriber(key, handler)
        probe = self.probe_session.declare_publisher(key)
        try:
            if not wait_for(lambda: probe.matching_status.matching, timeout_s):
                sub.undeclare()
                raise TimeoutError(f"the router did not pass on a subscriber to {key}")
        finally:
            probe.undeclare()
        return sub

    @property
    def probe_session(self):
        """A second client session: where `subscriber` watches its declarations arrive."""
        if self._probe is None:
            import zenoh

            from smana.common.config import ZenohConfig
            from smana.common.zenoh_config import make_zenoh_config

            zc = ZenohConfig(mode="client", connect=[self.endpoint])
            self._probe = zenoh.open(make_zenoh_config(zc))
        return self._probe

    def wait_alive(self, service: str, timeout_s: float = 30.0, robot: str | None = None) -> None:
        from smana.common import keys

        key = keys.alive(robot or self.robot, service)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if list(self.session.liveliness().get(key, timeout=1.0)) and kernels_ready(
                self.session, robot or self.robot, service
            ):
                return
            for name, p in self.procs:
                if name == service and p.poll() is not None:
                    raise RuntimeError(f"{service} exited ({p.returncode}):\n{self.log(service)}")
            time.sleep(0.1)
        raise TimeoutError(f"{service} not alive after {timeout_s} s:\n{self.log(service)}")

    def stop(self, proc: subprocess.Popen, sig=signal.SIGINT, timeout_s: float = 5.0) -> int:
        return stop_group(proc, sig, timeout_s)

    def close(self, timeout_s: float = 5.0) -> None:
        """The test's session, then every service at once (SIGINT, SIGKILL after `timeout_s`),
        then the router they were stopping through."""
        for session in (self._session, self._probe):
            if session is not None:
                session.close()
        self._session = self._probe = None
        stop_together([p for _, p in self.procs if p is not self.router], timeout_s)
        stop_group(self.router, timeout_s=timeout_s)


@pytest.fixture
def zenoh_stack(tmp_path):
    stack = ZenohStack(tmp_path)
    try:
        yield stack
    finally:
        stack.close()


@pytest.fixture
def fake_stack(tmp_path, monkeypatch):
    """Services in this process on a fake zenoh, with `zenoh_stack`'s API; the working directory
    is the test's folder, as it is for `zenoh_stack`'s processes."""
    from tests.support.fake_zenoh import FakeStack

    monkeypatch.chdir(tmp_path)
    stack = FakeStack(tmp_path)
    try:
        yield stack
    finally:
        stack.close()


def saved_maps(folder) -> list[str]:
    """The files a save wrote into `folder`: not the mapper's own journal of its integrations
    (`map.journal`, which it keeps beside its save path from its start), nor an autosave's file
    being written (`map.npz.tmp`, renamed onto `map.npz` when whole)."""
    return sorted(p.name for p in folder.iterdir() if p.suffix not in (".journal", ".tmp"))
