"""`smana bench startup`: how long each service takes from its process's start to being live,
and to its numba kernels being usable: on a cold cache, a warm one, and after a kill -9.

Every service runs as its own process (as under `smana up`), a client of a zenoh router this
benchmark opens on a free loopback port; the times are what a zenoh client sees, from just before
the process is spawned:

- `live`: the service's `alive` liveliness token appears (what the supervisor and the tests wait
  for: it answers its status and its queries);
- `kernels`: its numba kernels are loaded: the first status saying `details.kernels = "ready"`
  (published at once when they are), or the `alive` token for a service whose kernels load
  before it is live.

Three starts per side, in order, on a numba cache of their own (`NUMBA_CACHE_DIR`, a fresh
folder, so the cache of the source tree is left alone) and a cache of built worlds of their own
(`SMANA_WORLD_CACHE`, in the same folder):

- `cold`: every service at once on the empty cache, as the first `smana up` after an install;
- `warm`: all stopped (SIGINT) and started again on the cache the cold start filled;
- `kill`: each service in turn killed with SIGKILL and started again, the others running.

Two sides: `background` (now: kernels compile on a thread of the service, which is live
meanwhile) and `foreground` (`SMANA_KERNELS=foreground`: the order before, kernels then live).
The table gives, per start and service, both sides' live and kernel times and the ratio of the
live times (foreground / background), then the CPU and wall time of the run and the load average.
`imp s` is the part of `live` before the service object exists (Python, imports, config: from its
own `ready_s`); the rest is opening zenoh, `warm_up()` and `setup()` (and, foreground, kernels).
`cpu s` is the CPU time the process had spent when it got live (its status's `ready_cpu_s`: every
thread, imports included): unlike the wall times it hardly depends on what else the machine runs,
and its sum over the services started at once, divided by the cores, is the least wall time in
which they can all be live on an otherwise idle machine.
A service that never becomes live, or whose kernels never load, fails the run (exit status 1).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from smana.common import keys
from smana.common.cli import ArgumentParser, doc_summary, positive_float, run_command
from smana.lab.bench import procs

SERVICES = ("sim", "mapper", "navgraph", "planner", "explorer")
QUICK_SERVICES = ("navgraph",)
SIDES = ("background", "foreground")
STARTS = ("cold", "warm", "kill")
ROBOT = "bench"


class Watch:
    """The router's view: when each service's tokens and kernel-ready status first appear."""

    def __init__(self, session):
        import zenoh

        self._put = zenoh.SampleKind.PUT
        self._lock = threading.Lock()
        self.alive: dict[str, float] = {}
        self.kernels: dict[str, float] = {}
        self.ready_s: dict[str, float] = {}  # the service's own count: Service() to live
        self.ready_cpu_s: dict[str, float] = {}  # its CPU seconds, imports included, when live
        self.pids: dict[str, int] = {}
        self._subs = [
            session.liveliness().declare_subscriber(keys.alive_any(ROBOT), self._on_alive),
            session.declare_subscriber(keys.status_any(ROBOT), self._on_status),
        ]

    def reset(self, service: str) -> None:
        with self._lock:
            self.alive.pop(service, None)
            self.kernels.pop(service, None)
            self.ready_s.pop(service, None)
            self.ready_cpu_s.pop(service, None)

    def _on_alive(self, sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == self._put:
            with self._lock:
                self.alive.setdefault(service, time.monotonic())

    def _on_status(self, sample) -> None:
        from smana.common.messages import MessageError, ServiceStatus, decode

        now = time.monotonic()
        try:
            st = decode(sample.payload.to_bytes(), ServiceStatus)
        except MessageError:
            return
        if st.state != "running" or self.pids.get(st.service) != st.pid:  # (a killed one's)
            return
        with self._lock:
            if "ready_s" in st.details:
                self.ready_s.setdefault(st.service, float(st.details["ready_s"]))
            if "ready_cpu_s" in st.details:
                self.ready_cpu_s.setdefault(st.service, float(st.details["ready_cpu_s"]))
            if st.details.get("kernels", "ready") == "ready":
                self.kernels.setdefault(st.service, now)

    def times(self, service: str) -> tuple[float | None, float | None]:
        with self._lock:
            return self.alive.get(service), self.kernels.get(service)

    def own_ready_s(self, service: str) -> float | None:
        with self._lock:
            return self.ready_s.get(service)

    def own_ready_cpu_s(self, service: str) -> float | None:
        with self._lock:
            return self.ready_cpu_s.get(service)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


class Stack:
    """The service processes of one side, on one numba cache."""

    def __init__(self, endpoint: str, cache: Path, side: str, workdir: Path, watch: Watch):
        self.endpoint, self.cache, self.side, self.workdir = endpoint, cache, side, workdir
        self.watch = watch
        self.procs: dict[str, subprocess.Popen] = {}
        self.t_start: dict[str, float] = {}

    def start(self, service: str) -> None:
        from smana.common.service import KERNELS_ENV
        from smana.services.sim.worlds.cache import ENV as WORLD_CACHE_ENV

        # the sim's built world is cached beside the kernels: cold is cold for both
        env = dict(os.environ, NUMBA_CACHE_DIR=str(self.cache))
        env[WORLD_CACHE_ENV] = str(self.cache / "worlds")
        env[KERNELS_ENV] = self.side
        argv = procs.service_argv(
            service, self.endpoint, ROBOT, "--set", "explorer.time_budget_s=100000"
        )
        self.watch.reset(service)
        self.t_start[service] = time.monotonic()
        log = self.workdir / f"{self.side}-{service}.log"
        proc = procs.spawn(argv, log, env=env, cwd=self.workdir)
        self.watch.pids[service] = proc.pid
        self.procs[service] = proc

    def wait(self, services, timeout_s: float) -> dict[str, dict]:
        """Until every service of `services` is live with its kernels (or `timeout_s`): the
        seconds from each one's spawn to live and to kernels (None: never within the time)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(None not in self.watch.times(s) for s in services):
                break
            if any(self.procs[s].poll() is not None for s in services):
                break
            time.sleep(0.01)
        out = {}
        for s in services:
            alive, kernels = self.watch.times(s)
            t0 = self.t_start[s]
            own = self.watch.own_ready_s(s)
            out[s] = {
                # spawn to Service(): Python, imports, config (the rest is zenoh and state)
                "imports_s": None if alive is None or own is None else alive - t0 - own,
                "live_s": None if alive is None else alive - t0,
                "cpu_s": self.watch.own_ready_cpu_s(s),
                "kernels_s": None if kernels is None else max(kernels, alive or 0) - t0,
                "exit": self.procs[s].poll(),
            }
        return out

    def kill(self, service: str) -> None:
        procs.kill(self.procs[service])

    def stop(self) -> None:
        procs.stop(self.procs.values(), timeout_s=15)


