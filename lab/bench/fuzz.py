"""`smana bench fuzz`: the multi-process fuzz campaign (no input may end a service unseen).

The real services (mapper, navgraph, planner, explorer, the coordinator and, unless left out, the
simulator) run as their own processes against a zenoh router in this process, on a free loopback
port with multicast scouting and gossip off. The coordinator runs on a fleet name of its own
(`FLEET`, members `fuzz_messages.FLEET_MEMBERS`), so nothing but the campaign talks to it. The
campaign:

0. **map files** (issue 25; `--map-files`, in this process, before the stack starts): valid and
   corrupt map files from `lab/fuzz_maps.py`, each loaded as the mapper (or the fleet mapper)
   loads one; each ends in exactly one of loaded / refused / crash; a loaded file must equal the
   file as saved and a file the generator knows to be corrupt must be refused;
1. **establishes state**: a few genuine ground clouds (with a wall) go to the mapper; navgraph
   builds its graph from the deltas; the planner answers a fixed path query round the wall;
2. **phase `refused`**: inputs every service must refuse, on every key it listens to: payloads
   the codec refuses (structural mutations, broken bytes, oversize payloads), clouds outside the
   world frame, deltas and patches from a foreign producer or of another graph geometry; and
   fuzzed queries to every queryable (queries do not change state);
   then forces a navgraph resync and a planner sync and checks the state: the mapper's occupied
   voxels, navgraph's graph and the planner's answer to the fixed query are bit for bit those of
   step 1;
3. **phase `hostile`**: everything `deploy/fuzz.py` makes, valid-but-hostile messages included
   (wild stamps, numbering, producers, coordinates, sizes), which may change state;
4. **recovery**: genuine clouds again, until the genuine stream reaches navgraph's graph (the
   stamp gates may have locked onto a hostile clock: bounded by their relock rule);
5. **final checks**: the mapper's map equals a reference map fed exactly the clouds the mapper
   accepted (decided per cloud from its books); after a forced resync navgraph's graph equals the
   navgraph core fed the mapper's snapshot; after a forced sync the planner's answer equals the
   planner core's on that graph; no file written outside the mapper's save folder;
6. **books**: per service, settled once the stack is quiet: `msgs_in` grew by exactly the inputs
   and queries sent to it plus what its peers sent it (counted by the peers: deltas = mapper
   clouds, patches = navgraph patch numbers, graph/snapshot/path queries); every structural
   rejection kind (malformed, type, version, shape, ...) equals what the codec predicts for the
   inputs sent; no `internal` rejection and no `internal_*` event (crashes); same pid (no
   restart), every query answered, clean exit on SIGINT.

7. **ROS 2 topics** (issue 25; `--ros2 N`, after the stack has stopped): `smana ros2` reading a
   robot's topics, on a router of its own, gets hostile `/odom`, `/points`, `/tf_static` and
   GetPlan requests (`lab/bench/fuzz_ros2.py`); each case's fate predicted, the books checked
   against the predictions, genuine odometry and GetPlan working afterwards.

`--inputs 0` leaves out the stack (steps 1 to 6). Each input is generated from `--seed`; the
same generators drive the in-process hypothesis tests.
Output: a table, and the raw figures as JSON (`--out`). Exit status 1 when a check fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import random
import resource
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from smana.common import keys
from smana.common import messages as m
from smana.common.cli import doc_summary
from smana.common.config import SmanaConfig
from smana.common.zenoh_config import free_loopback_port
from smana.lab import fuzz_messages
from smana.lab.bench import fuzz_campaign, procs
from smana.lab.fuzz_values import RandomDraw

SERVICES = ("mapper", "navgraph", "planner", "explorer", "sim", "coordinator")
# Rejection kinds only the codec produces: the books must match the prediction exactly. Others
# ("value", and the handlers' own: stamp, producer, sequence, geometry, frame, pose_jump, ...) may
# also come from decodable input a handler refuses.
STRUCTURAL = (
    "oversize",
    "malformed",
    "type",
    "version",
    "missing_field",
    "unknown_field",
    "dtype",
    "shape",
    "length",
    "nonfinite",
)
FOREIGN = "fuzz-stranger"  # a producer no service follows
SETTLE_EVERY = 200  # FIFO inputs to one service before waiting for it to catch up
RELOCK = 5  # StampGate's default: consecutive consistent stamps that move its clock

# What the campaign configures (every service reads the same file; the references too).
CONFIG = """\
[general]
status_period_s = 1.0

[mapper]
resolution_m = 0.1
inputs = ["cloud", "scan"]
autosave_period_s = 0.0
save_path = "{save_path}"

[explorer]
time_budget_s = 1.0e9
done_after_empty = 1000000000

[sim]
lockstep = true
lockstep_timeout_s = 2.0

[sim.camera]
width = 64
height = 64
rate_hz = 2.0
"""


@dataclass(frozen=True)
class Target:
    """A key a service listens to (`latest`: one-slot mailbox, `fifo`: queue) or answers
    (`query`). `topic` is `<segment>/<name>` under `smana/<robot>/`."""

    service: str
    topic: str
    kind: str
    expect: type[m.Message] | None = None
    consumers: tuple[str, ...] = ()
    weight: float = 1.0
    drop_nonfinite: bool = False
    robot: str = ""  # a key of another robot than the service's own (a fleet member's)
    refused_phase: bool = True  # takes part in the refused phase (its input cannot change state)

    @property
    def name(self) -> str:
        return f"{self.service}:{self.robot + '/' if self.robot else ''}{self.topic}"

    @property
    def services(self) -> tuple[str, ...]:
        return self.consumers or (self.service,)


TARGETS: tuple[Target, ...] = (
    Target("mapper", "robot/cloud", "latest", m.SemanticCloud, ("mapper",), 8, True),
    Target("mapper", "robot/scan", "latest", m.SemanticCloud, ("mapper",), 4, True),
    Target("mapper", "mapper/stats", "query", weight=1),
    Target("mapper", "mapper/snapshot", "query", weight=3),
    Target("mapper", "mapper/save", "query", weight=2),
    Target("mapper", "mapper/point", "query", weight=3),
    Target("mapper", "mapper/status", "query", weight=1),
    Target("navgraph", "mapper/delta", "fifo", m.MapDelta, ("navgraph",), 14),
    Target("navgraph", "navgraph/graph", "query", weight=3),
    Target("navgraph", "navgraph/node", "query", weight=3),
    Target("navgraph", "navgraph/stats", "query", weight=1),
    Target("navgraph", "navgraph/status", "query", weight=1),
    Target("planner", "navgraph/patch", "fifo", m.GraphPatch, ("planner", "explorer"), 12),
    Target("planner", "planner/path", "query", weight=10),
    Target("planner", "planner/stats", "query", weight=1),
    Target("planner", "planner/status", "query", weight=1),
    Target("explorer", "robot/pose", "fifo", m.Pose, ("explorer",), 10),
    Target("explorer", "robot/safety_scan", "fifo", m.SemanticCloud, ("explorer",), 4),
    Target("explorer", "explorer/state", "query", weight=2),
    Target("explorer", "explorer/status", "query", weight=1),
    Target("sim", "robot/cmd_vel", "fifo", m.VelocityCommand, ("sim",), 6),
    Target("sim", "mapper/delta", "fifo", m.MapDelta, ("sim",), 3),
    Target("sim", "sim/status", "query", weight=1),
    # the coordinator, on the fleet's name; its members' states are raw msgpack maps (expect None)
    # claims on member fuzzc1's own key (`keys.claim`); the bodies name any member or none
    Target("coordinator", "coordinator/claim/fuzzc1", "query", weight=6, refused_phase=False),
    Target("coordinator", "coordinator/claims", "query", weight=1),
    Target("coordinator", "coordinator/stats", "query", weight=1),
    Target("coordinator", "coordinator/status", "query", weight=1),
    *(
        Target("coordinator", "explorer/state", "fifo", None, ("coordinator",), 3, robot=r)
        for r in fuzz_messages.FLEET_MEMBERS
    ),
)
# Oversize payloads (64 MiB + a little each), in this order, as many as asked.
OVERSIZE_ORDER = (
    "mapper:robot/cloud",
    "navgraph:mapper/delta",
    "planner:navgraph/patch",
    "explorer:robot/pose",
    "planner:planner/path",
    "sim:robot/cmd_vel",
    "mapper:mapper/point",
    "navgraph:navgraph/node",
)

# The scene: ground over the area, a hedge wall across it; the fixed query goes round the wall.
AREA = (-3.0, -3.0, 3.0, 3.0)
WALL_X, WALL_Y = 0.0, (-3.0, 1.0)
FIXED_QUERY = ((-2.0, -2.0), (2.0, -2.0))
RECOVERY_AREA = (4.0, -3.0, 6.0, -1.0)  # genuine clouds after the fuzz land here
GROUND, GRASS, HEDGE = 2, 1, 4
FLEET = "fuzzfleet"  # the coordinator's robot name (its members: fuzz_messages.FLEET_MEMBERS)
COORDINATOR_CONFIG = """\
[general]
status_period_s = 1.0

