"""`smana bench replay [DATASET]`: the paper's resource evaluation (section 5, Figures 11 and 12).

For each mapping back-end and each map/graph resolution pair, a zenoh router (in this process),
the mapper and the navgraph run as their own processes and the replay service feeds them the whole
sequence in lockstep. Measured per configuration:

- integration time per point, map and graph separately, mean and standard deviation over the
  scans: the mapper's own timing of each integration (its `stats` query) and the time from a
  MapDelta to the GraphPatch it caused, each divided by the scan's published points;
- CPU use (mean and standard deviation of psutil samples; 100 % = one core) and peak RSS of the
  mapper and navgraph processes over the sequence.

Then one realtime run (octree-max at 0.1 m / 0.2 m by default) with the planner up checks the
targets: no scan late or lost at the recorded rate, and path queries answered within 100 ms while
the map grows. Without a dataset the synthetic RELLIS-3D-layout sequence is written first
(131,072-point OS1-64-like scans at 10 Hz). Output: a table on stdout and in
`<out>/replay_bench.md`, the raw figures in `replay_bench.json`, and the plots
`fig11_cpu_ram.png` and `fig12_time_per_point.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from smana.common import progress
from smana.common.cli import doc_summary
from smana.common.zenoh_config import free_loopback_port
from smana.lab.bench import procs
from smana.lab.bench.replay_report import RunResult, aggregate, realtime_markdown, table_markdown
from smana.services.mapper.backends import BACKENDS as _REGISTRY


class Stack:
    """A router in this process, services as child processes (own process groups)."""

    def __init__(self, log_dir: Path, robot: str = "bench"):
        from smana.common.config import ZenohConfig
        from smana.deploy.router import open_router

        self.port = free_loopback_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.robot = robot
        self.log_dir = log_dir
        log_dir.mkdir(parents=True, exist_ok=True)
        zc = ZenohConfig(mode="router", connect=[], listen=[self.endpoint])
        self.session = open_router([self.endpoint], zc)
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, args: list[str]) -> subprocess.Popen:
        argv = procs.service_argv(name, self.endpoint, self.robot, *args)
        proc = procs.spawn(argv, self.log_dir / f"{name}.log")
        self.procs[name] = proc
        return proc

    def wait_alive(self, names: list[str], timeout_s: float = 60.0) -> None:
        """Live and serving: the alive token, and the kernels loaded (`common.query.ready`)."""
        from smana.common.query import ready

        deadline = time.monotonic() + timeout_s
        for name in names:
            while True:
                if ready(self.session, self.robot, name):
                    break
                if self.procs[name].poll() is not None or time.monotonic() > deadline:
                    log = (self.log_dir / f"{name}.log").read_text(errors="replace")[-3000:]
                    raise RuntimeError(f"{name} did not come up:\n{log}")
                time.sleep(0.1)

    def stop(self, name: str, timeout_s: float = 10.0) -> None:
        proc = self.procs.pop(name, None)
        if proc is not None:
            procs.stop([proc], timeout_s)

    def close(self) -> None:
        for name in list(self.procs):
            self.stop(name)
        self.session.close()


class Sampler(threading.Thread):
    """psutil CPU % and RSS of some processes, every `period_s`, while `active` is set."""

    def __init__(self, pids: dict[str, int], period_s: float = 0.25):
        super().__init__(daemon=True)
        import psutil

        self.procs = {n: psutil.Process(pid) for n, pid in pids.items()}
        self.period_s = period_s
        self.cpu: dict[str, list[float]] = {n: [] for n in pids}
        self.rss: dict[str, int] = dict.fromkeys(pids, 0)
        self.active = threading.Event()
        self.done = threading.Event()

    def run(self) -> None:
        import psutil

        for p in self.procs.values():
            p.cpu_percent(None)  # primes the counter: the next call measures from here
        while not self.done.wait(self.period_s):
            for n, p in self.procs.items():
                try:
                    cpu = p.cpu_percent(None)
                    rss = p.memory_info().rss
                except psutil.Error:
                    continue
                if self.active.is_set():
                    self.cpu[n].append(cpu)
                    self.rss[n] = max(self.rss[n], rss)


class Probe:
    """Listens to MapDeltas and GraphPatches (arrival times) and asks the mapper and the navgraph
    for their own timing of each integration (`integrate_ms_last` in their `stats`, matched to
    the scan by their integration counters)."""

    def __init__(self, stack: Stack):
        from smana.common import keys

        self.stack = stack
        self.deltas: dict[int, tuple[float, float]] = {}  # cloud_seq -> (stamp, arrival)
        self.patches: list[tuple[float, float]] = []  # (stamp, arrival)
        self.map_ms: dict[int, float] = {}  # k-th integration -> integrate_ms_last
        self.graph_ms: dict[int, float] = {}
        r = stack.robot
        self._stats_keys = (keys.query(r, "mapper", "stats"), keys.query(r, "navgraph", "stats"))
        # The counters before the first scan (the navgraph counts its start-up snapshot too).
        first = [query_map(stack.session, k) or {} for k in self._stats_keys]
        self._base = (int(first[0].get("clouds", 0)), int(first[1].get("deltas", 0)))
        self.poses: list[tuple[float, float]] = []
        self._wanted = threading.Event()
        self._stop = threading.Event()
        r = stack.robot
        s = stack.session
        self._subs = [
            s.declare_subscriber(keys.map_delta(r), self._on_delta),
            s.declare_subscriber(keys.graph_patch(r), self._on_patch),
            s.declare_subscriber(keys.pose(r), self._on_pose),
        ]
        self._thread = threading.Thread(target=self._ask_stats, daemon=True)
        self._thread.start()

    def _on_delta(self, sample) -> None:
        import msgpack

        now = time.monotonic()
        head = msgpack.unpackb(sample.payload.to_bytes(), raw=False)  # no need to validate
        self.deltas.setdefault(int(head["cloud_seq"]), (float(head["stamp_s"]), now))
        self._wanted.set()

    def _on_patch(self, sample) -> None:
        import msgpack

        now = time.monotonic()
        head = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        self.patches.append((float(head["stamp_s"]), now))
        self._wanted.set()

    def _on_pose(self, sample) -> None:
        from smana.common.messages import Pose, decode

        p = decode(sample.payload.to_bytes(), Pose)
        self.poses.append((float(p.position[0]), float(p.position[1])))

    def _ask_stats(self) -> None:
        # Queries queue behind the delta that triggered them (both services handle their input
        # in order), so `integrate_ms_last` is that integration's unless another came between;
        # the counter says which one it was either way.
        targets = ((self.map_ms, "clouds"), (self.graph_ms, "deltas"))
        while not self._stop.is_set():
            if not self._wanted.wait(0.2):
                continue
            self._wanted.clear()
            for key, base, (store, counter) in zip(
                self._stats_keys, self._base, targets, strict=True
            ):
                st = query_map(self.stack.session, key)
                if st and counter in st and "integrate_ms_last" in st and st[counter] > base:
                    store.setdefault(int(st[counter]) - base, float(st["integrate_ms_last"]))

    def graph_e2e_ms(self) -> dict[int, float]:
        return match_patches(self.deltas, self.patches)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for s in self._subs:
            s.undeclare()


def match_patches(
    deltas: dict[int, tuple[float, float]], patches: list[tuple[float, float]]
) -> dict[int, float]:
    """Per cloud seq, ms from its MapDelta's arrival to its GraphPatch's.

    `deltas`: seq -> (stamp, arrival); `patches`: (stamp, arrival). A patch carrying the stamp of
    a delta answers that delta. Patches with stamps no delta has are matched by order instead:
    the first patch after a delta and before the next one. A delta that changed no node may
    have no patch; it gets no figure.
    """
    by_stamp: dict[float, float] = {}
    for stamp, t in sorted(patches, key=lambda p: p[1]):
        by_stamp.setdefault(stamp, t)
    seqs = sorted(deltas)
    arrivals = [deltas[s][1] for s in seqs] + [float("inf")]
    stamped = {deltas[s][0] for s in seqs}
    loose = np.sort([t for stamp, t in patches if stamp not in stamped])
    out = {}
    for k, seq in enumerate(seqs):
        stamp, t = deltas[seq]
        if stamp in by_stamp and by_stamp[stamp] >= t:
            out[seq] = (by_stamp[stamp] - t) * 1000.0
            continue
        j = int(np.searchsorted(loose, t))
        if j < loose.size and loose[j] < arrivals[k + 1]:
            out[seq] = (loose[j] - t) * 1000.0
    return out


def query_map(session, key: str, payload: bytes | None = None, timeout_s: float = 5.0):
    """A query whose reply is a msgpack map; None when there is no (good) reply."""
    import msgpack

    for reply in session.get(key, payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            try:
                return msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
            except Exception:  # noqa: BLE001 - a garbled reply is no reply
                return None
    return None


def stack_settings(backend: str, map_res: float, graph_res: float, table: str) -> list[str]:
    sets = [
        f"general.class_table={table}",
        'mapper.inputs=["scan"]',
        f"mapper.backend={backend}",
        f"mapper.resolution_m={map_res}",
        "mapper.max_range_m=10.0",
        "mapper.raycast_range_m=1.0",
        "mapper.autosave_period_s=0",
        f"navgraph.resolution_m={graph_res}",
    ]
    return [a for s in sets for a in ("--set", s)]


def run_config(
    dataset: Path,
    backend: str,
    map_res: float,
    graph_res: float,
    repeat: int,
    out: Path,
    table: str,
    count: int,
    realtime: bool = False,
    probe_paths: bool = False,
) -> tuple[RunResult, dict]:
    """One pass over the sequence; returns the measurements and the replay's summary."""
    name = f"{backend}_{map_res:g}_{graph_res:g}" + ("_realtime" if realtime else f"_r{repeat}")
    run_dir = out / "runs" / name
    stack = Stack(run_dir / "logs")
    res = RunResult(backend, map_res, graph_res, repeat)
    path_times: list[dict] = []
    try:
        sets = stack_settings(backend, map_res, graph_res, table)
        services = ["mapper", "navgraph"] + (["planner"] if probe_paths else [])
        for s in services:
            stack.start(s, [*sets, "--run-dir", str(run_dir / s)])
        stack.wait_alive(services)
        probe = Probe(stack)
        sampler = Sampler({s: stack.procs[s].pid for s in ("mapper", "navgraph")})
        sampler.start()
        pace = ["--realtime"] if realtime else ["--lockstep"]
        extra = ["--count", str(count)] if count else []
        stack.start(
            "replay",
            [
                str(dataset),
                *pace,
                *extra,
                *sets,
                "--run-dir",
                str(run_dir / "replay"),
                "--set",
                f"replay.wait_for={json.dumps(services)}",
            ],
        )
        sampler.active.set()
        prober = None
        if probe_paths:
            prober = threading.Thread(
                target=_probe_paths,
                args=(stack, probe, path_times, stack.procs["replay"]),
                daemon=True,
            )
            prober.start()
        t0 = time.monotonic()
        code = stack.procs["replay"].wait()
        res.wall_s = time.monotonic() - t0
        time.sleep(0.5)  # the last GraphPatch
        sampler.active.clear()
        sampler.done.set()
        if prober is not None:
            prober.join(timeout=5)
        probe.close()
        summary_path = run_dir / "replay" / "replay.json"
        if code != 0 or not summary_path.exists():
            log = (run_dir / "logs" / "replay.log").read_text(errors="replace")[-3000:]
            raise RuntimeError(f"replay failed ({code}) for {name}:\n{log}")
        summary = json.loads(summary_path.read_text())
    finally:
        stack.close()

    per_scan = summary["per_scan"]
    points = {row[0]: row[4] for row in per_scan}
    graph_e2e = probe.graph_e2e_ms()
    res.scans = len(per_scan)
    res.lost = summary["lost"]
    res.points_per_scan = float(np.mean(list(points.values()))) if points else 0.0
    res.latency_ms = [row[5] for row in per_scan if row[5] is not None]
    # The mapper's k-th integration is the k-th published scan (lockstep, nothing lost). The
    # first is left out of the timing: it pays for loading the compiled kernels.
    for k, ms in sorted(probe.map_ms.items()):
        if k > 1 and k in points and points[k]:
            res.map_ms.append(ms)
            res.map_us_per_point.append(1000.0 * ms / points[k])
    for k, ms in sorted(probe.graph_ms.items()):
        if k > 1 and k in points and points[k]:
            res.graph_ms.append(ms)
            res.graph_us_per_point.append(1000.0 * ms / points[k])
    res.graph_e2e_ms = [ms for _, ms in sorted(graph_e2e.items())]
    res.cpu_map, res.cpu_graph = sampler.cpu["mapper"], sampler.cpu["navgraph"]
    res.rss_map_mb = sampler.rss["mapper"] / 2**20
    res.rss_graph_mb = sampler.rss["navgraph"] / 2**20
    summary["path_queries"] = path_times
    return res, summary


