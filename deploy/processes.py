"""The supervisor's processes: one `Managed` per supervised service, and how `smana up` starts,
signals, restarts and stops them, with their hot spares (deploy/supervisor.py holds the loop).

A spare is a second process of the same command, started with `STANDBY_ENV` naming a pipe: it
imports and prepares, says "ready" on the pipe, and waits on its stdin; "go" makes it take over,
closing its stdin ends it (common/service.py).
"""

from __future__ import annotations

import collections
import logging
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from smana.common.config import ServiceDeployConfig
from smana.common.service import STANDBY_ENV, die_with_parent

log = logging.getLogger("smana.up")


@dataclass
class Managed:
    """One supervised service process."""

    name: str  # "mapper", or "mapper@r2" when the supervisor runs several robots
    argv: list[str]
    policy: ServiceDeployConfig
    log_path: Path
    service: str = ""
    robot: str = ""
    proc: subprocess.Popen | None = None
    started_at: float = 0.0
    alive: bool = False  # its alive token is up (ready)
    starting: bool = False  # its starting token is up (loading, compiling)
    seen_alive: bool = False  # the alive token came up at least once since the last start
    seen_starting: bool = False  # ... the starting token
    lost_at: float | None = None  # when the token vanished while the process still ran
    down_at: float | None = None  # when its last process ended (for the time back)
    restarts: collections.deque = field(default_factory=collections.deque)  # in the window
    n_restarts: int = 0
    crash_looped: bool = False  # restarted more than max_restarts in a window at some point
    next_start: float = 0.0
    finished: bool = False  # exited and will not be restarted
    ever_ready: bool = False
    ready_s: list[float] = field(default_factory=list)  # start -> alive, each process
    ready_at: float | None = None  # when the current process became ready
    back_s: list[float] = field(default_factory=list)  # end of a process -> next one alive
    exit_codes: list[int] = field(default_factory=list)
    spare: subprocess.Popen | None = None  # the standby process, when the policy asks for one
    took_over: bool = False  # the current process is a spare that took over
    # each crash that was restarted: exit status, seconds into the run, seconds until the next
    # process was ready (None while it is not), whether a hot spare took over
    crashes: list[dict] = field(default_factory=list)
    killed_for: str = ""  # why the supervisor killed the current process (its health checks)