[fleet]
robots = {members}
"""


class CampaignError(RuntimeError):
    """The stack could not be set up or did not answer: the campaign could not run."""


# -- results -------------------------------------------------------------------------------------


@dataclass
class KeyFigures:
    """Per target: inputs sent, what the codec says of them, what came back (queries)."""

    inputs: int = 0
    codec: Counter = field(default_factory=Counter)  # predicted: "accepted" or a rejection kind
    handler_refusals: int = 0  # decodable inputs built to be refused by the handler (phase 1)
    replies: Counter = field(default_factory=Counter)  # queries: "ok" or the error kind
    cloud_accepted: int = 0  # latest-wins inputs: integrated (per cloud, from the books)
    not_sent: int = 0  # refused by zenoh in this process (an unusable selector)


@dataclass
class ServiceFigures:
    pid: int = 0
    mine: int = 0  # inputs and queries this campaign sent it (status polls included)
    background: int = 0  # what its peers sent it over the same span
    msgs_in: int = 0
    accepted: int = 0
    dropped: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    predicted: dict = field(default_factory=dict)  # rejection kinds of the inputs, as predicted
    events: dict = field(default_factory=dict)
    exit_code: int | None = None
    tracebacks: int = 0


@dataclass
class MapFileFigures:
    """Per kind of map file (`lab.fuzz_maps.MAP_MUTATIONS`): each file ends in exactly one of
    loaded / refused / crash; `wrong` counts outcomes against the prediction or a loaded map that
    differs from the file as saved (a subset, not an outcome of its own)."""

    inputs: int = 0
    loaded: int = 0
    refused: int = 0
    crash: int = 0
    wrong: int = 0


@dataclass
class Result:
    seed: int
    inputs_requested: int
    services: list[str]
    inputs: int = 0
    keys: dict[str, KeyFigures] = field(default_factory=dict)
    service_figures: dict[str, ServiceFigures] = field(default_factory=dict)
    checks: dict[str, bool] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    crashes: int = 0
    recovery_clouds: int = 0
    wall_s: float = 0.0
    cpu_s: float = 0.0
    cpu_s_services: float = 0.0
    load_start: tuple = ()
    load_end: tuple = ()
    phase_s: dict[str, float] = field(default_factory=dict)
    map_files: dict[str, MapFileFigures] = field(default_factory=dict)  # by mutation
    ros2: object = None  # `fuzz_ros2.Ros2Figures` of the ROS 2 family, when it ran

    @property
    def map_inputs(self) -> int:
        return sum(f.inputs for f in self.map_files.values())

    @property
    def ok(self) -> bool:
        ros2_ok = self.ros2 is None or self.ros2.ok
        return self.crashes == 0 and all(self.checks.values()) and bool(self.checks) and ros2_ok

    def to_json(self) -> dict:
        d = _plain(self)
        d["ok"] = self.ok
        return d


def _plain(obj):
    """Dataclasses, Counters and tuples as JSON-ready dicts and lists (dataclasses.asdict
    rebuilds a Counter from its items, which counts the pairs)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    return obj


def _check(result: Result, name: str, ok: bool, note: str = "") -> bool:
    result.checks[name] = bool(result.checks.get(name, True) and ok)
    if not ok and note:
        result.notes.append(f"{name}: {note}")
    return ok


# -- fingerprints of state -----------------------------------------------------------------------


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def map_fingerprint(centres, labels, confidences, occupied, values) -> str:
    """Occupied voxels, whatever their order."""
    order = np.lexsort(np.asarray(centres, np.float64).T[::-1])
    return _digest(
        *(np.asarray(a)[order] for a in (centres, labels, confidences, occupied, values))
    )


def graph_fingerprint(cells, labels, heights, flags) -> str:
    cells = np.asarray(cells, np.int32).reshape(-1, 2)
    order = np.lexsort((cells[:, 1], cells[:, 0]))
    heights = np.asarray(heights, np.float32)
    return _digest(
        cells[order],
        np.asarray(labels, np.uint16)[order],
        heights[order],
        np.asarray(flags, np.uint8)[order],
    )


def reply_fingerprint(r: m.PathReply) -> str:
    """A PathReply without what varies between two answers to one question (id, time)."""
    scalars = json.dumps(
        [
            r.ok,
            r.error,
            r.message,
            r.cost_total,
            r.cost_distance,
            r.cost_height,
            r.cost_traversability,
            sorted(r.label_share.items()),
            r.nodes_expanded,
        ]
    )
    return _digest(np.frombuffer(scalars.encode(), np.uint8), r.path, r.nearest_free)


# -- genuine input -------------------------------------------------------------------------------


def genuine_cloud(seq: int, stamp_s: float, area=AREA, wall: bool = True) -> m.SemanticCloud:
    """Ground (terrain and a grass strip) over `area`, and a hedge wall, seen from above."""
    x0, y0, x1, y1 = area
    xs, ys = np.meshgrid(np.arange(x0 + 0.025, x1, 0.05), np.arange(y0 + 0.025, y1, 0.05))
    ground = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    labels = np.where(ground[:, 1] > 2.0, GRASS, GROUND)
    parts, labs = [ground], [labels]
    if wall:
        wy, wz = np.meshgrid(np.arange(WALL_Y[0], WALL_Y[1], 0.05), np.arange(0.05, 1.0, 0.05))
        w = np.stack([np.full(wy.size, WALL_X), wy.ravel(), wz.ravel()], axis=1)
        parts.append(w)
        labs.append(np.full(len(w), HEDGE))
    pts = np.concatenate(parts).astype(np.float32)
    lab = np.concatenate(labs).astype(np.uint8)
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 2.0])
    return m.SemanticCloud(
        stamp_s,
        seq,
        pts,
        lab,
        np.full(len(pts), 0.9, np.float32),
        centre,
        np.array([0.0, 0.0, 0.0, 1.0]),
        "world",
        "camera",
    )


def fixed_request() -> m.PathRequest:
    (sx, sy), (gx, gy) = FIXED_QUERY
    return m.PathRequest("fixed", np.array([sx, sy]), np.array([gx, gy]))


# -- the stack -----------------------------------------------------------------------------------


class Stack:
    """A router in this process and the services as child processes (own process groups, killed
    with this process even by SIGKILL)."""

    def __init__(self, out: Path, config_path: Path, robot: str, sim_robot: str):
        from smana.common.config import ZenohConfig
        from smana.deploy.router import open_router

        self.out, self.config_path = out, config_path
        self.robot, self.sim_robot = robot, sim_robot
        self.endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        zc = ZenohConfig(mode="router", connect=[], listen=[self.endpoint])
        self.session = open_router([self.endpoint], zc)
        self.procs: dict[str, subprocess.Popen] = {}

    def robot_of(self, service: str) -> str:
        if service == "coordinator":
            return FLEET
        return self.sim_robot if service == "sim" else self.robot

    def start(self, name: str) -> None:
        config = self.config_path
        if name == "coordinator":  # a fleet of its own: nothing else talks to it
            config = self.out / "fuzz-coordinator.toml"
        argv = procs.service_argv(name, self.endpoint, self.robot_of(name), "--config", str(config))
        self.procs[name] = procs.spawn(argv, self.out / f"{name}.log", cwd=self.out)

    def log(self, name: str) -> str:
        p = self.out / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def wait_alive(self, names, timeout_s: float) -> None:
        """Live and serving: the alive token, and the kernels loaded (`common.query.ready`)."""
        from smana.common.query import ready

        deadline = time.monotonic() + timeout_s
        for name in names:
            while not ready(self.session, self.robot_of(name), name):
                if self.procs[name].poll() is not None or time.monotonic() > deadline:
                    raise CampaignError(f"{name} did not come up:\n{self.log(name)[-3000:]}")
                time.sleep(0.05)

    def stop_all(self, timeout_s: float = 15.0) -> dict[str, int | None]:
        """Exit codes by service; None for one that did not stop on SIGINT."""
        return dict(zip(self.procs, procs.stop(self.procs.values(), timeout_s), strict=True))

    def close(self) -> None:
        for proc in self.procs.values():
            procs.kill(proc)
        self.session.close()


