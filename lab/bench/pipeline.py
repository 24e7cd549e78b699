"""`smana bench pipeline`: scan published -> updated path available, at the LiDAR's 10 Hz.

A zenoh router (in this process, on its own loopback port, no scouting) and the mapper, navgraph,
planner and replay services as their own processes (`lab/bench/replay.py::Stack`); the replay
publishes the synthetic 131,072-point OS1-64-like sequence in realtime (10 Hz; the first scan
primes the stack, as in `smana bench replay`). Per scan, in milliseconds:

- map: scan published -> its MapDelta back (the replay's own clock, publish to acknowledgement);
- graph: MapDelta -> the GraphPatch it caused (arrivals at this process, matched by stamp);
- path: GraphPatch -> a path query answered on that graph version or a newer one. A planner
  stats query goes just before each path query on the same session; the planner answers its
  FIFO in order, so when the stats say `last_patch_seq >= N`, the path after it was planned on
  patch N. The query is first pose -> current pose, unknown space allowed;
- end to end: the sum, i.e. scan published -> updated path available.

p50 / p95 / p99 / max over the scans after the first (which loads every kernel), and the drops:
scans published, integrated (MapDeltas), stale or lost at the mapper, deltas and patches each next
service received, from the replay's summary and the services' status books. CPU per stage is
each process's CPU time (psutil, user + system) over the replay, per scan and as a share of one
core. `--pin` sets each process's cores (`os.sched_setaffinity`, inherited at fork): by default one
core per service when there are four or more; on two, the chain (mapper, navgraph, planner: a
scan passes through them one after the other) on one core and the replay on the other.

Exit status 1 when a scan was dropped or lost, a stage failed (no MapDelta, no patch or path
for a scan that changed the graph), or a service's books say it dropped a message (other than a
start-up sync answered `warming_up` while its kernels loaded, which the asker repeats).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.cli import doc_summary
from smana.lab.bench.replay import Stack, stack_settings

E2E_TARGET_MS = 100.0
E2E_GOAL_P99_MS = 30.0  # issue 30's goal for 131k-point scans; reported, the exit code ignores it
SERVICES = ("mapper", "navgraph", "planner")
QUICK = {"scans": 20, "beams": 16, "columns": 512}


class PathProbe:
    """Arrivals of MapDeltas and GraphPatches, and path queries on each new graph version."""

    def __init__(self, session, robot: str):
        from smana.common import keys

        self.session, self.robot = session, robot
        self.deltas: dict[int, tuple[float, float]] = {}  # cloud_seq -> (stamp, arrival)
        self.patches: dict[int, tuple[float, float]] = {}  # patch seq -> (stamp, arrival)
        self.answered: dict[int, float] = {}  # patch seq -> first path answered on it
        self.replies: list[dict] = []
        self.first_pose: tuple[float, float] | None = None
        self.pose: tuple[float, float] | None = None
        self._new = queue.Queue()
        self._stop = threading.Event()
        self._stats_key = keys.query(robot, "planner", "stats")
        self._path_key = keys.path_query(robot)
        self._subs = [
            session.declare_subscriber(keys.map_delta(robot), self._on_delta),
            session.declare_subscriber(keys.graph_patch(robot), self._on_patch),
            session.declare_subscriber(keys.pose(robot), self._on_pose),
        ]
        self._thread = threading.Thread(target=self._ask, daemon=True)
        self._thread.start()

    def _on_delta(self, sample) -> None:
        import msgpack

        now = time.monotonic()
        head = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        self.deltas.setdefault(int(head["cloud_seq"]), (float(head["stamp_s"]), now))

    def _on_patch(self, sample) -> None:
        import msgpack

        now = time.monotonic()
        head = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        seq = int(head["seq"])
        self.patches[seq] = (float(head["stamp_s"]), now)
        self._new.put(seq)

    def _on_pose(self, sample) -> None:
        from smana.common.messages import Pose, decode

        p = decode(sample.payload.to_bytes(), Pose)
        xy = (float(p.position[0]), float(p.position[1]))
        if self.first_pose is None:
            self.first_pose = xy
        self.pose = xy

    def _ask(self) -> None:
        """Whenever a patch came: stats then path, both in flight at once, until the stats say
        the planner held the newest patch when it planned."""
        import msgpack

        from smana.common.messages import PathReply, PathRequest, decode, encode

        n = 0
        while not self._stop.is_set():
            try:
                want = self._new.get(timeout=0.2)
            except queue.Empty:
                continue
            while not self._new.empty():  # a newer patch answers the older ones too
                want = max(want, self._new.get_nowait())
            while not self._stop.is_set() and self.pose is not None:
                n += 1
                req = PathRequest(
                    request_id=f"pipeline{n}",
                    start=np.array(self.first_pose),
                    goal=np.array(self.pose),
                    allow_unknown=True,
                )
                t0 = time.monotonic()
                stats = self.session.get(self._stats_key, timeout=5.0)
                path = self.session.get(self._path_key, payload=encode(req), timeout=5.0)
                held = -1
                for r in stats:
                    if r.ok is not None:
                        held = int(msgpack.unpackb(r.ok.payload.to_bytes())["last_patch_seq"])
                reply = None
                for r in path:
                    if r.ok is not None:
                        reply = decode(r.ok.payload.to_bytes(), PathReply)
                t1 = time.monotonic()
                if reply is None:
                    self.replies.append({"ok": False, "error": "no reply", "wall_ms": 0.0})
                    break
                self.replies.append(
                    {
                        "ok": bool(reply.ok),
                        "error": reply.error,
                        "wall_ms": (t1 - t0) * 1000.0,
                        "planner_ms": float(reply.time_ms),
                        "patch_seq": held,
                        "want": want,
                    }
                )
                for seq in range(1, held + 1):
                    self.answered.setdefault(seq, t1)
                if held >= want:
                    break
                time.sleep(0.001)  # the planner has not applied the patch yet

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=6)
        for s in self._subs:
            s.undeclare()


def pin_plan(how: str) -> dict[str, set[int]]:
    """Cores per process. `auto`: with four cores or more, one each for mapper, navgraph and
    planner, the replay on the rest; with fewer, `chain`. `chain`: mapper, navgraph and planner
    (a scan passes through them one after the other) on the first core, the replay (the sensor,
    reading and encoding the next scans) on the others. `mapper`: the mapper alone on the first
    core, everything else on the others. `none`: the scheduler's choice."""
    cpus = sorted(os.sched_getaffinity(0))
    if how == "none" or len(cpus) < 2:
        return {}
    first, rest = {cpus[0]}, set(cpus[1:])
    if how == "auto" and len(cpus) >= 4:
        rest = set(cpus[3:])
        return {"mapper": first, "navgraph": {cpus[1]}, "planner": {cpus[2]}, "replay": rest}
    if how == "mapper":
        return {"mapper": first, "navgraph": rest, "planner": rest, "replay": rest}
    return {"mapper": first, "navgraph": first, "planner": first, "replay": rest}


