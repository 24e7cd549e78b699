"""`smana up`: the supervisor that starts the whole stack and keeps it running.

It opens a zenoh router in its own process (a Python session in router mode on loopback, so no
zenohd is needed), writes the config it uses into the run directory, and starts each enabled
service as its own OS process (own process group, log file in `<run_dir>/logs/`),
connected to that router.

Per service, dora's vocabulary: a restart policy (`never`, `on-failure`, `always`), a restart delay
that doubles up to a cap, a maximum number of restarts in a window (then the service is given up),
and health from the liveliness token `smana/<robot>/alive/<service>`: a service that has not shown
its token `health_timeout_s` after it started, or whose token vanished while its process still
runs, is killed and restarted.

The run ends when the service named by `deploy.finish_with` exits with status 0 (the explorer, when
exploration is done), after `--duration`, or on Ctrl-C; every service then gets SIGINT, and SIGKILL
after `deploy.stop_timeout_s`.
"""

from __future__ import annotations

import collections
import dataclasses
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
from smana.common.config import ServiceDeployConfig, SmanaConfig
from smana.common.messages import MessageError, ServiceStatus, decode
from smana.common.service import die_with_parent, on_stop_signals

log = logging.getLogger("smana.up")

# Start order follows the data flow: producers first, so consumers find their inputs.
SERVICE_ORDER = ("sim", "mapper", "navgraph", "planner", "explorer")


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
    alive: bool = False  # its liveliness token is up
    seen_alive: bool = False  # the token came up at least once since the last start
    lost_at: float | None = None  # when the token vanished while the process still ran
    restarts: collections.deque = field(default_factory=collections.deque)
    next_start: float = 0.0
    given_up: bool = False
    finished: bool = False  # exited and will not be restarted
    exit_codes: list[int] = field(default_factory=list)