def run_side(side: str, services, endpoint: str, watch: Watch, out: Path, timeout_s: float):
    """Cold, warm and kill starts of `services` on a fresh numba cache."""
    cache = out / f"numba-cache-{side}"
    cache.mkdir()
    stack = Stack(endpoint, cache, side, out, watch)
    res: dict[str, dict] = {}
    try:
        for start in ("cold", "warm"):
            print(f"  {side}: {start} start of {', '.join(services)}", flush=True)
            for s in services:
                stack.start(s)
            res[start] = stack.wait(services, timeout_s)
            if start == "cold":
                stack.stop()
        res["kill"] = {}
        for s in services:
            print(f"  {side}: kill -9 and restart {s}", flush=True)
            stack.kill(s)
            stack.start(s)
            res["kill"] |= stack.wait([s], timeout_s)
    finally:
        stack.stop()
    return res


def _fmt(x: float | None) -> str:
    return f"{x:8.2f}" if x is not None else f"{'never':>8}"


def print_table(results: dict, services) -> bool:
    """The table, then per start of all at once the slowest live and the CPU they spent to get
    live; False when a service was never live or its kernels never loaded."""
    sides = list(results)
    head = f"{'start':<6}{'service':<10}"
    for side in sides:
        s4 = side[:4]
        head += f"{s4 + ' imp s':>12}{s4 + ' live s':>13}{s4 + ' kern s':>13}{s4 + ' cpu s':>12}"
    if len(sides) == 2:
        head += f"{'live ratio':>12}"
    print(head)
    ok = True
    for start in STARTS:
        for s in services:
            row = f"{start:<6}{s:<10}"
            lives = []
            for side in sides:
                r = results[side].get(start, {}).get(s) or {}
                live, kern, imp = r.get("live_s"), r.get("kernels_s"), r.get("imports_s")
                ok &= live is not None and kern is not None
                row += f"{_fmt(imp):>12}{_fmt(live):>13}{_fmt(kern):>13}{_fmt(r.get('cpu_s')):>12}"
                lives.append(live)
            if len(sides) == 2 and None not in lives:
                row += f"{lives[1] / lives[0]:>11.1f}x"
            print(row)
    cores = os.cpu_count() or 1
    for side in sides:
        for start in ("cold", "warm"):
            rows = [results[side].get(start, {}).get(s) or {} for s in services]
            lives = [r.get("live_s") for r in rows]
            cpus = [r.get("cpu_s") for r in rows]
            if None in lives or None in cpus:
                continue
            print(
                f"{side} {start}: all {len(services)} live in {max(lives):.2f} s; they spent "
                f"{sum(cpus):.2f} s of CPU to get there, {sum(cpus) / cores:.2f} s on {cores} "
                "cores with nothing else running"
            )
    return ok