def _probe_paths(stack: Stack, probe: Probe, out: list[dict], replay: subprocess.Popen) -> None:
    """While the replay runs: a path from the first pose to the latest one, twice a second."""
    from smana.common import keys
    from smana.common.messages import PathReply, PathRequest, decode, encode

    key = keys.path_query(stack.robot)
    n = 0
    while replay.poll() is None:
        time.sleep(0.5)
        # The LiDAR does not see the ground within 3.4 m of itself: the start pose is known
        # only once the robot has driven off it.
        if len(probe.poses) < 2 or np.hypot(*np.subtract(probe.poses[-1], probe.poses[0])) < 4.0:
            continue
        n += 1
        req = PathRequest(
            request_id=f"probe{n}", start=np.array(probe.poses[0]), goal=np.array(probe.poses[-1])
        )
        t0 = time.perf_counter()
        reply = None
        for r in stack.session.get(key, payload=encode(req), timeout=5.0):
            if r.ok is not None:
                reply = decode(r.ok.payload.to_bytes(), PathReply)
        wall_ms = (time.perf_counter() - t0) * 1000.0
        out.append(
            {
                "wall_ms": wall_ms,
                "planner_ms": reply.time_ms if reply else None,
                "ok": bool(reply and reply.ok),
                "error": reply.error if reply else "no reply",
            }
        )