class Supervisor:
    def __init__(self, config: SmanaConfig, run_dir: Path, services: list[str] | None = None):
        self.config = config
        self.run_dir = Path(run_dir).resolve()
        self.robot = config.general.robot
        self.robots = list(config.deploy.robots) or [self.robot]
        names = services if services is not None else [
            n for n in SERVICE_ORDER if getattr(config.deploy, n).enabled
        ]  # fmt: skip
        self.logs = self.run_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        # Every service is a client of our router (its first listen endpoint): rewrite [zenoh] so
        # the config file written into the run dir is exactly what they run with.
        self.service_config = dataclasses.replace(
            config,
            general=dataclasses.replace(config.general, run_dir=str(self.run_dir)),
            zenoh=dataclasses.replace(
                config.zenoh, mode="client", connect=config.deploy.router_listen[:1], listen=[]
            ),
        )
        self.config_path = self.service_config.write(self.run_dir / "config.toml")
        self.procs: dict[str, Managed] = {}
        for robot in self.robots:
            for n in names:
                argv = [sys.executable, "-m", f"smana.services.{n}", "--config",
                        str(self.config_path), "--robot", robot]  # fmt: skip
                if config.zenoh.credentials_file:
                    argv += ["--set", f'zenoh.user="{n}"']  # each service logs in as itself
                name = n if len(self.robots) == 1 else f"{n}@{robot}"
                policy = getattr(config.deploy, n)
                self.add(name, argv + policy.args, policy, service=n, robot=robot)
        self.statuses: dict[tuple[str, str], ServiceStatus] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.session = None

    def add(self, name: str, argv: list[str], policy: ServiceDeployConfig | None = None,
            service: str = "", robot: str = "") -> None:  # fmt: skip
        """Supervise another command (before `start()`): a sensor driver, a user's own node. It
        should declare the liveliness token `smana/<robot>/alive/<service>` as services do."""
        self.procs[name] = Managed(name, list(argv), policy or ServiceDeployConfig(),
                                   self.logs / f"{name}.log", service or name,
                                   robot or self.robot)  # fmt: skip

    # -- process control ---------------------------------------------------------------------------

    def _spawn(self, m: Managed) -> None:
        logf = open(m.log_path, "ab")  # noqa: SIM115 - the child owns it; closed below
        logf.write(f"\n--- start {time.strftime('%H:%M:%S')}: {' '.join(m.argv)}\n".encode())
        logf.flush()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        m.proc = subprocess.Popen(
            m.argv, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, env=env, preexec_fn=die_with_parent,
        )  # fmt: skip
        # Children keep the supervisor's working directory, so relative paths in the config
        # (certificates, maps, worlds) mean the same to every process.
        logf.close()
        m.started_at = time.monotonic()
        m.seen_alive = False
        m.lost_at = None
        log.info("started %s (pid %d)", m.name, m.proc.pid)

    def _signal(self, m: Managed, sig: int) -> None:
        if m.proc is not None and m.proc.poll() is None:
            try:
                os.killpg(m.proc.pid, sig)
            except ProcessLookupError:
                pass

    def _schedule_restart(self, m: Managed, why: str) -> None:
        now = time.monotonic()
        window = m.policy.restart_window_s
        while m.restarts and now - m.restarts[0] > window:
            m.restarts.popleft()
        if len(m.restarts) >= m.policy.max_restarts:
            m.given_up = m.finished = True
            log.error(
                "%s %s; %d restarts in %.0f s: giving up on it (see %s)",
                m.name, why, len(m.restarts), window, m.log_path,
            )  # fmt: skip
            return
        delay = min(m.policy.restart_delay_s * 2 ** len(m.restarts), m.policy.restart_max_delay_s)
        m.restarts.append(now)
        m.next_start = now + delay
        log.warning("%s %s; restarting in %.1f s (see %s)", m.name, why, delay, m.log_path)

    def poll(self) -> None:
        """One supervision step: reap exits, apply restart policies, check health."""
        now = time.monotonic()
        for m in self.procs.values():
            if m.finished:
                continue
            if m.proc is None:
                if now >= m.next_start:
                    self._spawn(m)
                continue
            code = m.proc.poll()
            if code is not None:
                m.exit_codes.append(code)
                m.proc = None
                with self._lock:
                    m.alive = False
                failed = code != 0
                if m.policy.restart == "always" or (m.policy.restart == "on-failure" and failed):
                    self._schedule_restart(m, f"exited with status {code}")
                else:
                    m.finished = True
                    level = logging.WARNING if failed else logging.INFO
                    log.log(level, "%s exited with status %d", m.name, code)
                continue
            with self._lock:
                alive, seen = m.alive, m.seen_alive
            age = now - m.started_at
            if not seen and age > self.config.deploy.health_timeout_s:
                log.warning("%s showed no liveliness token after %.0f s: killing it", m.name, age)
                self._signal(m, signal.SIGKILL)
            elif seen and not alive:
                # A service that stops on its own undeclares its token first and then flushes
                # its state: only a process still running well after that is hung.
                if m.lost_at is None:
                    m.lost_at = now
                elif now - m.lost_at > self.config.deploy.stop_timeout_s:
                    log.warning("%s lost its liveliness token %.0f s ago, still runs: killing it",
                                m.name, now - m.lost_at)  # fmt: skip
                    self._signal(m, signal.SIGKILL)
            else:
                m.lost_at = None

    def _find(self, robot: str, service: str) -> Managed | None:
        for m in self.procs.values():
            if m.robot == robot and m.service == service:
                return m
        return None

    def _on_liveliness(self, sample) -> None:
        parts = str(sample.key_expr).split("/")
        m = self._find(parts[1], parts[3]) if len(parts) == 4 else None
        if m is None:
            return
        import zenoh

        with self._lock:
            m.alive = sample.kind == zenoh.SampleKind.PUT
            m.seen_alive = m.seen_alive or m.alive

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
        self.session = open_router(d.router_listen, self.config.zenoh, d.router_connect)
        endpoints = ", ".join(d.router_listen)
        log.info("zenoh router listening on %s; run directory %s", endpoints, self.run_dir)
        if d.router_connect:
            log.info("linking to router(s) %s", ", ".join(d.router_connect))
        ll = self.session.liveliness()
        self._subs = [
            ll.declare_subscriber(keys.alive_any("*"), self._on_liveliness, history=True),
            self.session.declare_subscriber(keys.status_any("*"), self._on_status),
        ]
        for m in self.procs.values():
            self._spawn(m)

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        """SIGINT every service, wait, SIGKILL what is left, close the router."""
        running = [m for m in self.procs.values() if m.proc is not None]
        # Stop in reverse data-flow order: the explorer stops driving before the sim goes away.
        for m in reversed(running):
            self._signal(m, signal.SIGINT)
        deadline = time.monotonic() + self.config.deploy.stop_timeout_s
        for m in reversed(running):
            try:
                m.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s: killing it", m.name,
                            self.config.deploy.stop_timeout_s)  # fmt: skip
                self._signal(m, signal.SIGKILL)
                m.proc.wait()
            m.exit_codes.append(m.proc.returncode)
            m.proc = None
        for s in getattr(self, "_subs", []):
            s.undeclare()
        if self.session is not None:
            self.session.close()
            self.session = None

    def run(self, duration_s: float | None = None, progress_period_s: float = 10.0) -> int:
        """Supervise until done; returns 0 when the run finished normally."""
        self.start()
        t0 = time.monotonic()
        next_progress = t0 + progress_period_s
        finish_with = self.config.deploy.finish_with
        result = 0
        try:
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
                    log.info("%s finished (status %s): stopping the stack", finish_with,
                             ", ".join(map(str, codes)))  # fmt: skip
                    break
                if self.procs and all(m.finished for m in self.procs.values()):
                    log.error("every service has exited")
                    result = 1
                    break
                if duration_s is not None and now - t0 >= duration_s:
                    log.info("duration of %.0f s reached: stopping the stack", duration_s)
                    break
        finally:
            self.shutdown()
        return result

    def print_progress(self, elapsed_s: float) -> None:
        with self._lock:
            statuses = dict(self.statuses)
        parts = []
        for name, m in self.procs.items():
            st = statuses.get((m.robot, m.service))
            mark = "up" if m.alive else ("done" if m.finished else "down")
            extra = ""
            if st is not None:
                errs = sum(st.errors.values())
                extra = f" in={st.msgs_in} out={st.msgs_out}" + (f" err={errs}" if errs else "")
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
        from smana.deploy.recording import recorder_argv
    except ImportError as exc:  # rerun-sdk missing: the run goes on without a recording
        log.warning("no Rerun recording (%s): pip install rerun-sdk", exc)
        return False
    policy = sup.config.deploy.recorder
    for robot in sup.robots:
        argv = recorder_argv(sup.config_path, robot) + list(policy.args)
        if sup.config.zenoh.credentials_file:
            argv += ["--set", 'zenoh.user="recorder"']
        name = "recorder" if len(sup.robots) == 1 else f"recorder@{robot}"
        sup.add(name, argv, policy, service="recorder", robot=robot)
    return True