def _start_pinned(stack: Stack, name: str, args: list[str], cores: set[int] | None):
    # A child inherits the affinity of the thread that forks it: set ours, fork, restore.
    if not cores:
        return stack.start(name, args)
    mine = os.sched_getaffinity(0)
    os.sched_setaffinity(0, cores)
    try:
        return stack.start(name, args)
    finally:
        os.sched_setaffinity(0, mine)


def _status(session, robot: str, service: str) -> dict:
    from smana.common import keys
    from smana.common.messages import ServiceStatus
    from smana.common.query import QueryError, request

    try:
        st = request(session, keys.status(robot, service), timeout_s=3.0)
    except QueryError:
        return {}
    if not isinstance(st, ServiceStatus):
        return {}
    return {
        "msgs_in": st.msgs_in,
        "accepted": st.accepted,
        "dropped": dict(st.dropped),
        "rejected": dict(st.rejected),
        "pending": st.pending,
    }


def _cpu_s(proc) -> float:
    t = proc.cpu_times()
    return t.user + t.system


def run_pipeline(dataset: Path, args: argparse.Namespace, out: Path) -> dict:
    """One realtime replay through the whole chain; the raw figures."""
    import psutil

    run_dir = out / "run"
    stack = Stack(run_dir / "logs")
    pins = pin_plan(args.pin)
    mres, gres = args.res
    sets = stack_settings(args.backend, mres, gres, args.table)
    result: dict = {"pins": {k: sorted(v) for k, v in pins.items()}}
    try:
        for s in SERVICES:
            _start_pinned(stack, s, [*sets, "--run-dir", str(run_dir / s)], pins.get(s))
        stack.wait_alive(list(SERVICES))
        probe = PathProbe(stack.session, stack.robot)
        replay_args = [
            str(dataset),
            "--realtime",
            *sets,
            "--run-dir",
            str(run_dir / "replay"),
            "--set",
            f"replay.wait_for={json.dumps(list(SERVICES))}",
        ]
        replay = _start_pinned(stack, "replay", replay_args, pins.get("replay"))
        procs = {s: psutil.Process(stack.procs[s].pid) for s in ("replay", *SERVICES)}
        # CPU and wall count from the first MapDelta: the replay's start-up (imports, reading
        # ahead) and the priming scan are not the pipeline's steady cost.
        cpu0: dict[str, float] = {}
        cpu_end: dict[str, float] = {}
        t0 = None
        while replay.poll() is None:
            if t0 is None and probe.deltas:
                t0 = time.monotonic()
                cpu0 = {s: _cpu_s(p) for s, p in procs.items()}
            try:  # the replay's CPU just before it exits
                cpu_end["replay"] = _cpu_s(procs["replay"])
            except psutil.Error:
                break
            time.sleep(0.02)
        code = replay.wait()
        wall = time.monotonic() - (t0 or time.monotonic())
        time.sleep(0.5)  # the last patch and its path
        probe.close()
        for s in SERVICES:
            cpu_end[s] = _cpu_s(procs[s])
        result["status"] = {s: _status(stack.session, stack.robot, s) for s in SERVICES}
        summary_path = run_dir / "replay" / "replay.json"
        if code != 0 or not summary_path.exists():
            log = (run_dir / "logs" / "replay.log").read_text(errors="replace")[-3000:]
            raise RuntimeError(f"the replay failed ({code}):\n{log}")
        summary = json.loads(summary_path.read_text())
    finally:
        stack.close()
    result.update(
        summary=summary,
        wall_s=wall,
        cpu_s={s: cpu_end.get(s, 0.0) - cpu0.get(s, 0.0) for s in procs},
        deltas=probe.deltas,
        patches=probe.patches,
        answered=probe.answered,
        replies=probe.replies,
    )
    return result


