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

import dataclasses
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from smana.common import keys, service_table
from smana.common.cli import config_from_args, make_parser, setup_logging
from smana.common.config import ConfigError, ServiceDeployConfig, SmanaConfig
from smana.common.messages import MessageError, ServiceStatus, decode
from smana.common.service import die_with_parent, on_stop_signals
from smana.deploy.fleet import add_fleet
from smana.deploy.outcome import CONFIG_ERROR, Outcome, last_line
from smana.deploy.processes import Managed, ProcessControl

__all__ = ["CONFIG_ERROR", "Managed", "Supervisor", "cli", "die_with_parent", "main"]

log = logging.getLogger("smana.up")

# Start order follows the data flow, producers first so consumers find their inputs, and the
# fleet's layout (FLEET_SHARED on the base, FLEET_MEMBER per member): both from the table of
# services (common/service_table.py), as everything else that lists services.
SERVICE_ORDER = service_table.start_order()
FLEET_SHARED = service_table.fleet("shared")
FLEET_MEMBER = service_table.fleet("member")
# What a service needs beyond smana's own dependencies (the table's `requires`: the module and
# the extra that installs it). A missing one stops `smana up` before anything starts, in one line
# (exit 2), instead of a service that exits 2 at every restart.
OPTIONAL_NEEDS = {r.name: r.requires for r in service_table.supervised() if r.requires}


def _row(name: str) -> service_table.ServiceRow:
    row = service_table.row(name)
    if row is None:
        raise ConfigError(f"unknown service {name!r} (known: {', '.join(service_table.names())})")
    return row


class Supervisor(ProcessControl, Outcome):
    """Starts the services of one host, watches their health, restarts them by their policy
    (deploy/processes.py), and says at the end what went wrong (deploy/outcome.py)."""

    def __init__(self, config: SmanaConfig, run_dir: Path, services: list[str] | None = None):
        self.config = config
        self.run_dir = Path(run_dir).resolve()
        self.robot = config.general.robot
        self.robots = list(config.deploy.robots) or [self.robot]
        names = (
            services
            if services is not None
            else [n for n in SERVICE_ORDER if getattr(config.deploy, n).enabled]
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
            names = [n for n in names if not _row(n).fleet_only]  # the coordinator: a fleet's
        else:
            add_fleet(self, names)
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
            _row(service).module,
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
                    self.config_error = f"{m.name} refused its configuration: {last_line(m)}"
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
        if d.ros2.enabled and not zc.acl_file:
            # ROS 2 nodes are peers that find each other through the router. Not under access
            # control: gossip would tell each peer where the others listen, and two peers linked
            # directly exchange what the router's policy would refuse (docs/ros2.md).
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
        last = [m for m in running if service_table.stops_last(m.service)]
        for wave in ([m for m in running if m not in last], last):
            self._stop_wave(wave)
        for s in getattr(self, "_subs", []):
            s.undeclare()
        if self.session is not None:
            self.session.close()
            self.session = None

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
        known = [r.name for r in service_table.supervised()]
        unknown = [s for s in services if s not in known]
        if unknown:
            p.error(f"unknown service(s) {unknown}; known: {', '.join(known)}")
    return main(cfg, args.duration, services)
