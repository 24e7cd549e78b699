"""`smana bench restart`: how long a service killed with -9 under `smana up` stays down, and
whether the map survives it.

The whole stack runs under the supervisor (router, sim, mapper, navgraph, planner, explorer; the
default config, with a long exploration budget so the run outlasts the benchmark). Each service is
killed with SIGKILL in turn, `--kills` times; the time back is from the kill to the service's
`alive` liveliness token coming back (a new process, ready: kernels loaded, map resumed, inputs
declared), as a zenoh client of the stack sees it. Before each mapper kill the benchmark saves the
map (`mapper/save`, so the autosave period does not blur the figure) and checks that the
restarted mapper holds at least the voxels the saved map had observed.

The same sequence runs twice, side by side: with the hot spare (`deploy.<service>.standby`, the
default) and with a plain respawn (what systemd or supervisord would do: start the process
again). The table gives the median and maximum time back per service for each, their ratio, and
the CPU and wall time and load average of the run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

from smana.common import keys
from smana.common import progress as bars
from smana.common.cli import ArgumentParser, doc_summary, positive_float, positive_int, run_command
from smana.common.config import SmanaConfig
from smana.common.messages import ServiceStatus
from smana.common.query import QueryError, request

SERVICES = ("sim", "mapper", "navgraph", "planner", "explorer")


def _config(port: int, standby: bool, overrides: list[str]) -> SmanaConfig:
    sets = [
        f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
        "deploy.recorder.enabled=false",
        "explorer.time_budget_s=100000",
        "general.robot=bench",
        "deploy.standby_delay_s=0",  # spares at once: the kills come every few seconds
        *[f"deploy.{s}.standby={'true' if standby else 'false'}" for s in SERVICES],
        *overrides,
    ]
    return SmanaConfig.load(None, sets)


class Watch:
    """A client of the stack: alive tokens as they come and go, and status queries."""

    def __init__(self, session, robot: str):
        import zenoh

        self.session, self.robot = session, robot
        self.up: dict[str, float] = {}  # service -> when its token last appeared
        self._lock = threading.Lock()
        self._kind = zenoh.SampleKind
        self.sub = session.liveliness().declare_subscriber(
            keys.alive_any(robot), self._on, history=True
        )

    def _on(self, sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == self._kind.PUT:
                self.up[service] = time.monotonic()
            else:
                self.up.pop(service, None)

    def alive_since(self, service: str) -> float | None:
        with self._lock:
            return self.up.get(service)

    def status(self, service: str) -> ServiceStatus | None:
        try:
            st = request(self.session, keys.status(self.robot, service), timeout_s=2.0)
        except QueryError:
            return None
        return st if isinstance(st, ServiceStatus) else None

    def query(self, service: str, name: str, body=None):
        try:
            return request(self.session, keys.query(self.robot, service, name), body, 5.0)
        except QueryError:
            return None


def _wait(pred, timeout_s: float, step_s: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step_s)
    return False


def run_once(
    standby: bool, kills: int, settle_s: float, overrides: list[str], out: Path, progress
) -> dict:
    """One stack, every service killed `kills` times; the times back and the map checks."""
    import zenoh

    from smana.common.config import ZenohConfig
    from smana.common.zenoh_config import free_loopback_port, make_zenoh_config
    from smana.deploy.supervisor import Supervisor

    port = free_loopback_port()
    cfg = _config(port, standby, overrides)
    run_dir = out / ("standby" if standby else "respawn")
    sup = Supervisor(cfg, run_dir)
    thread = threading.Thread(target=sup.run, kwargs={"progress_period_s": 1e9}, daemon=True)
    thread.start()
    result: dict = {"standby": standby, "back_s": {s: [] for s in SERVICES}, "map": []}
    try:
        zc = ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"])
        if not _wait(lambda: sup.session is not None, 60):
            raise RuntimeError("the stack's router did not open")
        with zenoh.open(make_zenoh_config(zc)) as session:
            w = Watch(session, "bench")
            if not _wait(lambda: all(w.alive_since(s) for s in SERVICES), 600):
                raise RuntimeError(f"the stack did not come up: {sorted(w.up)}")
            if standby and not _wait(
                lambda: all(sup.spare_ready(m) for m in sup.procs.values()), 300
            ):
                raise RuntimeError("the standby processes did not get ready")
            time.sleep(settle_s)  # let the map grow a little
            for k in range(kills):
                for service in SERVICES:
                    m = sup.procs[service]
                    if m.proc is None or m.finished:
                        continue
                    if service == "mapper":  # what the saved map holds
                        before = w.query("mapper", "save") or {}
                    pid = m.proc.pid
                    t_kill = time.monotonic()
                    os.kill(pid, signal.SIGKILL)
                    back = _wait(lambda s=service, t=t_kill: (w.alive_since(s) or 0) > t, 120)
                    if not back:
                        raise RuntimeError(f"{service} did not come back within 120 s")
                    result["back_s"][service].append(w.alive_since(service) - t_kill)
                    if service == "mapper":
                        after = w.query("mapper", "stats") or {}
                        result["map"].append(
                            {
                                "voxels_before": before.get("voxels_observed"),
                                "voxels_after": after.get("voxels_observed"),
                            }
                        )
                    progress(standby, k, service, result["back_s"][service][-1])
                    # the next kill finds the stack whole again (a spare ready, when used)
                    _wait(lambda m=m: not standby or sup.spare_ready(m), 120)
                    time.sleep(settle_s)
            w.sub.undeclare()
    finally:
        sup.stop()
        thread.join(60)
    return result


def _summary(r: dict) -> dict:
    return {
        s: {"median_s": statistics.median(v), "max_s": max(v), "n": len(v)} if v else None
        for s, v in r["back_s"].items()
    }


def cli(argv: list[str] | None = None) -> int:
    p = ArgumentParser(
        prog="smana bench restart",
        description=doc_summary(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Duration measured once on a 2-core machine: about 5 minutes by default (5 kills "
        "per service,\n"
        "standby and respawn). A progress bar with an ETA shows on a terminal\n"
        "(SMANA_PROGRESS=1 forces it, 0 hides it).",
    )
    p.add_argument("--kills", type=positive_int, default=5, help="kills per service")
    p.add_argument(
        "--settle",
        type=positive_float,
        default=3.0,
        metavar="S",
        help="seconds between kills (the stack works meanwhile)",
    )
    p.add_argument("--only", choices=["standby", "respawn"], help="run one variant only")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="config override for the stack",
    )
    p.add_argument("--out", type=Path, help="JSON result file (default: a temporary folder)")
    args = p.parse_args(argv)
    variants = [True, False] if args.only is None else [args.only == "standby"]
    out = Path(tempfile.mkdtemp(prefix="smana-bench-restart-"))
    total = args.kills * len(SERVICES) * len(variants)
    done = [0]
    t0 = time.monotonic()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    self0 = resource.getrusage(resource.RUSAGE_SELF)

    bar = None  # drawn once the heading is out

    def progress(standby, k, service, back_s):
        done[0] += 1
        eta = (time.monotonic() - t0) / done[0] * (total - done[0])
        bars.say(
            f"[{done[0]:3d}/{total}] {'standby' if standby else 'respawn':<8} kill {k + 1} "
            f"{service:<9} back in {back_s:5.2f} s   (ETA {eta:4.0f} s)"
        )
        bar.update()

    print(
        f"smana bench restart: {args.kills} kills per service, load average "
        f"{os.getloadavg()[0]:.2f} at start; run dirs in {out}",
        flush=True,
    )
    bar = bars.bar(total, "bench restart", unit="kill")
    results = [
        run_once(v, args.kills, args.settle, args.overrides, out, progress) for v in variants
    ]
    bar.close()
    wall = time.monotonic() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    self1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (
        cpu1.ru_utime
        + cpu1.ru_stime
        - cpu0.ru_utime
        - cpu0.ru_stime
        + self1.ru_utime
        + self1.ru_stime
        - self0.ru_utime
        - self0.ru_stime
    )
    load = os.getloadavg()
    summaries = {("standby" if r["standby"] else "respawn"): _summary(r) for r in results}
    print()
    print(
        f"{'service':<10}"
        + "".join(f"{v + ' median':>16}{v + ' max':>14}" for v in summaries)
        + (f"{'ratio':>8}" if len(summaries) == 2 else "")
    )
    failed = False
    for s in SERVICES:
        row = f"{s:<10}"
        med = []
        for v in summaries.values():
            x = v.get(s)
            row += f"{x['median_s']:>15.2f}s{x['max_s']:>13.2f}s" if x else f"{'-':>16}{'-':>14}"
            med.append(x["median_s"] if x else None)
        if len(med) == 2 and all(med):
            row += f"{med[1] / med[0]:>7.1f}x"
        print(row)
    for r in results:
        for i, mp in enumerate(r["map"]):
            lost = (mp["voxels_before"] or 0) - (mp["voxels_after"] or 0)
            ok = mp["voxels_after"] is not None and lost <= 0
            failed |= not ok
            print(
                f"map {'standby' if r['standby'] else 'respawn'} kill {i + 1}: "
                f"{mp['voxels_before']} observed voxels saved before, {mp['voxels_after']} after"
                f"{'' if ok else '  LOST'}"
            )
    print(
        f"\nwall {wall:.0f} s, CPU {cpu:.0f} s (all processes), load average "
        f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}",
        flush=True,
    )
    doc = {
        "kills": args.kills,
        "results": results,
        "summary": summaries,
        "wall_s": wall,
        "cpu_s": cpu,
        "loadavg": load,
    }
    path = args.out or out / "restart.json"
    Path(path).write_text(json.dumps(doc, indent=1))
    print(f"results: {path}")
    if failed:
        print("FAILED: the map lost voxels across a restart", file=sys.stderr)
    return 1 if failed else 0


def main() -> int:
    return run_command("bench restart", cli)


if __name__ == "__main__":
    sys.exit(main())