def per_scan_ms(result: dict) -> dict[str, dict[int, float]]:
    """Per cloud seq: map, graph, path and end-to-end latency (ms) where measured."""
    stages: dict[str, dict[int, float]] = {"map": {}, "graph": {}, "path": {}, "e2e": {}}
    by_stamp: dict[float, int] = {}
    for seq, (stamp, _) in sorted(result["patches"].items()):
        by_stamp.setdefault(stamp, seq)  # the first patch a delta caused
    for row in result["summary"]["per_scan"]:
        seq, latency = row[0], row[5]
        if latency is None:
            continue
        stages["map"][seq] = latency
        if seq not in result["deltas"]:
            continue
        stamp, t_delta = result["deltas"][seq]
        pseq = by_stamp.get(stamp)
        if pseq is None:
            continue
        t_patch = result["patches"][pseq][1]
        stages["graph"][seq] = (t_patch - t_delta) * 1000.0
        if pseq in result["answered"]:
            stages["path"][seq] = (result["answered"][pseq] - t_patch) * 1000.0
            stages["e2e"][seq] = latency + stages["graph"][seq] + stages["path"][seq]
    return stages


def _pct(values) -> tuple[float, float, float, float]:
    """p50, p95, p99 and max (nan when there are none)."""
    v = np.asarray(list(values), float)
    if v.size == 0:
        return (float("nan"),) * 4
    p50, p95, p99 = np.percentile(v, [50, 95, 99])
    return float(p50), float(p95), float(p99), float(v.max())