def main(args: argparse.Namespace) -> int:
    from smana.lab.data import synthetic as syn
    from smana.services.replay.readers import open_dataset

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.dataset:
        dataset = Path(args.dataset).resolve()
    else:
        params = syn.SyntheticConfig(n_scans=args.scans)
        print(
            f"writing the synthetic sequence ({args.scans} scans of 131,072 points) ...",
            file=sys.stderr,
        )
        with progress.bar(args.scans, "writing scans", unit="scan") as bar:
            syn.write_rellis_sequence(
                out / "synthetic", params, progress=lambda k, n: bar.update(k - bar.n)
            )
        dataset = (out / "synthetic").resolve()
    with open_dataset(dataset) as reader:
        table = args.table or reader.default_class_table
        n_scans = len(reader)
    count = args.scans if args.dataset and args.scans else 0
    pairs = [tuple(float(v) for v in p.split("/")) for p in args.res.split(",")]
    backends = args.backends.split(",")
    load = os.getloadavg()[0]
    runs: list[RunResult] = []
    # one step per replay run, the realtime check included: each replays the whole sequence
    n_runs = len(backends) * len(pairs) * args.repeats + (0 if args.no_realtime else 1)
    bar = progress.bar(n_runs, "bench replay", unit="run")
    for backend in backends:
        for mres, gres in pairs:
            for rep in range(args.repeats):
                progress.say(
                    f"{backend} {mres:g}/{gres:g} m, run {rep + 1}/{args.repeats} ...",
                    file=sys.stderr,
                )
                r, _ = run_config(dataset, backend, mres, gres, rep, out, table, count)
                runs.append(r)
                bar.update()
    rows = aggregate(runs)
    text = [
        f"# smana bench replay: {dataset} ({count or n_scans} scans, class table {table})",
        "",
        f"Machine: {os.cpu_count()} cores, load average {load:.1f} at the start"
        + (" (busy: figures are pessimistic)" if load > 0.5 else "")
        + f"; median of {args.repeats} run(s) per configuration. CPU: 100 % = one core.",
        "",
        table_markdown(rows),
    ]
    realtime_summary = None
    if not args.no_realtime:
        backend, mres, gres = args.realtime_backend, *pairs[0]
        progress.say(
            f"realtime check: {backend} {mres:g}/{gres:g} m with the planner ...", file=sys.stderr
        )
        _, realtime_summary = run_config(
            dataset, backend, mres, gres, 0, out, table, count, realtime=True, probe_paths=True
        )
        bar.update()
        text += ["", realtime_markdown(realtime_summary, backend, mres, gres)]
    bar.close()
    report = "\n".join(text) + "\n"
    print(report)
    (out / "replay_bench.md").write_text(report)
    (out / "replay_bench.json").write_text(
        json.dumps(
            {"rows": rows, "runs": [asdict(r) for r in runs], "realtime": realtime_summary},
            indent=1,
            default=float,
        )
    )
    from smana.lab.paper_figures import figure_11, figure_12

    figure_11(rows, out / "fig11_cpu_ram.png")
    figure_12(rows, out / "fig12_time_per_point.png")
    print(
        f"written: {out}/replay_bench.md, replay_bench.json, fig11_cpu_ram.png, "
        "fig12_time_per_point.png",
        file=sys.stderr,
    )
    return 0