class ProcessControl:
    """Starting, signalling, restarting and stopping `Managed` processes, and their spares. Mixed
    into `Supervisor`, whose `config`, `statuses`, `_lock`, `_stop` and `_t0` it uses."""

    def _start_process(self, m: Managed, standby: bool) -> subprocess.Popen:
        logf = open(m.log_path, "ab")  # noqa: SIM115 - the child owns it; closed below
        what = "standby" if standby else "start"
        logf.write(f"\n--- {what} {time.strftime('%H:%M:%S')}: {' '.join(m.argv)}\n".encode())
        logf.flush()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        ready_r = ready_w = None
        if standby:  # the spare says "ready" on a pipe of its own once it has prepared
            ready_r, ready_w = os.pipe()
            os.set_blocking(ready_r, False)
            env[STANDBY_ENV] = str(ready_w)
        proc = subprocess.Popen(
            m.argv,
            stdout=logf,
            stderr=subprocess.STDOUT,
            stdin=subprocess.PIPE if standby else subprocess.DEVNULL,
            start_new_session=True,
            env=env,
            preexec_fn=die_with_parent,
            pass_fds=(ready_w,) if standby else (),
        )
        # Children keep the supervisor's working directory, so relative paths in the config
        # (certificates, maps, worlds) mean the same to every process.
        logf.close()
        if standby:
            os.close(ready_w)
            proc.ready_fd = ready_r
            proc.prepared = False
        return proc

    def _spawn(self, m: Managed) -> None:
        m.took_over = False
        if m.spare is not None and m.spare.poll() is None:
            # The hot spare has imported and prepared (or is about to): one line, it takes over.
            proc, m.spare = m.spare, None
            os.close(proc.ready_fd)
            try:
                proc.stdin.write(b"go\n")
                proc.stdin.close()
            except OSError:  # it died meanwhile: start afresh
                proc = self._start_process(m, standby=False)
            else:
                log.info("%s: the standby process (pid %d) takes over", m.name, proc.pid)
                m.took_over = True
        else:
            proc = self._start_process(m, standby=False)
            log.info("started %s (pid %d)", m.name, proc.pid)
        if m.crashes and m.crashes[-1]["back_s"] is None:
            m.crashes[-1]["spare"] = m.took_over
        m.proc = proc
        m.started_at = time.monotonic()
        with self._lock:
            m.alive = m.starting = m.seen_alive = m.seen_starting = False
            m.ready_at = None
        m.lost_at = None

    def _keep_spare(self, m: Managed) -> None:
        """A ready service with `standby` gets a hot spare, `deploy.standby_delay_s` after it
        became ready and once its kernels are loaded (a service is live while they compile: so
        the two never compile the same kernels at once on a cold cache, and a short run never
        pays for it)."""
        if m.spare is not None and m.spare.poll() is not None:
            log.warning("%s: its standby process exited with status %d", m.name, m.spare.returncode)
            self._end_spare(m)
        ready_for = time.monotonic() - m.ready_at if m.ready_at is not None else -1.0
        st = self.statuses.get((m.robot, m.service))  # one dict read: no lock needed
        if (
            m.spare is None
            and m.policy.standby
            and ready_for >= self.config.deploy.standby_delay_s
            and (st is None or st.details.get("kernels", "ready") == "ready")
            and not self._stop.is_set()
        ):
            m.spare = self._start_process(m, standby=True)
        if m.spare is not None and not m.spare.prepared:
            try:
                m.spare.prepared = bool(os.read(m.spare.ready_fd, 64))
            except BlockingIOError:
                pass

    def spare_ready(self, m: Managed) -> bool:
        """Whether `m` has a standby process that has prepared and waits to take over."""
        return m.spare is not None and m.spare.prepared

    def _end_spare(self, m: Managed) -> None:
        if m.spare is not None:
            try:
                m.spare.stdin.close()  # a standby process ends when its stdin closes
                m.spare.wait(timeout=2.0)
            except (OSError, subprocess.TimeoutExpired):
                m.spare.kill()
                m.spare.wait()
            os.close(m.spare.ready_fd)
            m.spare = None

    def _signal(self, m: Managed, sig: int) -> None:
        if m.proc is not None and m.proc.poll() is None:
            try:
                os.killpg(m.proc.pid, sig)
            except ProcessLookupError:
                pass

    def _schedule_restart(self, m: Managed, why: str) -> None:
        now = time.monotonic()
        if m.exit_codes and m.exit_codes[-1] != 0:  # a crash, not a clean end under "always"
            at = now - self._t0 if self._t0 is not None else 0.0
            crash = {"code": m.exit_codes[-1], "at_s": at, "back_s": None, "spare": False}
            m.crashes.append({**crash, "killed_for": m.killed_for})
            m.killed_for = ""
        p = m.policy
        while m.restarts and now - m.restarts[0] > p.restart_window_s:
            m.restarts.popleft()
        if len(m.restarts) >= p.max_restarts:
            # A crash loop: keep trying, slowly, and make sure the run says so.
            delay = p.restart_max_delay_s
            if not m.crash_looped:
                log.error(
                    "%s keeps failing (%d restarts in %.0f s): restarting it every %.0f s "
                    "from now on; the run will be reported failed (see %s)",
                    m.name,
                    len(m.restarts),
                    p.restart_window_s,
                    delay,
                    m.log_path,
                )
            m.crash_looped = True
        else:
            delay = min(p.restart_delay_s * 2 ** len(m.restarts), p.restart_max_delay_s)
        m.restarts.append(now)
        m.n_restarts += 1
        m.next_start = now + delay
        log.warning("%s %s; restarting in %.1f s (see %s)", m.name, why, delay, m.log_path)

    def _stop_wave(self, running: list[Managed]) -> None:
        # Stop in reverse data-flow order: the explorer stops driving before the sim goes away.
        for m in reversed(running):
            self._signal(m, signal.SIGINT)
        deadline = time.monotonic() + self.config.deploy.stop_timeout_s
        for m in reversed(running):
            try:
                m.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning(
                    "%s did not stop within %.0f s: killing it",
                    m.name,
                    self.config.deploy.stop_timeout_s,
                )
                self._signal(m, signal.SIGKILL)
                m.proc.wait()
            m.exit_codes.append(m.proc.returncode)
            m.proc = None
