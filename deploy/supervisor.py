"""`smana up`: the supervisor that starts the whole stack and keeps it running.

It opens a zenoh router in its own process (a Python session in router mode on loopback, so no
zenohd is needed), writes the config it uses into the run directory, and starts each enabled
service as its own OS process (own process group, log file in `<run_dir>/logs/`),
connected to that router.

Per service, dora's vocabulary: a restart policy (`never`, `on-failure`, `always`), a restart delay
that doubles up to a cap, and a maximum number of restarts in a window, past which the service is
in a crash loop: still restarted, every `restart_max_delay_s`, and the run is reported failed. The
supervisor never gives a service up silently.

Health comes from two liveliness tokens. `smana/<robot>/starting/<service>` appears as soon as the
service's session is open: it is loading or compiling (a cold numba cache takes minutes on a busy
2-core machine), and is left alone up to `startup_timeout_s`. `smana/<robot>/alive/<service>` says
it is ready. A service that shows neither within `health_timeout_s` of its start, is still
starting after `startup_timeout_s`, or whose alive token vanished while its process still runs, is
killed and restarted.

The mapper resumes from its autosave and its journal in the run directory (`mapper.load = "auto"`
unless the config names a file): a crash loses no voxel a consumer saw, only what was in flight
(counted, `services/mapper/service.py`); its hot spare follows the journal while it stands by.
Navgraph, planner and explorer resync from their producers' snapshots and the explorer from its
checkpoint. A crash is never silent, even when a spare took over at once: each process that ended
on its own with a non-zero status and was restarted is a warning of the run (`crashes`), in
report.md and the terminal summary.

The run ends when the service named by `deploy.finish_with` exits with status 0 (the explorer, when
exploration is done), after `--duration`, or on Ctrl-C; every service then gets SIGINT, and SIGKILL
after `deploy.stop_timeout_s`; the recorder only once the others have exited, so that it records
everything they sent. The report then says whether the run did its job: a service that
never became ready or kept crashing, a needed service that never ran, no path ever answered, a
robot that did not move each head `report.md` as a warning, end the terminal summary, and make
`smana up` exit 1.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from smana.common import keys
from smana.common.cli import config_from_args, make_parser, setup_logging
from smana.common.config import ConfigError, ServiceDeployConfig, SmanaConfig
from smana.common.messages import MessageError, ServiceStatus, decode
from smana.common.service import STANDBY_ENV, die_with_parent, on_stop_signals

log = logging.getLogger("smana.up")

# Start order follows the data flow: producers first, so consumers find their inputs.
SERVICE_ORDER = ("sim", "mapper", "navgraph", "planner", "explorer", "ros2")
# A fleet (`fleet.robots`, `smana up --robots N`): the fleet's shared services run under
# `fleet.name` on the base (`deploy.fleet_base`), each member's own under its name, on its host
# (`deploy.robots`, default every member). One simulator simulates every member.
FLEET_SHARED = ("sim", "mapper", "navgraph", "coordinator")
FLEET_MEMBER = ("mapper", "planner", "explorer")
# What a service needs beyond smana's own dependencies: (module, the extra that installs it). A
# missing one stops `smana up` before anything starts, in one line (exit 2), instead of a service
# that exits 2 at every restart.
OPTIONAL_NEEDS = {"ros2": (("rosbags", "ros2"),)}
# A service that exits with this status refused its configuration (`run_command`'s user errors):
# restarting it cannot help, so the stack stops and `smana up` exits with it.
CONFIG_ERROR = 2


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


class Supervisor:
    def __init__(self, config: SmanaConfig, run_dir: Path, services: list[str] | None = None):
        self.config = config
        self.run_dir = Path(run_dir).resolve()
        self.robot = config.general.robot
        self.robots = list(config.deploy.robots) or [self.robot]
        names = (
            services
            if services is not None
            else [n for n in (*SERVICE_ORDER, "coordinator") if getattr(config.deploy, n).enabled]
        )
        self.logs = self.run_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        # Every service is a client of our router (its first listen endpoint): rewrite [zenoh] so
        # the config file written into the run dir is exactly what they run with. The mapper
        # resumes from its autosave in the run dir, so a restart does not lose the map.
        self.service_config = dataclasses.replace(
            config,
            general=dataclasses.replace(config.general, run_dir=str(self.run_dir)),
            zenoh=dataclasses.replace(
                config.zenoh, mode="client", connect=config.deploy.router_listen[:1], listen=[]
            ),
            mapper=dataclasses.replace(config.mapper, load=config.mapper.load or "auto"),
        )
        self.config_path = self.service_config.write(self.run_dir / "config.toml")
        self.procs: dict[str, Managed] = {}
        self.fleet = config.fleet.name if config.fleet.robots else None
        if self.fleet is None:
            names = [n for n in names if n != "coordinator"]  # a fleet's alone
        else:
            self._add_fleet(names)
            names = []
        for robot in self.robots:
            for n in names:
                name = n if len(self.robots) == 1 else f"{n}@{robot}"
                self._add_service(name, n, robot)
        self.statuses: dict[tuple[str, str], ServiceStatus] = {}
        self.ended = ""  # why the run ended (for the summary)
        self.seen_ready: set[tuple[str, str]] = set()  # (robot, service) alive at some point,
        # here or on another host
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.config_error: str | None = None  # a service's one line when it exited CONFIG_ERROR
        self.session = None

    _t0: float | None = None  # when start() began: crash times count from it

    def _add_service(self, name: str, service: str, robot: str, extra=()) -> None:
        argv = [
            sys.executable,
            "-m",
            f"smana.services.{service}",
            "--config",
            str(self.config_path),
            "--robot",
            robot,
            *extra,
        ]
        if self.config.zenoh.credentials_file:
            argv += ["--set", f'zenoh.user="{robot}.{service}"']  # each service as itself
        policy = getattr(self.config.deploy, service)
        self.add(name, argv + policy.args, policy, service=service, robot=robot)

    def _add_fleet(self, names: list[str]) -> None:
        """The fleet's layout (FLEET_SHARED, FLEET_MEMBER). Members' files go to
        `<run_dir>/robots/<member>/` (their own map, the explorer's state), the fleet's to the
        run directory itself (the merged map, the simulator's record)."""
        fc, dc = self.config.fleet, self.config.deploy
        if not dc.fleet_members:
            members = []
        elif dc.robots:
            members = list(dc.robots)
        else:  # a base runs every member; a member's own host runs itself
            members = list(fc.robots) if dc.fleet_base else [self.config.general.robot]
        strangers = [r for r in members if r not in fc.robots]
        if strangers:
            raise ConfigError(f"deploy.robots {strangers} are not in fleet.robots {fc.robots}")
        self.robots = members or [self.fleet]
        enabled = names
        if dc.fleet_base:
            for n in FLEET_SHARED:
                if n in enabled:
                    extra = ["--set", 'mapper.source="fleet"'] if n == "mapper" else []
                    self._add_service(f"{n}@{self.fleet}", n, self.fleet, extra)
        for robot in members:
            run_dir = self.run_dir / "robots" / robot
            run_dir.mkdir(parents=True, exist_ok=True)
            for n in FLEET_MEMBER:
                if n in enabled:
                    extra = ["--set", f"general.run_dir={json.dumps(str(run_dir))}"]
                    self._add_service(f"{n}@{robot}", n, robot, extra)

    def add(
        self,
        name: str,
        argv: list[str],
        policy: ServiceDeployConfig | None = None,
        service: str = "",
        robot: str = "",
    ) -> None:
        """Supervise another command (before `start()`): a sensor driver, a user's own node. It
        should declare the liveliness token `smana/<robot>/alive/<service>` as services do."""
        self.procs[name] = Managed(
            name,
            list(argv),
            policy or ServiceDeployConfig(),
            self.logs / f"{name}.log",
            service or name,
            robot or self.robot,
        )

    # -- process control ---------------------------------------------------------------------------

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

    def poll(self) -> None:
        """One supervision step: reap exits, apply restart policies, check health."""
        now = time.monotonic()
        d = self.config.deploy
        for m in self.procs.values():
            if m.finished:
                self._end_spare(m)
                continue
            if m.proc is None:
                if now >= m.next_start:
                    self._spawn(m)
                continue
            self._keep_spare(m)
            code = m.proc.poll()
            if code is not None:
                m.exit_codes.append(code)
                m.proc = None
                m.down_at = now
                with self._lock:
                    m.alive = m.starting = False
                failed = code != 0
                if code == CONFIG_ERROR:
                    m.finished = True
                    self.config_error = f"{m.name} refused its configuration: {_last_line(m)}"
                    log.error("%s; stopping the stack", self.config_error)
                    self._stop.set()
                elif m.policy.restart == "always" or (m.policy.restart == "on-failure" and failed):
                    self._schedule_restart(m, f"exited with status {code}")
                else:
                    m.finished = True
                    level = logging.WARNING if failed else logging.INFO
                    log.log(level, "%s exited with status %d", m.name, code)
                continue
            with self._lock:
                alive, seen, sign = m.alive, m.seen_alive, m.seen_starting or m.seen_alive
            age = now - m.started_at
            if not seen:
                if not sign and age > d.health_timeout_s:
                    log.warning(
                        "%s showed no sign of life (no starting token) %.0f s after its "
                        "start: killing it",
                        m.name,
                        age,
                    )
                    m.killed_for = "no sign of life after its start"
                    self._signal(m, signal.SIGKILL)
                elif age > d.startup_timeout_s:
                    log.warning(
                        "%s still not ready %.0f s after its start "
                        "(deploy.startup_timeout_s): killing it",
                        m.name,
                        age,
                    )
                    m.killed_for = "not ready within deploy.startup_timeout_s"
                    self._signal(m, signal.SIGKILL)
            elif not alive:
                # A service that stops on its own undeclares its token first and then flushes
                # its state: only a process still running well after that is hung.
                if m.lost_at is None:
                    m.lost_at = now
                elif now - m.lost_at > d.stop_timeout_s:
                    log.warning(
                        "%s lost its liveliness token %.0f s ago, still runs: killing it",
                        m.name,
                        now - m.lost_at,
                    )
                    m.killed_for = "hung: its liveliness token gone, the process still running"
                    self._signal(m, signal.SIGKILL)
            else:
                m.lost_at = None

    def _find(self, robot: str, service: str) -> Managed | None:
        for m in self.procs.values():
            if m.robot == robot and m.service == service:
                return m
        return None

    def _on_liveliness(self, sample) -> None:
        import zenoh

        parts = str(sample.key_expr).split("/")
        if len(parts) != 4 or parts[2] not in ("alive", "starting"):
            return
        robot, kind, service = parts[1], parts[2], parts[3]
        up = sample.kind == zenoh.SampleKind.PUT
        now = time.monotonic()
        with self._lock:
            if kind == "alive" and up:
                self.seen_ready.add((robot, service))
            m = self._find(robot, service)
            if m is None or m.proc is None:
                return
            if kind == "starting":
                m.starting = up
                m.seen_starting = m.seen_starting or up
                return
            m.alive = up
            if up and not m.seen_alive:
                m.seen_alive = m.ever_ready = True
                m.ready_at = now
                m.ready_s.append(now - m.started_at)
                if m.down_at is not None:
                    m.back_s.append(now - m.down_at)
                    if m.crashes and m.crashes[-1]["back_s"] is None:
                        m.crashes[-1]["back_s"] = m.back_s[-1]
                    log.info(
                        "%s is back %.2f s after its last process ended (ready %.2f s "
                        "after its start)",
                        m.name,
                        m.back_s[-1],
                        m.ready_s[-1],
                    )

    def _on_status(self, sample) -> None:
        try:
            st = decode(sample.payload.to_bytes(), ServiceStatus)
        except MessageError:
            return
        with self._lock:
            self.statuses[(st.robot, st.service)] = st

    # -- running ---------------------------------------------------------------------------------

    def start(self) -> None:
        from smana.deploy.router import open_router

        d = self.config.deploy
        zc = self.config.zenoh
        if d.ros2.enabled:  # ROS 2 nodes are peers that find each other through the router
            zc = dataclasses.replace(zc, gossip=True)
        self._t0 = time.monotonic()
        self.session = open_router(d.router_listen, zc, d.router_connect)
        endpoints = ", ".join(d.router_listen)
        log.info("zenoh router listening on %s; run directory %s", endpoints, self.run_dir)
        if d.router_connect:
            log.info("linking to router(s) %s", ", ".join(d.router_connect))
        ll = self.session.liveliness()
        self._subs = [
            ll.declare_subscriber(keys.alive_any("*"), self._on_liveliness, history=True),
            ll.declare_subscriber(keys.starting_any("*"), self._on_liveliness, history=True),
            self.session.declare_subscriber(keys.status_any("*"), self._on_status),
        ]
        for m in self.procs.values():
            self._spawn(m)

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        """SIGINT every service, wait, SIGKILL what is left, close the router. Recorders stop
        last, once every other service has exited, so that they record everything it sent."""
        for m in self.procs.values():
            self._end_spare(m)
        running = [m for m in self.procs.values() if m.proc is not None]
        last = [m for m in running if m.service == "recorder"]
        for wave in ([m for m in running if m not in last], last):
            self._stop_wave(wave)
        for s in getattr(self, "_subs", []):
            s.undeclare()
        if self.session is not None:
            self.session.close()
            self.session = None

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

    def run(self, duration_s: float | None = None, progress_period_s: float = 10.0) -> int:
        """Supervise until done; returns 0 when the run finished normally."""
        t0 = time.monotonic()
        next_progress = t0 + progress_period_s
        finish_with = self.config.deploy.finish_with
        result = 0
        self.ended = "stopped (Ctrl-C or a signal)"
        try:
            # Inside the try: a start that fails halfway stops what it started (no orphans)
            self.start()
            while not self._stop.wait(0.1):
                self.poll()
                now = time.monotonic()
                if now >= next_progress:
                    next_progress = now + progress_period_s
                    self.print_progress(now - t0)
                fin = [m for m in self.procs.values() if m.service == finish_with]
                if fin and all(m.finished for m in fin):
                    codes = [m.exit_codes[-1] if m.exit_codes else None for m in fin]
                    result = 0 if all(c == 0 for c in codes) else 1
                    log.info(
                        "%s finished (status %s): stopping the stack",
                        finish_with,
                        ", ".join(map(str, codes)),
                    )
                    self.ended = f"{finish_with} finished"
                    break
                if self.procs and all(m.finished for m in self.procs.values()):
                    log.error("every service has exited")
                    self.ended = "every service exited"
                    result = 1
                    break
                if duration_s is not None and now - t0 >= duration_s:
                    log.info("duration of %.0f s reached: stopping the stack", duration_s)
                    self.ended = f"--duration {duration_s:g} s reached"
                    break
        finally:
            self.shutdown()
        if self.config_error is not None:
            self.ended = self.config_error
            return CONFIG_ERROR
        return result

    def warnings(self) -> list[str]:
        """What the supervisor saw go wrong in this run (the report adds what its figures show)."""
        out = []
        for m in self.procs.values():
            log_file = (
                m.log_path.relative_to(self.run_dir)
                if m.log_path.is_relative_to(self.run_dir)
                else m.log_path
            )
            if not m.ever_ready:
                out.append(f"{m.name} never became ready (see {log_file})")
            if m.crash_looped:
                codes = ", ".join(str(c) for c in m.exit_codes[-5:])
                out.append(
                    f"{m.name} kept crashing: restarted {m.n_restarts} times, more than "
                    f"{m.policy.max_restarts} in {m.policy.restart_window_s:.0f} s (last "
                    f"exit statuses {codes}; see {log_file})"
                )
            else:
                out += self._crash_lines(m, log_file)
            if m.finished and m.exit_codes and m.exit_codes[-1] not in (0, -signal.SIGINT):
                out.append(
                    f"{m.name} exited with status {m.exit_codes[-1]} and was not "
                    f"restarted (restart = {m.policy.restart})"
                )
        if self.config.deploy.finish_with == "explorer":
            # What exploration needs, here or on another host of the deployment.
            for m in [m for m in self.procs.values() if m.service == "explorer"]:
                for need in ("mapper", "navgraph", "planner", "coordinator"):
                    where = m.robot
                    if self.fleet is not None and need in ("navgraph", "coordinator"):
                        where = self.fleet  # the fleet's shared graph and coordinator
                    elif need == "coordinator":
                        continue
                    if (where, need) in self.seen_ready:
                        continue
                    why = "see above"
                    if self._find(where, need) is None:
                        why = f"disabled in this run (deploy.{need}.enabled = false) and none ran"
                        why += " elsewhere"
                    out.append(
                        f"the {need} the explorer of robot {m.robot} needs never came up ({why})"
                    )
        return out

    @staticmethod
    def _crash_lines(m: Managed, log_file) -> list[str]:
        """One line per crash that was restarted (or kill by the health checks): a run that
        recovered still says it crashed."""
        out = []
        for c in m.crashes:
            if c["back_s"] is None:
                back = "not ready again before the run ended"
            else:
                how = "a hot spare took over" if c["spare"] else "restarted"
                back = f"{how}, ready {c['back_s']:.2f} s after it ended"
            what = (
                f"was killed by the supervisor ({c['killed_for']})"
                if c["killed_for"]
                else "crashed"
            )
            out.append(
                f"{m.name} {what} {c['at_s']:.0f} s into the run (exit status {c['code']}; "
                f"{back}; see {log_file})"
            )
        return out

    def print_progress(self, elapsed_s: float) -> None:
        with self._lock:
            statuses = dict(self.statuses)
        parts = []
        for name, m in self.procs.items():
            st = statuses.get((m.robot, m.service))
            mark = (
                "up" if m.alive else "starting" if m.starting else "done" if m.finished else "down"
            )
            extra = ""
            if st is not None and st.pid == (m.proc.pid if m.proc else -1):
                # a stream's first messages, refused while its clock settles, are no news
                bad = sum(n for k, n in st.rejected.items() if k != "settling")
                extra = f" in={st.msgs_in} out={st.msgs_out}" + (f" rejected={bad}" if bad else "")
                progress = st.details.get("progress")
                if progress:
                    extra += f" {progress}"
            parts.append(f"{name}:{mark}{extra}")
        print(f"[{elapsed_s:6.0f} s] " + " | ".join(parts), flush=True)


def profile_path(name: str, parser=None) -> Path:
    """A bundled profile by name, or a TOML file by path."""
    if name.endswith(".toml"):
        return Path(name)
    from importlib import resources

    res = resources.files("smana.deploy").joinpath("profiles", f"{name}.toml")
    if not res.is_file():
        folder = resources.files("smana.deploy").joinpath("profiles")
        known = sorted(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".toml"))
        msg = f"unknown profile {name!r}; known: {', '.join(known)}"
        if parser is not None:
            parser.error(msg)
        raise ValueError(msg)
    return Path(str(res))


def default_run_dir() -> Path:
    return Path("runs") / time.strftime("%Y%m%d-%H%M%S")


def add_recorder(sup: Supervisor) -> bool:
    """Record the run into `<run_dir>/recording.rrd` (one recorder per robot)."""
    try:
        from smana.services.recorder.service import recorder_argv
    except ImportError as exc:  # rerun-sdk missing: the run goes on without a recording
        log.warning("no Rerun recording (%s): pip install rerun-sdk", exc)
        return False
    policy = sup.config.deploy.recorder
    if sup.fleet is not None:  # one recording of the whole fleet, on the base
        if not sup.config.deploy.fleet_base:
            return False
        argv = recorder_argv(sup.config_path, sup.fleet) + list(policy.args)
        if sup.config.zenoh.credentials_file:
            argv += ["--set", f'zenoh.user="{sup.fleet}.recorder"']
        sup.add(f"recorder@{sup.fleet}", argv, policy, service="recorder", robot=sup.fleet)
        return True
    for robot in sup.robots:
        argv = recorder_argv(sup.config_path, robot) + list(policy.args)
        if sup.config.zenoh.credentials_file:
            argv += ["--set", f'zenoh.user="{robot}.recorder"']
        name = "recorder" if len(sup.robots) == 1 else f"recorder@{robot}"
        sup.add(name, argv, policy, service="recorder", robot=robot)
    return True


def _last_line(m: Managed) -> str:
    """The last line a service wrote to its log (a refusal is one line: its reason)."""
    try:
        lines = m.log_path.read_text(errors="replace").strip().splitlines()
    except OSError:
        lines = []
    return lines[-1].strip() if lines else f"exit status {CONFIG_ERROR}, empty log"


def check_optional_needs(config: SmanaConfig, services=None) -> None:
    """A UsageError, before anything starts, when an enabled service needs a package that is not
    installed (`OPTIONAL_NEEDS`), naming the extra that brings it."""
    import importlib.util

    from smana.common.cli import UsageError

    for name, needs in OPTIONAL_NEEDS.items():
        enabled = name in services if services is not None else getattr(config.deploy, name).enabled
        for module, extra in needs if enabled else ():
            if importlib.util.find_spec(module) is None:
                raise UsageError(
                    f"the {name} service needs the {module!r} package, which is not installed: "
                    f"pip install 'smana[{extra}]'"
                )


def main(
    config: SmanaConfig, duration_s: float | None = None, services=None, prog: str = "smana up"
) -> int:
    import shutil

    from smana.common.cli import UsageError, output_dir
    from smana.common.zenoh_config import SessionError
    from smana.deploy.report.finish import RunProgress, finish

    # Refuse what cannot work before the router starts, not halfway through the run.
    if duration_s is not None and not 0 < duration_s < float("inf"):
        raise UsageError(f"--duration must be a number of seconds > 0, got {duration_s:g}")
    check_optional_needs(config, services)
    run_dir = Path(config.general.run_dir) if config.general.run_dir else default_run_dir()
    fresh = not run_dir.exists()
    output_dir(run_dir)
    record = config.deploy.recorder.enabled if services is None else "recorder" in services
    if services is not None:
        services = [s for s in services if s != "recorder"]
    sup = Supervisor(config, run_dir, services)
    if record:
        add_recorder(sup)
    on_stop_signals(lambda _sig: sup.stop())
    print(f"{prog}: run directory {run_dir}", flush=True)
    t0 = time.monotonic()
    try:
        with RunProgress(sup):
            code = sup.run(duration_s)
    except SessionError:
        # The router did not open (its port is taken, ...): nothing ran, so leave no run
        # directory behind unless it was there before.
        if fresh:
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    wall_time_s = time.monotonic() - t0
    if code == CONFIG_ERROR:
        # one line, as for a mistake caught before the start; the logs stay in the run directory
        raise UsageError(f"{sup.config_error} (logs in {run_dir / 'logs'})")
    return finish(sup, run_dir, code, wall_time_s, prog)  # report, summary, exit status


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import positive_float, positive_int

    p = make_parser(
        "smana up",
        "Start the smana stack: router, sim, mapper, navgraph, planner, "
        "explorer; explore until done, then write the run directory.",
    )
    p.add_argument(
        "--profile",
        default="local",
        help="deployment profile: local (default), robot, base, multi-robot, fleet, "
        "fleet-robot, or a TOML file; --config and --set apply on top of it",
    )
    p.add_argument("--only", metavar="A,B", help="start only these services, e.g. mapper,planner")
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--robots",
        type=positive_int,
        metavar="N",
        help="a fleet of N robots r1..rN in one simulated world, sharing one map, one "
        "navigation graph and a coordinator (the same as --set 'fleet.robots=[\"r1\", ...]')",
    )
    args = p.parse_args(argv)
    if args.robots is not None:
        members = ", ".join(f'"r{i + 1}"' for i in range(args.robots))
        args.overrides = [*(args.overrides or []), f"fleet.robots=[{members}]"]
    cfg = config_from_args(args, layers=[profile_path(args.profile, p)])
    from smana.services.mapper.backends import check_backend

    check_backend(cfg.mapper.backend)  # the composition root checks what only a service knows
    setup_logging(cfg.general.log_level, "up")
    services = None
    if args.only:
        services = [s.strip() for s in args.only.split(",") if s.strip()]
        known = (*SERVICE_ORDER, "coordinator", "recorder")
        unknown = [s for s in services if s not in known]
        if unknown:
            p.error(f"unknown service(s) {unknown}; known: {', '.join(known)}")
    return main(cfg, args.duration, services)