BACKENDS = tuple(_REGISTRY)  # the mapper's registry: every back-end it knows


def _backends(text: str) -> str:
    """--backends: a comma-separated subset of BACKENDS (kept as the string main() splits)."""
    bad = [b for b in text.split(",") if b not in BACKENDS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown back-end(s) {bad}; known: {', '.join(BACKENDS)}")
    return text


def _resolution_pairs(text: str) -> str:
    """--res: MAP/GRAPH pairs in metres, both > 0, e.g. 0.1/0.2,0.2/0.4."""
    for pair in text.split(","):
        try:
            ok = all(float(v) > 0 for v in pair.split("/")) and pair.count("/") == 1
        except ValueError:
            ok = False
        if not ok:
            raise argparse.ArgumentTypeError(
                f"expected MAP/GRAPH resolutions > 0 in metres, e.g. 0.1/0.2,0.2/0.4; got {pair!r}"
            )
    return text


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, non_negative_int, output_dir, positive_int

    p = ArgumentParser(
        prog="smana bench replay",
        description=doc_summary(__doc__),
        epilog=(
            "Duration measured once on a 2-core machine: about 5 minutes by default (a synthetic "
            "100-scan "
            "OS1-64 sequence, 3 back-ends x 3 resolutions x 3 repeats, then the realtime "
            "check: 28 runs of about 11 s); on a real dataset, 28 runs of about 10 s plus its "
            "scans at the mapper's pace (--scans 0: all of them). A progress bar with an ETA "
            "shows on a terminal "
            "(SMANA_PROGRESS=1 forces it, 0 hides it)."
        ),
    )
    p.add_argument("dataset", nargs="?", help="a dataset (default: the synthetic sequence)")
    p.add_argument(
        "--scans",
        type=non_negative_int,
        default=100,
        help="synthetic: scans to write; a dataset: scans to replay (0 = all)",
    )
    p.add_argument("--backends", type=_backends, default=",".join(BACKENDS))
    p.add_argument(
        "--res",
        type=_resolution_pairs,
        default="0.1/0.2,0.2/0.4,0.3/0.6",
        help="map/graph resolution pairs",
    )
    p.add_argument(
        "--repeats", type=positive_int, default=3, help="runs per configuration (median)"
    )
    p.add_argument("--table", help="class table (default: the dataset's)")
    p.add_argument("--out", default="runs/bench-replay")
    p.add_argument("--no-realtime", action="store_true", help="skip the realtime check")
    p.add_argument("--realtime-backend", choices=BACKENDS, default="octree-max")
    args = p.parse_args(argv)
    if args.dataset and not Path(args.dataset).exists():
        p.error(f"dataset {args.dataset} does not exist")
    if args.scans == 0 and not args.dataset:
        p.error("--scans 0 means every scan of a dataset; the synthetic sequence needs >= 1")
    output_dir(args.out, "output directory", "--out")
    return main(args)


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("bench replay", cli))