def cli(argv: list[str] | None = None) -> int:
    p = ArgumentParser(
        prog="smana bench startup",
        description=doc_summary(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Duration measured once on a 2-core machine: about 3 minutes by default (two "
        "sides, each a cold\n"
        "start of the whole stack); --quick (one service) well under a minute.",
    )
    p.add_argument(
        "--services",
        default=",".join(SERVICES),
        help=f"services to start, comma-separated (default {','.join(SERVICES)})",
    )
    p.add_argument("--only", choices=SIDES, help="run one side only")
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=600.0,
        metavar="S",
        help="give up on a start after S seconds",
    )
    p.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK_SERVICES)}")
    p.add_argument("--out", type=Path, help="JSON result file (default: in a temporary folder)")
    args = p.parse_args(argv)
    services = QUICK_SERVICES if args.quick else tuple(args.services.split(","))
    unknown = [s for s in services if s not in SERVICES]
    if unknown:
        p.error(f"unknown service {unknown[0]!r} (one of {', '.join(SERVICES)})")
    sides = SIDES if args.only is None else (args.only,)

    import zenoh

    from smana.common.zenoh_config import free_loopback_port
    from smana.deploy.router import router_config

    out = Path(tempfile.mkdtemp(prefix="smana-bench-startup-"))
    load0 = os.getloadavg()
    print(
        f"smana bench startup: {', '.join(services)}; load average {load0[0]:.2f} "
        f"{load0[1]:.2f} {load0[2]:.2f} at start; logs and caches in {out}",
        flush=True,
    )
    t0 = time.monotonic()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    results: dict[str, dict] = {}
    with zenoh.open(router_config([endpoint])) as session:
        watch = Watch(session)
        try:
            for side in sides:
                results[side] = run_side(side, services, endpoint, watch, out, args.timeout)
        finally:
            watch.close()
    wall = time.monotonic() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime
    load = os.getloadavg()
    print()
    ok = print_table(results, services)
    print(
        f"\nwall {wall:.0f} s, CPU {cpu:.0f} s (service processes), load average "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} at the end",
        flush=True,
    )
    doc = {"services": list(services), "results": results, "wall_s": wall, "cpu_s": cpu}
    doc |= {"loadavg_start": load0, "loadavg_end": load}
    path = args.out or out / "startup.json"
    Path(path).write_text(json.dumps(doc, indent=1))
    print(f"results: {path}")
    if not ok:
        print(f"FAILED: a service never got live or its kernels never loaded (logs in {out})")
    return 0 if ok else 1


def main() -> int:
    return run_command("bench startup", cli)


if __name__ == "__main__":
    sys.exit(main())
