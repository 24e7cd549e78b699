"""A service process started as a hot spare, the way `smana up` starts one (`SMANA_STANDBY_FD`:
it prepares, writes "ready" on that pipe, and takes over at a line on its stdin). The take-over
chain tests start, kill and replace these."""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
from collections import Counter

from smana.common import keys
from smana.common.query import QueryError, request
from smana.deploy.supervisor import die_with_parent

_started: Counter = Counter()  # spares started per service: each log file gets its own name


class HotSpare:
    """`service` (e.g. "mapper") standing by with `args` (after --robot) until `go()`."""

    def __init__(self, stack, service: str, args: list[str]):
        _started[service] += 1
        self.service, self.name = service, f"{service}{_started[service]}"
        r, w = os.pipe()
        log = open(stack.tmp / f"{self.name}.log", "ab")  # noqa: SIM115 - the child owns it
        self.proc = subprocess.Popen(
            [sys.executable, "-m", f"smana.services.{service}", *stack.zenoh_args()]
            + ["--robot", stack.robot, *args],
            stdin=subprocess.PIPE,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1", SMANA_STANDBY_FD=str(w)),
            cwd=stack.tmp,
            pass_fds=(w,),
            preexec_fn=die_with_parent,
        )
        os.close(w)
        log.close()
        self.proc.log_name = self.name
        self.ready_fd = r
        self.stack = stack
        stack.procs.append((self.name, self.proc))

    def wait_prepared(self, timeout_s: float = 180.0) -> None:
        ready, _, _ = select.select([self.ready_fd], [], [], timeout_s)
        assert ready and os.read(self.ready_fd, 16).startswith(b"ready"), self.log()
        os.close(self.ready_fd)

    def go(self) -> None:
        self.proc.stdin.write(b"go\n")
        self.proc.stdin.flush()

    def running(self) -> bool:
        """Live, and the service answering its status is this process."""
        assert self.proc.poll() is None, self.log()
        try:
            st = request(
                self.stack.session, keys.status(self.stack.robot, self.service), timeout_s=1
            )
        except QueryError:
            return False
        return st.pid == self.proc.pid and st.state == "running"

    def kill(self, sig=signal.SIGKILL) -> int:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, sig)
        return self.proc.wait(30)

    def log(self) -> str:
        return self.stack.log(self.name)


class SpareChain:
    """One service's spares and the one that runs: `make()` starts a spare; `take_over` tells
    the first spare waiting (or a new one) to take over."""

    def __init__(self, make):
        self.make = make
        self.spares: list[HotSpare] = []
        self.active: HotSpare | None = None

    def spare(self) -> HotSpare:
        s = self.make()
        self.spares.append(s)
        return s

    def take_over(self, prepared: bool = True) -> HotSpare:
        """`prepared`: wait until it has prepared first (else it is told at once)."""
        s = self.spares.pop(0) if self.spares else self.spare()
        if prepared:
            s.wait_prepared()
        s.go()
        self.active = s
        return s

    def wait_running(self) -> None:
        from tests.conftest import wait_for

        assert wait_for(self.active.running, 120, 0.05), self.active.log()