def report(result: dict, args: argparse.Namespace, load: tuple) -> tuple[str, list[str]]:
    """The tables as markdown, and what failed (empty: nothing)."""
    s = result["summary"]
    stages = per_scan_ms(result)
    first = min((row[0] for row in s["per_scan"]), default=0)
    steady = {k: {q: v for q, v in d.items() if q != first} for k, d in stages.items()}
    n_pub = s["published"]
    failures: list[str] = []
    lines = [
        f"# smana bench pipeline: {n_pub} scans of {result['points_in_scan']:,} points at "
        f"{s['recorded_rate_hz']:.0f} Hz, {args.backend} {args.res[0]:g} / {args.res[1]:g} m",
        "",
        f"Machine: {os.cpu_count()} cores, load average {load[0]:.2f} at the start, "
        f"{result['load_end']:.2f} at the end"
        + (" (busy: figures are pessimistic)" if load[0] > 0.75 * (os.cpu_count() or 1) else "")
        + f"; pinning: {_pins_text(result['pins'])}. The first scan (kernels loading) is "
        "left out of the latencies.",
        "",
        "| stage | scans | p50 ms | p95 ms | p99 ms | max ms |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    names = {
        "map": "scan published -> MapDelta (mapper)",
        "graph": "MapDelta -> GraphPatch (navgraph)",
        "path": "GraphPatch -> path on it (planner)",
        "e2e": "scan published -> updated path (end to end)",
    }
    for k, name in names.items():
        p50, p95, p99, mx = _pct(steady[k].values())
        lines.append(
            f"| {name} | {len(steady[k])} | {p50:.1f} | {p95:.1f} | {p99:.1f} | {mx:.1f} |"
        )
    cpu = result["cpu_s"]
    wall = result["wall_s"]
    lines += [
        "",
        "CPU from the first MapDelta to the end (the scans after the first):",
        "",
        "| process | CPU s | CPU ms / scan | CPU % of one core | pinned to |",
        "|---|---:|---:|---:|---|",
    ]
    for name in ("replay", *SERVICES):
        c = cpu.get(name, 0.0)
        lines.append(
            f"| {name} | {c:.2f} | {1000.0 * c / max(n_pub - 1, 1):.1f} | "
            f"{100.0 * c / max(wall, 1e-9):.0f} | "
            f"{','.join(map(str, result['pins'].get(name, []))) or 'any'} |"
        )
    st = result["status"]
    integrated = len(result["deltas"])
    drops = {
        n: {k: v for k, v in (st.get(n) or {}).get("dropped", {}).items() if v} for n in SERVICES
    }
    rejected = {
        n: {k: v for k, v in (st.get(n) or {}).get("rejected", {}).items() if v} for n in SERVICES
    }
    # A service whose kernels were still loading answered a peer's start-up sync `warming_up`
    # and the peer asked again (common/service.py): by design, no scan is involved.
    warming = {n: drops[n].pop("warming_up", 0) for n in SERVICES}
    changed = list(steady["graph"])
    lines += [
        "",
        f"Drops: {n_pub} scans published, {s['acknowledged']} integrated by the mapper "
        f"({integrated} MapDeltas seen here), {s['overtaken']} overtaken (stale at the mapper), "
        f"{s['unacknowledged']} unacknowledged, {s['late_published']} published late, "
        f"{s['late_integrated']} integrated more than one period late. Books: mapper dropped "
        f"{drops['mapper'] or 0}, navgraph {drops['navgraph'] or 0}, planner "
        f"{drops['planner'] or 0}; rejected {rejected}"
        + (
            f"; start-up syncs answered `warming_up` and asked again: "
            f"{ {n: w for n, w in warming.items() if w} }."
            if any(warming.values())
            else "."
        ),
    ]
    rep = result["replies"]
    ok = sum(r["ok"] for r in rep)
    plan = [r["planner_ms"] for r in rep if "planner_ms" in r]
    trip = [r["wall_ms"] for r in rep if "planner_ms" in r]
    early = sum(r.get("patch_seq", 0) < r.get("want", 0) for r in rep)
    lines.append(
        f"Path queries: {len(rep)} asked ({ok} with a path, {early} asked again because the "
        f"planner had not applied the patch yet), {len(result['answered'])} graph versions "
        f"answered of {len(result['patches'])} patches; round trip (stats + path) p50 "
        f"{_pct(trip)[0]:.1f} ms, p95 {_pct(trip)[1]:.1f} ms; planner's own time p50 "
        f"{_pct(plan)[0]:.1f} ms, max {_pct(plan)[3]:.1f} ms. Wall "
        f"{wall:.1f} s after the first scan, CPU {sum(cpu.values()):.1f} s for the four processes."
    )
    _, p95, p99, _ = _pct(steady["e2e"].values())
    verdict = "met" if p95 <= E2E_TARGET_MS and s["lost"] == 0 else "NOT met"
    lines.append(
        f"Target p95 end to end <= {E2E_TARGET_MS:.0f} ms with no scan dropped at 10 Hz: "
        f"{verdict} (p95 {p95:.1f} ms, {s['lost']} dropped). Issue 30's goal, p99 <= "
        f"{E2E_GOAL_P99_MS:.0f} ms: {'met' if p99 <= E2E_GOAL_P99_MS else 'NOT met'} (p99 "
        f"{p99:.1f} ms; a goal, not a failure of the run)."
    )
    if s["lost"]:
        failures.append(f"{s['lost']} scans dropped or lost")
    if s["acknowledged"] < n_pub:
        failures.append(f"only {s['acknowledged']} of {n_pub} scans integrated")
    for n in SERVICES:
        if not st.get(n):
            failures.append(f"{n} did not answer its status")
        elif drops[n] or rejected[n]:
            failures.append(f"{n} dropped {drops[n]} rejected {rejected[n]}")
    missing = [q for q in changed if q not in steady["path"]]
    if missing:
        failures.append(f"no path answered after the patches of scans {missing[:10]}")
    if not steady["graph"]:
        failures.append("no GraphPatch followed any scan")
    return "\n".join(lines), failures