def main(config: SmanaConfig, duration_s: float | None = None, services=None) -> int:
    import shutil

    from smana.common.cli import UsageError, output_dir
    from smana.common.zenoh_config import SessionError

    # Refuse what cannot work before the router starts, not halfway through the run.
    if duration_s is not None and not 0 < duration_s < float("inf"):
        raise UsageError(f"--duration must be a number of seconds > 0, got {duration_s:g}")
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
    print(f"smana up: run directory {run_dir}", flush=True)
    try:
        code = sup.run(duration_s)
    except SessionError:
        # The router did not open (its port is taken, ...): nothing ran, so leave no run
        # directory behind unless it was there before.
        if fresh:
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    try:
        from smana.deploy import report
    except ModuleNotFoundError:
        report = None
    if report is not None and hasattr(report, "write_report"):
        try:
            path = report.write_report(run_dir, sup.service_config)
            print(f"smana up: report written to {path}", flush=True)
        except Exception as exc:  # a failed report must not hide the run's own outcome
            log.exception("writing the report failed: %s", exc)
    print(f"smana up: done, everything is in {run_dir}", flush=True)
    return code


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import positive_float

    p = make_parser("smana up", "Start the smana stack: router, sim, mapper, navgraph, planner, "
                    "explorer; explore until done, then write the run directory.")  # fmt: skip
    p.add_argument("--profile", default="local",
                   help="deployment profile: local (default), robot, base, multi-robot, or a "
                        "TOML file; --config and --set apply on top of it")  # fmt: skip
    p.add_argument("--only", metavar="A,B", help="start only these services, e.g. mapper,planner")
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    args = p.parse_args(argv)
    cfg = config_from_args(args, layers=[profile_path(args.profile, p)])
    setup_logging(cfg.general.log_level, "up")
    services = None
    if args.only:
        services = [s.strip() for s in args.only.split(",") if s.strip()]
        known = (*SERVICE_ORDER, "recorder")
        unknown = [s for s in services if s not in known]
        if unknown:
            p.error(f"unknown service(s) {unknown}; known: {', '.join(known)}")
    return main(cfg, args.duration, services)