# -- the campaign --------------------------------------------------------------------------------


class Campaign:
    """One fuzz campaign (see the module docstring). `run()` returns a `Result`; set up failures
    raise `CampaignError`."""

    def __init__(
        self,
        out: Path,
        inputs: int = 10_000,
        seed: int = 0,
        services: tuple[str, ...] = SERVICES,
        oversize: int = 6,
        progress: bool = False,
        startup_timeout_s: float = 600.0,
        settle_timeout_s: float = 120.0,
        robot: str = "fuzz",
        sim_robot: str = "fuzzsim",
        map_files: int = 1000,
        ros2: int = 0,
    ):
        self.out = Path(out)
        self.n_ros2 = ros2
        self.n_map_files = map_files
        self.n_inputs, self.seed = inputs, seed
        self.services = tuple(s for s in SERVICES if s in services)
        self.targets = [
            dataclasses.replace(t, consumers=tuple(c for c in t.consumers if c in self.services))
            for t in TARGETS
            if t.service in self.services
        ]
        self.oversize = oversize
        self.progress = progress
        self.startup_timeout_s, self.settle_timeout_s = startup_timeout_s, settle_timeout_s
        self.robot, self.sim_robot = robot, sim_robot
        self.draw = RandomDraw(random.Random(seed))
        self.result = Result(seed, inputs, list(self.services))
        self.mine: Counter = Counter()  # per service: messages and queries we sent it
        self.pubs: dict[str, object] = {}
        self.base: dict[str, m.ServiceStatus] = {}  # books when the campaign's count starts
        self.base_mine: Counter = Counter()  # self.mine at that moment
        self.base_counters: dict[str, float] = {}
        self.sent = 0
        self.stamp_s = 0.0  # the genuine clock
        self.cloud_seq = 0
        self.accepted_clouds: list[m.SemanticCloud] = []  # for the reference map
        self._t_progress = 0.0
        self._t_phase = time.monotonic()
        self._phase_total = 1
        self._phase_done = 0
        self._phase = ""

    # -- plumbing ---------------------------------------------------------------------------------

    def key(self, t: Target) -> str:
        seg, name = t.topic.split("/", 1)
        return keys.key(t.robot or self.stack.robot_of(t.service), seg, name)

    def publisher(self, t: Target):
        import zenoh

        k = self.key(t)
        if k not in self.pubs:
            pub = self.stack.session.declare_publisher(
                k,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            deadline = time.monotonic() + self.settle_timeout_s
            while not pub.matching_status.matching:
                if time.monotonic() > deadline:
                    raise CampaignError(f"no subscriber for {k}")
                time.sleep(0.02)
            self.pubs[k] = pub
        return self.pubs[k]

    def ask(
        self,
        service: str,
        name: str,
        payload: bytes | None = None,
        encoding=None,
        params: str = "",
        timeout_s: float | None = None,
    ):
        """One query to `smana/<robot>/<service>/<name>`: a list of (ok, bytes) replies, or None
        when zenoh refused the selector in this process."""
        import zenoh

        k = keys.query(self.stack.robot_of(service), service, name)
        sel = f"{k}?{params}" if params else k
        kw = {}
        if payload is not None:
            kw["payload"] = payload
        if encoding is not None:
            kw["encoding"] = zenoh.Encoding(encoding)
        try:
            replies = self.stack.session.get(sel, timeout=timeout_s or self.settle_timeout_s, **kw)
        except Exception:  # noqa: BLE001 - zenoh refuses some selectors before sending them
            return None
        self.mine[service] += 1
        out = []
        for r in replies:
            if r.ok is not None:
                out.append((True, r.ok.payload.to_bytes()))
            else:
                out.append((False, r.err.payload.to_bytes()))
        return out

    def request(self, service: str, name: str, body=None, as_json: bool = False):
        """A query whose answer must come: the decoded reply (a Message or a map)."""
        payload = enc = None
        if isinstance(body, m.Message):
            payload, enc = m.encode(body), "application/msgpack"
        elif body is not None:
            payload, enc = msgpack.packb(body), "application/msgpack"
        replies = self.ask(service, name, payload, enc)
        if not replies:
            raise CampaignError(f"{service}/{name}: no reply")
        ok, data = replies[0]
        parsed = _parse(data)
        if not ok:
            raise CampaignError(f"{service}/{name}: error reply {parsed}")
        return parsed

    def status(self, service: str) -> m.ServiceStatus:
        st = self.request(service, "status")
        if not isinstance(st, m.ServiceStatus):
            raise CampaignError(f"{service}/status: not a ServiceStatus")
        _check(self.result, "books add up in every status", st.books_add_up(), f"{service}: {st}")
        return st

    def settle(self, service: str) -> m.ServiceStatus:
        """Wait until every input sent to `service` so far was handled (all received, none
        pending); timeout counted from the last progress."""
        deadline = time.monotonic() + self.settle_timeout_s
        last = None
        while True:
            st = self.status(service)
            want = 0
            if service in self.base:
                want = self.base[service].msgs_in + self.mine[service] - self.base_mine[service]
            if st.pending == 0 and st.msgs_in >= want:
                return st
            progress = (st.msgs_in - self.mine[service], st.pending)  # our polls are no progress
            if progress != last:
                deadline, last = time.monotonic() + self.settle_timeout_s, progress
            if time.monotonic() > deadline:
                raise CampaignError(f"{service} did not settle: {st}")
            time.sleep(0.002)

    def _tick(self, n: int = 1) -> None:
        self._phase_done += n
        now = time.monotonic()
        if not self.progress or now - self._t_progress < (0.5 if sys.stderr.isatty() else 10.0):
            return
        self._t_progress = now
        done, total = self._phase_done, self._phase_total
        rate = done / max(now - self._t_phase, 1e-6)
        eta = (total - done) / rate if rate > 0 else float("nan")
        line = f"fuzz {self._phase}: {done}/{total} inputs, {rate:.0f}/s, ETA {eta:.0f} s"
        if sys.stderr.isatty():
            print(f"\r{line}   ", end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def _begin(self, phase: str, total: int) -> None:
        if self.progress and sys.stderr.isatty() and self._phase:
            print(file=sys.stderr)
        self._phase, self._phase_total, self._phase_done = phase, max(total, 1), 0
        self._t_phase = time.monotonic()

    # -- the run ----------------------------------------------------------------------------------

    def run(self) -> Result:
        r = self.result
        r.load_start = os.getloadavg()
        t0, cpu0 = time.monotonic(), resource.getrusage(resource.RUSAGE_SELF)
        self.out.mkdir(parents=True, exist_ok=True)
        self.save_dir = self.out / "mapper"
        self.save_dir.mkdir(exist_ok=True)
        config_path = self.config_path = self.out / "fuzz.toml"
        config_path.write_text(CONFIG.format(save_path=self.save_dir / "map.npz"))
        members = json.dumps(list(fuzz_messages.FLEET_MEMBERS))
        (self.out / "fuzz-coordinator.toml").write_text(COORDINATOR_CONFIG.format(members=members))
        self.config = SmanaConfig.load(config_path)
        self.files_before = _files(self.out, exclude=self.save_dir)
        if self.n_map_files:
            self._timed("map_files", lambda: self.map_file_phase(self.n_map_files))
        codes: dict[str, int | None] = {}
        if self.n_inputs:
            codes = self._run_stack()
        for name, code in codes.items():
            sf = r.service_figures.setdefault(name, ServiceFigures())
            sf.exit_code = code
            sf.tracebacks = self.stack.log(name).count("Traceback")
            _check(r, "clean exit on SIGINT", code == 0, f"{name} exited {code}")
        self.check_files()
        if self.n_ros2:
            self._timed("ros2", self.ros2_family)
        r.crashes = sum(
            sf.rejected.get("internal", 0)
            + sum(v for k, v in sf.events.items() if k.startswith("internal"))
            for sf in r.service_figures.values()
        ) + sum(f.crash for f in r.map_files.values())
        if r.ros2 is not None:
            r.crashes += r.ros2.crashes
        r.inputs = self.sent
        r.wall_s = time.monotonic() - t0
        me = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        r.cpu_s = me.ru_utime + me.ru_stime - cpu0.ru_utime - cpu0.ru_stime
        r.cpu_s_services = kids.ru_utime + kids.ru_stime
        r.load_end = os.getloadavg()
        if self.progress and sys.stderr.isatty():
            print(file=sys.stderr)
        return r

    def _run_stack(self) -> dict[str, int | None]:
        """Steps 1 to 6 on the stack; the services' exit codes."""
        r = self.result
        t_stack = time.monotonic()
        self.stack = Stack(self.out, self.config_path, self.robot, self.sim_robot)
        try:
            for name in self.services:
                self.stack.start(name)
            self.stack.wait_alive(self.services, self.startup_timeout_s)
            r.phase_s["startup"] = time.monotonic() - t_stack
            self._timed("establish", self.establish)
            budget = self.n_inputs
            n1 = budget * 2 // 5
            self._timed("refused", lambda: self.phase("refused", n1))
            self._timed("check_refused", self.check_unchanged)
            self._timed("hostile", lambda: self.phase("hostile", budget - n1))
            self._timed("recovery", self.recovery)
            self._timed("final", self.final_checks)
            self._timed("books", self.books)
        finally:
            for pub in self.pubs.values():
                pub.undeclare()
            codes = self.stack.stop_all()
            self.stack.close()
        return codes

    def ros2_family(self) -> None:
        """Step 7: the ROS 2 family, its own router and `smana ros2` (lab/bench/fuzz_ros2.py)."""
        from smana.lab.bench.fuzz_ros2 import Ros2Family, Ros2FuzzError

        family = Ros2Family(
            self.out / "ros2",
            self.n_ros2,
            self.seed,
            oversize=min(self.oversize, 4),  # one per ROS 2 key at most
            startup_timeout_s=self.startup_timeout_s,
            settle_timeout_s=self.settle_timeout_s,
            progress=self.progress,
        )
        try:
            self.result.ros2 = family.run()
        except Ros2FuzzError as exc:
            raise CampaignError(f"ROS 2 family: {exc}") from None

    def _timed(self, name: str, fn) -> None:
        t0 = time.monotonic()
        if self.progress and not sys.stderr.isatty():
            print(f"fuzz: {name} ...", file=sys.stderr, flush=True)
        fn()
        self.result.phase_s[name] = time.monotonic() - t0

    # -- 0. map files (in this process: the loaders, no stack) -----------------------------------

    def map_file_phase(self, n: int) -> None:
        """`n` map files, valid and corrupt (`lab.fuzz_maps`), each loaded as the mapper (or the
        fleet mapper) loads one; every file ends in exactly one counter."""
        import tempfile

        from smana.lab import fuzz_maps

        r = self.result
        bases = fuzz_maps.bases()
        self._begin("map files", n)
        with tempfile.TemporaryDirectory(prefix="smana-fuzz-maps-") as tmp:
            path = Path(tmp) / "map.npz"
            for _ in range(n):
                base = self.draw.choice(bases)
                mutant = fuzz_maps.mutate_map(base, self.draw)
                kind = mutant.how.split(":", 1)[0]
                f = r.map_files.setdefault(kind, MapFileFigures())
                f.inputs += 1
                path.write_bytes(mutant.data)
                out, why = fuzz_maps.try_load(path, base)
                setattr(f, out, getattr(f, out) + 1)
                wrong = (
                    (out == "loaded" and why != "same")
                    or (mutant.predict is True and out != "refused")
                    or (mutant.predict is False and out != "loaded")
                )
                if wrong or out == "crash":
                    f.wrong += int(wrong)
                    if len(r.notes) < 50:
                        r.notes.append(f"map file {base.name} {mutant.how}: {out} ({why})")
                self._tick()
        _check(r, "map files: no crash", all(f.crash == 0 for f in r.map_files.values()))
        _check(
            r,
            "map files: refused or loaded as predicted, a loaded one as saved",
            all(f.wrong == 0 for f in r.map_files.values()),
        )
        _check(
            r,
            "map files: each ends in exactly one counter",
            all(f.inputs == f.loaded + f.refused + f.crash for f in r.map_files.values())
            and sum(f.inputs for f in r.map_files.values()) == n,
        )

    # -- 1. establish -----------------------------------------------------------------------------

    def send_cloud(self, cloud_or_payload, t: Target, genuine: m.SemanticCloud | None = None):
        """Publish one cloud and wait until the mapper settled it; True if it was integrated.
        Exact whatever else the mapper receives meanwhile (navgraph's snapshot queries, all
        accepted): the mapper's clouds + rejected + dropped grow by one, and only by this cloud."""
        payload = (
            m.encode(cloud_or_payload)
            if isinstance(cloud_or_payload, m.Message)
            else cloud_or_payload
        )

        def fates(st):
            return st.details["clouds"] + sum(st.rejected.values()) + sum(st.dropped.values())

        before = self.status("mapper")
        self.publisher(t).put(payload)
        self.mine["mapper"] += 1
        deadline = time.monotonic() + self.settle_timeout_s
        while True:
            st = self.status("mapper")
            if st.pending == 0 and fates(st) > fates(before):
                break
            if time.monotonic() > deadline:
                raise CampaignError(f"the mapper did not settle a cloud: {st}")
            time.sleep(0.002)
        integrated = st.details["clouds"] == before.details["clouds"] + 1
        _check(
            self.result,
            "one cloud, one outcome",
            fates(st) == fates(before) + 1,
            f"mapper books moved by {fates(st) - fates(before)} for one cloud",
        )
        if integrated:
            msg = genuine or m.decode(payload, m.SemanticCloud, drop_nonfinite=True)
            self.accepted_clouds.append(msg)
        return integrated

    def genuine(self, area=AREA, wall=True) -> m.SemanticCloud:
        self.cloud_seq += 1
        self.stamp_s += 0.5
        return genuine_cloud(self.cloud_seq, self.stamp_s, area, wall)

    def establish(self) -> None:
        cloud_t = next(t for t in TARGETS if t.topic == "robot/cloud")
        for name in self.services:
            self.base[name] = self.status(name)
            self.base_mine[name] = self.mine[name]
        self.stamp_s = 10.0
        for _ in range(4):
            c = self.genuine()
            if not self.send_cloud(c, cloud_t, genuine=c):
                raise CampaignError("the mapper refused a genuine cloud")
        self.wait_pipeline()
        reply = self.request("planner", "path", fixed_request())
        if not (isinstance(reply, m.PathReply) and reply.ok):
            raise CampaignError(f"the planner has no path for the fixed query: {reply}")
        self.s0 = self.fingerprints()
        self.applied0 = self.applied()
        snap = self.request("mapper", "snapshot")
        graph = self.request("navgraph", "graph")
        self.ctx = fuzz_messages.Context(
            stamp_s=self.stamp_s,
            seq=self.cloud_seq,
            producers={"mapper": snap.producer, "navgraph": graph.producer},
            map_resolution_m=self.config.mapper.resolution_m,
            graph_resolution_m=self.config.navgraph.resolution_m,
            graph_origin_xy=tuple(graph.origin_xy.tolist()),
            area=AREA,
        )
        # The books start here: everything after is the campaign's and its echoes.
        self.base_counters, self.base, self.base_mine = self.quiet()

    def wait_pipeline(self) -> None:
        """Until navgraph integrated every delta and the planner holds navgraph's last patch."""
        deadline = time.monotonic() + self.settle_timeout_s
        while True:
            ng = self.request("navgraph", "stats")
            ok = ng["deltas"] >= 1
            if "planner" in self.services:
                pl = self.request("planner", "stats")
                ok = ok and pl["last_patch_seq"] == ng["patch_seq"] and pl["nodes_known"] > 0
            if ok:
                return
            if time.monotonic() > deadline:
                raise CampaignError(f"the pipeline did not carry the map: navgraph {ng}")
            time.sleep(0.05)

    def counters(self) -> dict[str, float]:
        """The peers' own counts of what they sent each other (see `books`)."""
        c: dict[str, float] = {}
        if "mapper" in self.services:
            c["mapper.clouds"] = self.settle("mapper").details["clouds"]
        if "navgraph" in self.services:
            ng = self.request("navgraph", "stats")
            c["navgraph.patch_seq"] = ng["patch_seq"]
            c["navgraph.snapshot_queries"] = ng["snapshot_queries"]
        if "planner" in self.services:
            c["planner.graph_queries"] = self.request("planner", "stats")["graph_queries"]
        if "explorer" in self.services:
            d = self.status("explorer").details
            c["explorer.graph_queries"] = d["graph_queries"]
            c["explorer.path_queries"] = d["path_queries"]
        return c

    def quiet(self) -> tuple[dict[str, float], dict[str, m.ServiceStatus], Counter]:
        """Every service settled while no peer sent anything: the peers' counters, the statuses,
        and how many messages the campaign had sent each service when its status was taken."""
        deadline = time.monotonic() + self.settle_timeout_s
        while True:
            before = self.counters()
            sts, mark = {}, Counter()
            for s in self.services:
                sts[s] = self.settle(s)
                mark[s] = self.mine[s]  # the status counts the query that asked for it
            after = self.counters()
            if before == after:
                return after, sts, mark
            if time.monotonic() > deadline:
                raise CampaignError(f"the stack does not go quiet: {before} -> {after}")

    def background(self, counters: dict[str, float]) -> dict[str, int]:
        """What the peers sent each service since the baseline, by their own counts."""
        d = {k: v - self.base_counters.get(k, 0) for k, v in counters.items()}
        return {
            "mapper": d.get("navgraph.snapshot_queries", 0),  # navgraph's resyncs
            "navgraph": d.get("mapper.clouds", 0)  # one MapDelta per integrated cloud
            + d.get("planner.graph_queries", 0)
            + d.get("explorer.graph_queries", 0),
            "planner": d.get("navgraph.patch_seq", 0) + d.get("explorer.path_queries", 0),
            "explorer": d.get("navgraph.patch_seq", 0),
            "sim": 0,  # on its own robot: nothing else talks to it
            "coordinator": 0,  # on the fleet's name, its members the campaign's: the same
        }

    # -- fingerprints -----------------------------------------------------------------------------

    def fingerprints(self) -> dict[str, str]:
        snap = self.request("mapper", "snapshot")
        graph = self.request("navgraph", "graph")
        fp = {
            "mapper": map_fingerprint(
                snap.centres, snap.labels, snap.confidences, snap.occupied, snap.values
            ),
            "navgraph": graph_fingerprint(graph.cells, graph.labels, graph.heights, graph.flags),
        }
        if "planner" in self.services:
            fp["planner"] = reply_fingerprint(self.request("planner", "path", fixed_request()))
        if "coordinator" in self.services:
            claims = self.request("coordinator", "claims")
            fp["coordinator"] = json.dumps([claims["claims"], claims["version"]], sort_keys=True)
        return fp

    # -- 2/3. the phases --------------------------------------------------------------------------

    def plan_inputs(self, n: int, phase: str = "") -> list[Target]:
        """`n` targets drawn by weight (each target at least once), in a random order."""
        targets = [t for t in self.targets if phase != "refused" or t.refused_phase]
        weights = [t.weight for t in targets]
        total = sum(weights)
        counts = [max(1, int(round(n * w / total))) for w in weights]
        plan = [t for t, c in zip(targets, counts) for _ in range(c)]
        self.draw.r.shuffle(plan)
        return plan[:n] if len(plan) > n else plan

    def phase(self, name: str, n: int) -> None:
        plan = self.plan_inputs(n, name)
        self._begin(name, len(plan))
        if name == "refused":  # the oversize payloads go first, they are refused in any phase
            by_name = {t.name: t for t in self.targets}
            big = [by_name[k] for k in OVERSIZE_ORDER if k in by_name][: self.oversize]
            for t in big:
                if t.kind == "query":
                    self.send_query(t, oversize=True)
                else:
                    self.send(t, None, oversize=True)
                self._tick()
        unsettled: Counter = Counter()
        for t in plan:
            if t.kind == "query":
                self.send_query(t)
            else:
                self.send(t, name)
                if t.kind == "fifo":
                    for s in t.services:
                        unsettled[s] += 1
                        if unsettled[s] >= SETTLE_EVERY:
                            self.settle(s)
                            unsettled[s] = 0
            self._tick()
        for s in self.services:
            self.settle(s)

    def refused_input(self, t: Target) -> tuple[bytes, bool]:
        """A payload `t`'s service must refuse: one the codec refuses, or (some of the time) a
        decodable one its handler refuses whatever its state. Returns (payload, decodable)."""
        d, ctx = self.draw, self.ctx
        certain = t.expect in (m.SemanticCloud, m.GraphPatch) or t.name == "navgraph:mapper/delta"
        if certain and d.boolean(0.3):
            msg = fuzz_messages.plausible(t.expect, d, ctx)
            while not _rows(msg):  # an empty one would change nothing even if it got through
                msg = fuzz_messages.plausible(t.expect, d, ctx)
            if t.expect is m.SemanticCloud:
                msg.frame_id = d.choice(("odom", "", "World", "world ", "map", "\x00"))
                return m.encode(msg), True
            if t.expect is m.MapDelta and t.service == "navgraph":
                msg.producer, msg.stamp_s = FOREIGN, ctx.stamp_s
                return m.encode(msg), True
            if t.expect is m.GraphPatch:
                if d.boolean():
                    msg.producer = FOREIGN
                else:
                    msg.resolution_m = d.choice((0.1, 0.2 + 1e-6, 0.25))
                return m.encode(msg), True
        for _ in range(50):
            mut = fuzz_messages.message_payload(
                t.expect, d, ctx, mode=d.choice(("wire", "wire", "bytes"))
            )
            if fuzz_messages.predict(mut.payload, t.expect, drop_nonfinite=t.drop_nonfinite):
                return mut.payload, False
        return b"\xc1", False

    def send(self, t: Target, phase: str | None, oversize: bool = False) -> None:
        kf = self.result.keys.setdefault(t.name, KeyFigures())
        if t.expect is None:  # a member's explorer state, for the coordinator
            payload, _ = fuzz_messages.explorer_state(self.draw, self.ctx)
            if phase == "refused":  # one it must refuse
                for _ in range(50):
                    if fuzz_messages.predict_explorer_state(payload):
                        break
                    payload, _ = fuzz_messages.explorer_state(self.draw, self.ctx)
                else:
                    payload = b"\xc1"
            decodable = None
        elif oversize:
            payload, decodable = (
                fuzz_messages.oversize_payload(t.expect, self.draw.integer(1, 4096)),
                False,
            )
        elif phase == "refused":
            payload, decodable = self.refused_input(t)
        elif t.expect is m.Pose and self.draw.boolean(0.15):  # a track the gates lock onto
            for pose in fuzz_messages.pose_track(self.draw, self.ctx):
                self._put(t, kf, m.encode(pose), None)
            return
        else:
            payload = fuzz_messages.message_payload(t.expect, self.draw, self.ctx).payload
            decodable = None
        self._put(t, kf, payload, decodable)

    def _put(self, t: Target, kf: KeyFigures, payload: bytes, decodable: bool | None) -> None:
        if t.expect is None:
            kind = fuzz_messages.predict_explorer_state(payload)
        else:
            kind = fuzz_messages.predict(payload, t.expect, drop_nonfinite=t.drop_nonfinite)
        kf.inputs += 1
        kf.codec[kind or "accepted"] += 1
        if decodable:
            kf.handler_refusals += 1
        self.sent += 1
        for s in t.services:
            sf = self.result.service_figures.setdefault(s, ServiceFigures())
            if kind:
                sf.predicted[kind] = sf.predicted.get(kind, 0) + 1
        if t.kind == "latest":
            if self.send_cloud(payload, t):
                kf.cloud_accepted += 1
            return
        self.publisher(t).put(payload)
        for s in t.services:
            self.mine[s] += 1

    def send_query(self, t: Target, oversize: bool = False) -> None:
        kf = self.result.keys.setdefault(t.name, KeyFigures())
        service, name = t.topic.split("/", 1)
        case = fuzz_messages.query_case(service, name, self.draw, self.ctx)
        if oversize:
            case = fuzz_messages.QueryCase("", bytes(m.MAX_PAYLOAD_BYTES + 1), None, "oversize")
        replies = self.ask(service, name, case.payload, case.encoding, case.params)
        if replies is None:
            kf.not_sent += 1
            return
        kf.inputs += 1
        self.sent += 1
        sf = self.result.service_figures.setdefault(service, ServiceFigures())
        if not replies:
            kf.replies["no_reply"] += 1
            _check(self.result, "every query answered", False, f"{t.name} {case.how}")
            if case.payload is not None and len(case.payload) > m.MAX_PAYLOAD_BYTES:
                # counted all the same (common/service.py refuses it before it can answer)
                sf.predicted["oversize"] = sf.predicted.get("oversize", 0) + 1
            return
        ok, data = replies[0]
        as_json = _asks_json(case.encoding, case.params)
        try:
            body = json.loads(data) if as_json else msgpack.unpackb(data, strict_map_key=False)
        except Exception:  # noqa: BLE001
            _check(
                self.result,
                "replies in the query's encoding",
                False,
                f"{t.name} ({'json' if as_json else 'msgpack'}): {data[:80]!r}",
            )
            body = None
        kind = None
        if not ok:
            kind = body.get("error", "?") if isinstance(body, dict) else "?"
        elif (service, name) == ("planner", "path"):
            kind = _path_rejection(case, as_json)
        kf.replies[kind or "ok"] += 1
        if kind:
            sf.predicted[kind] = sf.predicted.get(kind, 0) + 1
        if kind == "internal":
            self.result.notes.append(f"internal error on {t.name}: {case.how}: {body}")

    # -- checks -----------------------------------------------------------------------------------

    def force_resync(self) -> None:
        """navgraph rebuilds its graph from the mapper's snapshot, then the planner fetches it:
        both refuse a message from a foreign producer and ask their source again."""
        if "navgraph" in self.services:
            before = self.request("navgraph", "stats")["resyncs"]
            t = next(t for t in self.targets if t.name == "navgraph:mapper/delta")
            delta = fuzz_messages.plausible(m.MapDelta, self.draw, self.ctx)
            delta.producer, delta.stamp_s, delta.seq = FOREIGN, self.stamp_s, 1
            self._wait_counter(t, m.encode(delta), "navgraph", "resyncs", before)
        if "planner" in self.services:
            before = self.request("planner", "stats")["syncs"]
            t = next(t for t in self.targets if t.name == "planner:navgraph/patch")
            patch = fuzz_messages.plausible(m.GraphPatch, self.draw, self.ctx)
            patch.producer, patch.seq = FOREIGN, 1
            self._wait_counter(t, m.encode(patch), "planner", "syncs", before)

    def _wait_counter(self, t: Target, payload: bytes, service: str, counter: str, before: int):
        kf = self.result.keys.setdefault(t.name, KeyFigures())
        kf.inputs += 1
        kf.codec["accepted"] += 1
        kf.handler_refusals += 1
        self.sent += 1
        self.publisher(t).put(payload)
        for s in t.services:
            self.mine[s] += 1
        deadline = time.monotonic() + self.settle_timeout_s
        while self.request(service, "stats")[counter] <= before:
            if time.monotonic() > deadline:
                raise CampaignError(f"{service} did not {counter[:-1]} after a foreign message")
            time.sleep(0.02)

    def applied(self) -> dict[str, int]:
        """How often each service changed its state from a message: clouds integrated, deltas
        integrated, patches published, patches applied. A resync repairs a graph that refused
        input corrupted, so these counts are what can tell."""
        out = {"mapper.clouds": self.status("mapper").details["clouds"]}
        if "navgraph" in self.services:
            ng = self.request("navgraph", "stats")
            out["navgraph.deltas"], out["navgraph.patch_seq"] = ng["deltas"], ng["patch_seq"]
        if "planner" in self.services:
            out["planner.patches"] = self.request("planner", "stats")["patches"]
        return out

    def check_unchanged(self) -> None:
        """After the refused phase: nothing was applied anywhere, the map is the same; and after
        a forced resync and sync, the graph and the planner's answer are the same too."""
        self.quiet()
        applied = self.applied()
        for k, v in self.applied0.items():
            _check(
                self.result,
                f"nothing applied from refused input ({k.split('.')[0]})",
                applied[k] == v,
                f"{k}: {v} -> {applied[k]}",
            )
        s0, s1 = self.s0, self.fingerprints()
        for k in s0:
            _check(
                self.result,
                f"state unchanged by refused input ({k})",
                s1[k] == s0[k],
                f"{s0[k]} -> {s1[k]}",
            )
        self.force_resync()
        self.quiet()
        s2 = self.fingerprints()
        for k in ("navgraph", "planner"):
            if k in s0:
                _check(
                    self.result,
                    f"the same state after a forced resync ({k})",
                    s2[k] == s0[k],
                    f"{s0[k]} -> {s2[k]}",
                )

    def recovery(self) -> None:
        """Genuine clouds until they reach navgraph's graph. The stream may be in doubt: a stamp
        gate locked onto a hostile clock lets go after RELOCK consistent stamps; a follower
        moved by a spoofed sequence number refuses genuine deltas until its resync (a tick
        later), which the loop waits for."""
        cloud_t = next(t for t in self.targets if t.name == "mapper:robot/cloud")
        x0, y0, x1, y1 = RECOVERY_AREA
        probe = {"x": (x0 + x1) / 2, "y": (y0 + y1) / 2}
        limit = 2 * RELOCK + 3  # the mapper's gate, then navgraph's, may each need RELOCK
        t0 = time.monotonic()
        for n in range(1, limit + 1):
            resyncs = self.request("navgraph", "stats")["resyncs"]
            doubt0 = self._doubts()
            c = self.genuine(RECOVERY_AREA, wall=False)  # the genuine clock goes on
            self.send_cloud(c, cloud_t, genuine=c)
            self.quiet()  # the delta (if any) reached navgraph, its patch the planner
            if self._doubts() > doubt0:  # refused as out of sequence: wait for the resync
                deadline = time.monotonic() + self.settle_timeout_s
                while self.request("navgraph", "stats")["resyncs"] <= resyncs:
                    if time.monotonic() > deadline:
                        raise CampaignError("navgraph did not resync after a refused delta")
                    time.sleep(0.02)
                self.quiet()
            if self.request("navgraph", "node", probe).get("known"):
                self.result.recovery_clouds = n
                break
        self.result.phase_s["recovery_to_graph"] = time.monotonic() - t0
        _check(
            self.result,
            "genuine input flows again after the fuzz",
            self.result.recovery_clouds > 0,
            f"not after {limit} genuine clouds",
        )

    def _doubts(self) -> int:
        """navgraph's refusals that ask for a resync."""
        rej = self.status("navgraph").rejected
        return rej.get("sequence", 0) + rej.get("producer", 0)

    def final_checks(self) -> None:
        from smana.common.classes import ClassTable
        from smana.services.mapper.takeover import build_map

        r = self.result
        table = ClassTable.load(self.config.general.class_table)
        ref = build_map(self.config, table)
        for c in self.accepted_clouds:
            _reference_integrate(ref, table, c)
        rows = ref.occupied_voxels()
        snap = self.request("mapper", "snapshot")
        want = map_fingerprint(
            rows.centres, rows.labels, rows.confidences, rows.occupied, rows.values
        )
        got = map_fingerprint(
            snap.centres, snap.labels, snap.confidences, snap.occupied, snap.values
        )
        _check(
            r,
            "mapper map == reference fed the accepted clouds",
            got == want,
            f"{len(snap.centres)} voxels vs {len(rows.centres)} in the reference",
        )
        if "navgraph" not in self.services:
            return
        self.force_resync()
        for s in self.services:
            self.settle(s)
        graph = self.request("navgraph", "graph")
        ref_graph = _reference_graph(self.config, table, self.request("mapper", "snapshot"))
        _check(
            r,
            "navgraph graph == core fed the mapper's snapshot",
            graph_fingerprint(graph.cells, graph.labels, graph.heights, graph.flags)
            == graph_fingerprint(*ref_graph),
            f"{len(graph.cells)} nodes vs {len(ref_graph[0])} in the reference",
        )
        if "planner" in self.services:
            got = self.request("planner", "path", fixed_request())
            want = _reference_plan(self.config, table, graph, fixed_request())
            _check(
                r,
                "planner answer == core on navgraph's graph",
                reply_fingerprint(got) == reply_fingerprint(want),
                f"{got.ok} {got.cost_total} vs {want.ok} {want.cost_total}",
            )

    def books(self) -> None:
        """Once the stack is quiet: every service's books against what was sent to it."""
        r = self.result
        counters, sts, mark = self.quiet()
        background = self.background(counters)
        for s, st in sts.items():
            b = self.base[s]
            sf = r.service_figures.setdefault(s, ServiceFigures())
            sf.pid = st.pid
            sf.mine, sf.background = mark[s] - self.base_mine[s], int(background[s])
            sf.msgs_in = st.msgs_in - b.msgs_in
            sf.accepted = st.accepted - b.accepted
            sf.dropped = _diff(st.dropped, b.dropped)
            sf.rejected = _diff(st.rejected, b.rejected)
            sf.events = _diff(st.events, b.events)
            _check(
                r,
                "same process (no restart)",
                st.pid == self.stack.procs[s].pid,
                f"{s}: pid {st.pid}",
            )
            _check(
                r,
                "msgs_in = inputs + queries + peers' messages",
                sf.msgs_in == sf.mine + sf.background,
                f"{s}: {sf.msgs_in} received, {sf.mine} sent by the campaign + "
                f"{sf.background} by its peers",
            )
            settled = sf.accepted + sum(sf.dropped.values()) + sum(sf.rejected.values())
            _check(
                r,
                "every message settled",
                settled == sf.msgs_in and st.pending == 0,
                f"{s}: {settled} settled of {sf.msgs_in}, {st.pending} pending",
            )
            for kind in set(sf.rejected) | set(sf.predicted):
                got, want = sf.rejected.get(kind, 0), sf.predicted.get(kind, 0)
                if kind in STRUCTURAL:
                    _check(
                        r,
                        "structural rejections == codec's prediction",
                        got == want,
                        f"{s}: {kind} {got} counted, {want} predicted",
                    )
                elif kind != "internal":
                    _check(
                        r,
                        "other rejections >= predicted",
                        got >= want,
                        f"{s}: {kind} {got} counted, {want} at least predicted",
                    )
            if self.stack.procs[s].poll() is not None:
                _check(r, "alive after the fuzz", False, f"{s} exited")

    def check_files(self) -> None:
        """A save query writes in the mapper's save folder only."""
        new = _files(self.out, exclude=self.save_dir) - self.files_before
        new = {p for p in new if not p.endswith(".log")}
        _check(self.result, "no file written outside the save folder", not new, str(sorted(new)))
        names = sorted(p.name for p in self.save_dir.iterdir())
        self.result.notes.append(f"files in the mapper's save folder: {names}")


# -- helpers -------------------------------------------------------------------------------------


def _parse(data: bytes):
    from smana.common.query import QueryError, parse_reply

    try:
        return parse_reply(data)
    except QueryError as exc:
        raise CampaignError(str(exc)) from None


def _asks_json(encoding: str | None, params: str) -> bool:
    """As `common/service.py` decides it: a JSON or text encoding, or `format=json`."""
    enc = encoding or ""
    pairs = dict(p.split("=", 1) if "=" in p else (p, "") for p in params.split(";") if p)
    return enc.startswith(("application/json", "text/")) or pairs.get("format") == "json"


def _path_rejection(case: fuzz_messages.QueryCase, as_json: bool) -> str | None:
    """The kind the planner counts a path query under (it answers refused requests with an
    ordinary PathReply, so the reply does not say): as `PlannerService.on_path` decides."""
    from smana.services.planner.service import request_from_params

    try:
        if case.payload:
            if as_json:
                m.from_json(case.payload, m.PathRequest)
            else:
                m.decode(case.payload, m.PathRequest)
        else:
            pairs = dict(p.split("=", 1) for p in case.params.split(";") if "=" in p)
            request_from_params(pairs)
    except m.MessageError as exc:
        return exc.kind
    return None


def _reference_integrate(ref, table, cloud: m.SemanticCloud) -> None:
    """What `MapperService.on_cloud` does with a cloud it accepts, on the reference map."""
    labels, _ = table.sanitise(cloud.labels)
    conf = cloud.confidences
    if conf.size and (conf.min() < 0 or conf.max() > 1):
        conf = np.clip(conf, 0.0, 1.0)
    ref.integrate(cloud.points, labels, conf, cloud.sensor_position)


def _reference_graph(config: SmanaConfig, table, snap: m.MapDelta):
    from smana.services.navgraph.graph import NavGraph
    from smana.services.navgraph.service import to_patch

    g = NavGraph(table, config.navgraph)
    g.integrate_delta(snap)
    p = to_patch(g, *g.export(), seq=0, stamp_s=0.0)  # the wire form navgraph itself sends
    return p.cells, p.labels, p.heights, p.flags


def _reference_plan(config: SmanaConfig, table, graph: m.GraphPatch, req) -> m.PathReply:
    from smana.common.navgrid import NavGrid
    from smana.services.planner.planner import Planner
    from smana.services.planner.service import reply_of

    nc = config.navgraph
    grid = NavGrid.from_bounds(nc.bounds_min_xy, nc.bounds_max_xy, nc.resolution_m, nc.tile_size)
    grid.apply_patch(graph.cells, graph.labels, graph.heights, graph.flags)
    return reply_of(req.request_id, Planner(grid, table, config.planner).plan_request(req))


def _rows(msg: m.Message) -> int:
    for name in ("points", "centres", "cells"):
        if hasattr(msg, name):
            return len(getattr(msg, name))
    return 1


def _diff(now: dict, before: dict) -> dict:
    out = {k: now.get(k, 0) - before.get(k, 0) for k in set(now) | set(before)}
    return {k: v for k, v in sorted(out.items()) if v}


def _files(root: Path, exclude: Path) -> set[str]:
    out = set()
    for dirpath, _dirs, names in os.walk(root):
        if Path(dirpath).resolve().is_relative_to(exclude.resolve()):
            continue
        out |= {str(Path(dirpath, n).relative_to(root)) for n in names}
    for p in (root.parent / "escape.npz", Path("/tmp/escape.npz")):
        if p.exists():
            out.add(str(p))
    return out


# -- the report ----------------------------------------------------------------------------------


def table(r: Result) -> str:
    n_ros2 = r.ros2.inputs if r.ros2 is not None else 0
    lines = [
        f"smana bench fuzz: seed {r.seed}, {r.inputs + r.map_inputs + n_ros2} inputs: {r.inputs} "
        f"over {', '.join(r.services) if r.inputs else 'no stack'}, {r.map_inputs} map files, "
        f"{n_ros2} to smana ros2",
        "",
    ]
    lines.append(
        "| service:key | inputs | codec refuses (by kind) | accepted by codec | query replies |"
    )
    lines.append("|---|---:|---|---:|---|")
    for name, k in sorted(r.keys.items()):
        refused = ", ".join(
            f"{kind} {n}" for kind, n in sorted(k.codec.items()) if kind != "accepted"
        )
        replies = ", ".join(f"{kind} {n}" for kind, n in sorted(k.replies.items()))
        acc = k.codec.get("accepted", 0) if k.codec else "-"
        if k.cloud_accepted:
            acc = f"{acc} ({k.cloud_accepted} integrated)"
        lines.append(f"| {name} | {k.inputs} | {refused or '-'} | {acc} | {replies or '-'} |")
    lines += [
        "",
        "| service | received | sent by fuzz | by peers | accepted | dropped | "
        "rejected (by kind) | crashes | exit |",
        "|---|---:|---:|---:|---:|---|---|---:|---:|",
    ]
    for name, s in sorted(r.service_figures.items()):
        rej = ", ".join(f"{k} {v}" for k, v in sorted(s.rejected.items()))
        drop = ", ".join(f"{k} {v}" for k, v in sorted(s.dropped.items())) or "0"
        crashes = s.rejected.get("internal", 0) + sum(
            v for k, v in s.events.items() if k.startswith("internal")
        )
        lines.append(
            f"| {name} | {s.msgs_in} | {s.mine} | {s.background} | {s.accepted} | "
            f"{drop} | {rej or '-'} | {crashes} | {s.exit_code} |"
        )
    if r.map_files:
        lines += [
            "",
            "| map file | inputs | loaded (as saved) | refused (one line) | crash | wrong |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for kind, f in sorted(r.map_files.items()):
            lines.append(
                f"| {kind} | {f.inputs} | {f.loaded} | {f.refused} | {f.crash} | {f.wrong} |"
            )
    if r.ros2 is not None:
        from smana.lab.bench.fuzz_ros2 import table as ros2_table

        lines += ["", ros2_table(r.ros2)]
    lines += ["", "| check | result |", "|---|---|"]
    lines += [f"| {k} | {'pass' if v else 'FAIL'} |" for k, v in r.checks.items()]
    lines += [
        "",
        f"crashes: {r.crashes}; genuine clouds to recover: {r.recovery_clouds}",
        f"wall {r.wall_s:.1f} s (" + ", ".join(f"{k} {v:.1f}" for k, v in r.phase_s.items()) + ")",
        f"CPU {r.cpu_s:.1f} s (campaign, with the router) + {r.cpu_s_services:.1f} s "
        f"(services); load average {_load(r.load_start)} at start, "
        f"{_load(r.load_end)} at the end",
    ]
    if r.notes:
        lines += ["", "notes:"] + [f"- {n}" for n in r.notes]
    lines.append("")
    lines.append("PASS" if r.ok else "FAIL")
    return "\n".join(lines)


def _load(la) -> str:
    return "/".join(f"{x:.2f}" for x in la) if la else "?"


def _campaign_cli(p, args) -> int:
    from smana.common.cli import output_dir

    total = len(fuzz_campaign.FAMILIES) * fuzz_campaign.QUICK_INPUTS if args.quick else None
    total = total or args.campaign
    if args.resume:
        run_dir = Path(args.resume)
        spec = run_dir / "campaign-spec.json"
        if not spec.is_file():
            p.error(f"--resume: {run_dir} holds no campaign (no campaign-spec.json)")
        was = json.loads(spec.read_text())
        total, args.seed, args.chunk = was["total"], was["seed"], was["chunk"]
    else:
        if not total:
            p.error("--campaign: give a number of inputs over 0 (or --quick)")
        stamp = time.strftime("%Y%m%d-%H%M%S")
        run_dir = output_dir(Path(args.out) / f"campaign-{stamp}", "output folder", "--out")
    if args.chunk < 1 or args.hang_s <= 0:
        p.error("--chunk and --hang-s must be over 0")
    s = fuzz_campaign.campaign(
        run_dir,
        total,
        args.seed,
        args.chunk,
        args.hang_s,
        args.plant,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    text = fuzz_campaign.table(s)
    print(text)
    (run_dir / "campaign.md").write_text(text + "\n")
    verdict = "ok" if s["ok"] else "FAILED: a crash, a hang or counters that do not add up"
    print(f"\n{verdict} ({s['seconds']} s); written: {run_dir / 'campaign.json'}")
    return 0 if s["ok"] else 1


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import ArgumentParser, non_negative_int, output_dir

    p = ArgumentParser(
        prog="smana bench fuzz",
        description=doc_summary(__doc__),
        epilog=(
            "Duration measured once on a 2-core machine: about 1.5 minutes for the default "
            "10,000 inputs (a stack without the sim; docs/benchmarks.md), plus 10 to 20 s for the "
            "default 1,000 map files, plus 10 to 15 s for the default 2,000 ROS 2 inputs (10,000 "
            "took 30 to 51 s); --inputs 300 --map-files 0 --ros2 0 takes 10 to 20 s."
        ),
    )
    p.add_argument(
        "--inputs",
        type=non_negative_int,
        default=10_000,
        help="fuzzed inputs to the stack (default 10000; 0: no stack)",
    )
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--services",
        default=",".join(SERVICES),
        help=f"a subset of {','.join(SERVICES)} (default: all)",
    )
    p.add_argument(
        "--oversize",
        type=non_negative_int,
        default=6,
        help="payloads over 64 MiB to send (default 6; they cost memory)",
    )
    p.add_argument(
        "--map-files",
        type=non_negative_int,
        default=1000,
        help="map files, valid and corrupt, to load in this process (default 1000; 0: none)",
    )
    p.add_argument(
        "--ros2",
        type=non_negative_int,
        default=2000,
        help="hostile ROS 2 inputs (/odom, /points, /tf_static, GetPlan) to smana ros2 on a "
        "router of its own, after the stack (default 2000; 0: none)",
    )
    p.add_argument("--out", default="runs/fuzz", help="folder for logs and fuzz.json")
    p.add_argument(
        "--campaign",
        type=non_negative_int,
        metavar="N",
        help="instead of the stack: N inputs over every family (zenoh keys and selectors, "
        "smana's messages, map files, journals, block files, ROS 2 topics, actions and smana's "
        "messages into the ROS 2 bridge), in chunks, each input ending in one counter; "
        "lab/bench/fuzz_campaign.py",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"the campaign with {fuzz_campaign.QUICK_INPUTS} inputs per family (seconds)",
    )
    p.add_argument(
        "--chunk",
        type=non_negative_int,
        default=fuzz_campaign.DEFAULT_CHUNK,
        help=f"campaign inputs per worker process (default {fuzz_campaign.DEFAULT_CHUNK})",
    )
    p.add_argument(
        "--resume",
        metavar="DIR",
        help="go on with the campaign in DIR (a run folder it wrote): done chunks are kept",
    )
    p.add_argument(
        "--hang-s",
        type=float,
        default=60.0,
        help="campaign: an input not answered within this many seconds is a hang (default 60)",
    )
    p.add_argument("--plant", default="", help=argparse.SUPPRESS)  # the tests: FAMILY:I:crash
    args = p.parse_args(argv)
    if args.campaign is not None or args.quick or args.resume:
        return _campaign_cli(p, args)
    services = tuple(s.strip() for s in args.services.split(",") if s.strip())
    unknown = set(services) - set(SERVICES)
    if not (args.inputs or args.map_files or args.ros2):
        p.error("nothing to fuzz: --inputs, --map-files and --ros2 are all 0")
    if args.ros2:
        try:
            import rosbags  # noqa: F401 - the ROS 2 family's message types and CDR
        except ImportError:
            p.error("--ros2 needs the 'rosbags' package: pip install 'smana[ros2]' (or --ros2 0)")
    if unknown or (args.inputs and not {"mapper", "navgraph"} <= set(services)):
        p.error(f"--services: the mapper and navgraph are needed; known: {','.join(SERVICES)}")
    run_dir = output_dir(Path(args.out) / time.strftime("%Y%m%d-%H%M%S"), "output folder", "--out")
    campaign = Campaign(
        run_dir,
        args.inputs,
        args.seed,
        services,
        args.oversize,
        progress=True,
        map_files=args.map_files,
        ros2=args.ros2,
    )
    try:
        result = campaign.run()
    except CampaignError as exc:
        print(f"smana bench fuzz: the campaign could not run: {exc}", file=sys.stderr)
        return 1
    text = table(result)
    print(text)
    (run_dir / "fuzz.md").write_text(text + "\n")
    (run_dir / "fuzz.json").write_text(json.dumps(result.to_json(), indent=1, default=str))
    print(f"\nwritten: {run_dir / 'fuzz.json'}")
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(cli())