def _pins_text(pins: dict) -> str:
    if not pins:
        return "none (the scheduler's choice)"
    return ", ".join(f"{k} on {','.join(map(str, v))}" for k, v in pins.items())


def main(args: argparse.Namespace) -> int:
    from smana.lab.data import synthetic as syn
    from smana.services.replay.readers import open_dataset

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    beams, columns = (QUICK["beams"], QUICK["columns"]) if args.quick else (64, 2048)
    n = args.scans or (QUICK["scans"] if args.quick else 100)
    params = syn.SyntheticConfig(n_scans=n, beams=beams, columns=columns)
    progress.say(f"writing the synthetic sequence ({n} scans of {beams * columns:,} points) ...")
    with progress.bar(n, "writing scans", unit="scan") as bar:
        syn.write_rellis_sequence(
            out / "synthetic", params, progress=lambda k, _: bar.update(k - bar.n)
        )
    dataset = (out / "synthetic").resolve()
    with open_dataset(dataset) as reader:
        args.table = reader.default_class_table
    load = os.getloadavg()
    progress.say(
        f"replaying at 10 Hz through mapper, navgraph and planner (load {load[0]:.2f}) ..."
    )
    result = run_pipeline(dataset, args, out)
    result["points_in_scan"] = beams * columns
    result["load_end"] = os.getloadavg()[0]
    text, failures = report(result, args, load)
    print(text)
    (out / "pipeline_bench.md").write_text(text + "\n")
    raw = {k: result[k] for k in ("pins", "status", "wall_s", "cpu_s", "replies", "load_end")} | {
        "load_start": load[0],
        "per_scan_ms": per_scan_ms(result),
    }
    (out / "pipeline_bench.json").write_text(json.dumps(raw, indent=1, default=float))
    if failures:
        print("FAILED: " + "; ".join(failures), file=sys.stderr)
        return 1
    return 0


def _res_pair(text: str) -> tuple[float, float]:
    try:
        m, g = (float(v) for v in text.split("/"))
    except ValueError:
        m = g = -1.0
    if not (m > 0 and g > 0):
        raise argparse.ArgumentTypeError(f"expected MAP/GRAPH in metres, e.g. 0.1/0.2; got {text}")
    return m, g


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, non_negative_int, output_dir
    from smana.lab.bench.replay import BACKENDS

    p = ArgumentParser(
        prog="smana bench pipeline",
        description=doc_summary(__doc__),
        epilog=(
            "Duration measured once on a 2-core machine: 1 to 3 minutes by default (the 100-scan "
            "sequence "
            "is written once and reused, four services start, 10 s of replay); --quick, the "
            "test suite's (20 scans of 8,192 points), about 30 s, mostly the services starting. "
            "Output: the tables on stdout and in <out>/pipeline_bench.md, the per-scan figures "
            "in <out>/pipeline_bench.json."
        ),
    )
    p.add_argument("--scans", type=non_negative_int, default=0, help="scans (default 100)")
    p.add_argument("--backend", choices=BACKENDS, default="octree-max")
    p.add_argument("--res", type=_res_pair, default=(0.1, 0.2), help="MAP/GRAPH resolution")
    p.add_argument(
        "--pin",
        choices=("auto", "chain", "mapper", "none"),
        default="auto",
        help="cores per process (os.sched_setaffinity): auto = one per service with 4 cores or "
        "more, else chain = mapper, navgraph and planner on one core and the replay on the "
        "other(s); mapper = the mapper alone on one core; none = the scheduler's",
    )
    p.add_argument("--quick", action="store_true", help="20 scans of 8,192 points")
    p.add_argument("--out", default="runs/bench-pipeline", help="default: runs/bench-pipeline")
    args = p.parse_args(argv)
    output_dir(args.out, "output directory", "--out")
    return main(args)


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench pipeline", cli))
