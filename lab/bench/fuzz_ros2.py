"""The ROS 2 family of `smana bench fuzz` (issue 25, `--ros2 N`): `smana ros2` reading a robot's
topics (`ros2.robot_input = on`) runs as its own process against a zenoh router in this process
(free loopback port, multicast scouting and gossip off); this process is the ROS 2 robot and
client. It publishes on the rmw_zenoh keys of `/odom`, `/points` and `/tf_static` and asks the
GetPlan service, with the cases of `lab/fuzz_ros2.py` (genuine, mutated CDR, wild values, bad
attachments), and a stand-in planner answers the service's path queries with a fixed path.

Each case's fate is predicted by `Ros2Reference` at the moment it is sent; a cloud (latest wins)
is sent only when everything before it was handled and waited for, so nothing is dropped
`stale` and the order is the reference's. Checks: no crash (no `internal` rejection or event, no
traceback, the same pid, exit 0 on SIGINT); the books add up to exactly the inputs, the plan
and status queries and the service's own poses echoed on `robot/pose`; every rejection kind and
the accepted count as predicted, and the service's `received` counters as the reference's; after
the fuzz a genuine Odometry still reaches `robot/pose` and a genuine GetPlan is answered with the
planner's path and the asker's sequence number and gid.
"""

from __future__ import annotations

import os
import random
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from smana.common import keys
from smana.common import messages as m
from smana.common.zenoh_config import free_loopback_port
from smana.lab import fuzz_ros2
from smana.lab.bench import procs

TOPIC_WEIGHTS = {"odom": 4, "cloud": 3, "tf_static": 1, "plan": 2}
HIJACK_ONE_IN = 150  # a burst of odometry on another clock and place, about this often
HISTORY = 20  # replies of a hostile /tf_static cache to the service's history query
SETTLE_EVERY = 100  # FIFO inputs before waiting for the service to catch up
RELOCK = 5  # the gates' default: consistent messages that move an established clock or place
PLANNER_PATH = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [2.0, 1.0, 0.0]], np.float32)
CONFIG = """\
[general]
status_period_s = 1.0

[deploy.sim]
enabled = false

[ros2]
robot_input = "on"
min_range_m = 0.0
"""


class Ros2FuzzError(RuntimeError):
    """The service could not be set up or did not answer: the family could not run."""


@dataclass
class Ros2Figures:
    inputs: int = 0
    by_kind: dict = field(default_factory=dict)  # "topic:kind" -> inputs
    fates: dict = field(default_factory=dict)  # "topic:fate" -> inputs, as predicted
    kind_fates: dict = field(default_factory=dict)  # "topic:kind" -> {fate: inputs}
    intent_held: int = 0  # cases whose fate the generator knew, and the reference agreed
    status_polls: int = 0
    echoes: int = 0  # accepted odometry seen on robot/pose
    plan_replies: Counter = field(default_factory=Counter)  # "ok" / "err" / "none"
    history: dict = field(default_factory=dict)  # /tf_static history replies: taken / refused
    msgs_in: int = 0
    accepted: int = 0
    dropped: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    predicted: dict = field(default_factory=dict)  # rejection kinds, by the reference
    events: dict = field(default_factory=dict)
    received: dict = field(default_factory=dict)  # the service's `received` details
    received_predicted: dict = field(default_factory=dict)
    crashes: int = 0
    tracebacks: int = 0
    exit_code: int | None = None
    checks: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    wall_s: float = 0.0
    load_start: tuple = ()
    load_end: tuple = ()

    @property
    def ok(self) -> bool:
        return self.crashes == 0 and bool(self.checks) and all(self.checks.values())

    def check(self, name: str, ok: bool, note: str = "") -> bool:
        self.checks[name] = bool(self.checks.get(name, True) and ok)
        if not ok and note:
            self.notes.append(f"{name}: {note}")
        return ok


class Ros2Family:
    """One run of the ROS 2 family; `run()` returns `Ros2Figures` (raises `Ros2FuzzError` when
    the service does not come up or stops answering)."""

    def __init__(
        self,
        out: Path,
        inputs: int = 2000,
        seed: int = 0,
        robot: str = "fuzzros2",
        oversize: int = 1,
        startup_timeout_s: float = 300.0,
        settle_timeout_s: float = 60.0,
        progress: bool = False,
    ):
        from smana.lab.fuzz_values import RandomDraw

        self.out, self.n, self.seed, self.robot = Path(out), inputs, seed, robot
        self.startup_timeout_s, self.settle_timeout_s = startup_timeout_s, settle_timeout_s
        self.progress = progress
        self.n_oversize = oversize
        self.draw = RandomDraw(random.Random(seed))
        self.fig = Ros2Figures()
        self.mine = 0  # samples and queries sent to the service (status polls included)
        self.fifo_since_settle = 0
        self.poses: list[m.Pose] = []

    # -- plumbing --------------------------------------------------------------------------------

    def status(self) -> m.ServiceStatus:
        from smana.common.query import QueryError, request

        try:
            st = request(self.session, keys.status(self.robot, "ros2"), None, 10.0)
        except QueryError as exc:
            raise Ros2FuzzError(f"ros2/status: {exc}") from None
        self.mine += 1
        self.fig.status_polls += 1
        return st

    def settle(self) -> m.ServiceStatus:
        """Until every input sent so far (and every pose the service echoed to itself) was
        handled; the timeout counts from the last progress."""
        deadline, last = time.monotonic() + self.settle_timeout_s, None
        while True:
            st = self.status()
            want = self.base.msgs_in + self.mine + self.ref.received["odometry"]
            if st.pending == 0 and st.msgs_in >= want:
                self.fifo_since_settle = 0
                return st
            progress = (st.msgs_in - self.mine, st.pending)
            if progress != last:
                deadline, last = time.monotonic() + self.settle_timeout_s, progress
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise Ros2FuzzError(f"ros2 did not settle: {st}\n{self.log()[-3000:]}")
            time.sleep(0.002)

    def log(self) -> str:
        p = self.out / "ros2.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def send(self, case: fuzz_ros2.Ros2Case) -> list:
        """Predict, then put the case on the wire; a GetPlan waits for its replies (returned)."""
        f = self.fig
        if case.topic == "cloud" and self.fifo_since_settle:
            self.settle()  # the odometry before it handled first, as the reference had it
        fate = self.ref.fate(case)
        f.inputs += 1
        key = f"{case.topic}:{case.kind}"
        f.by_kind[key] = f.by_kind.get(key, 0) + 1
        f.fates[f"{case.topic}:{fate}"] = f.fates.get(f"{case.topic}:{fate}", 0) + 1
        kf = f.kind_fates.setdefault(key, {})
        kf[fate] = kf.get(fate, 0) + 1
        if fate != "accepted":
            f.predicted[fate] = f.predicted.get(fate, 0) + 1
        if case.refuse is not None:
            held = case.refuse == (fate != "accepted")
            f.intent_held += held
            f.check(
                "the reference agrees with the generator where it knows",
                held,
                f"{case.topic} {case.kind} {case.how}: {fate}",
            )
        self.mine += 1
        if case.topic == "plan":
            return self._ask_plan(case)
        self.pubs[case.topic].put(case.payload, attachment=case.attachment)
        if case.topic == "cloud":
            self.settle()
        else:
            self.fifo_since_settle += 1
            if self.fifo_since_settle >= SETTLE_EVERY:
                self.settle()
        return []

    def _ask_plan(self, case) -> list:
        kw = {"payload": case.payload}
        if case.attachment is not None:
            kw["attachment"] = case.attachment
        replies = list(self.session.get(self.plan_key, timeout=self.settle_timeout_s, **kw))
        kind = "none" if not replies else ("ok" if replies[0].ok is not None else "err")
        self.fig.plan_replies[kind] += 1
        if kind == "none":
            self.fig.check("every GetPlan answered", False, f"{case.kind} {case.how}")
        return replies

    def _planner(self, query) -> None:
        """The stand-in planner: a fixed path for any request it can read."""
        try:
            req = m.decode(query.payload.to_bytes(), m.PathRequest)
            reply = m.PathReply(request_id=req.request_id, ok=True, path=PLANNER_PATH)
            query.reply(str(query.key_expr), m.encode(reply))
        except Exception:  # noqa: BLE001 - the service asks only with what it could encode
            pass

    # -- the run ---------------------------------------------------------------------------------

    def run(self) -> Ros2Figures:
        from smana.common.config import SmanaConfig, ZenohConfig
        from smana.common.query import ready
        from smana.deploy.router import open_router
        from smana.services.ros2 import rmw

        f = self.fig
        f.load_start = os.getloadavg()
        t0 = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
        config_path = self.out / "fuzz-ros2.toml"
        config_path.write_text(CONFIG)
        config = SmanaConfig.load(config_path)
        types = rmw.RosTypes()
        self.ref = fuzz_ros2.Ros2Reference(config, types)
        self.inputs = fuzz_ros2.Ros2Inputs(types, self.draw, time.time())
        endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        self.session = open_router([endpoint], ZenohConfig(mode="router", listen=[endpoint]))
        declared = []
        try:
            declared.append(
                self.session.declare_queryable(keys.path_query(self.robot), self._planner)
            )
            declared.append(
                self.session.declare_subscriber(
                    keys.pose(self.robot),
                    lambda s: self.poses.append(m.decode(s.payload.to_bytes(), m.Pose)),
                )
            )
            declared.append(self._history_cache(types, config))
            argv = procs.service_argv("ros2", endpoint, self.robot, "--config", str(config_path))
            self.proc = procs.spawn(argv, self.out / "ros2.log", cwd=self.out)
            deadline = time.monotonic() + self.startup_timeout_s
            while not ready(self.session, self.robot, "ros2"):
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise Ros2FuzzError(f"ros2 did not come up:\n{self.log()[-3000:]}")
                time.sleep(0.05)
            self._declare(types, config, declared)
            self.base = self.status()
            self.mine = self.fig.status_polls = 0  # that poll is in the base's books
            self._establish()
            self._fuzz()
            self._after()
            self._books()
        finally:
            for d in declared:
                try:
                    d.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            if getattr(self, "proc", None) is not None:
                (code,) = procs.stop([self.proc], 15.0)
                procs.kill(self.proc)
                f.exit_code = code
            self.session.close()
        f.tracebacks = self.log().count("Traceback")
        f.check("clean exit on SIGINT", f.exit_code == 0, f"exited {f.exit_code}")
        f.check("no traceback in the log", f.tracebacks == 0, f"{f.tracebacks} tracebacks")
        f.crashes += len(self.ref.crashes) + f.tracebacks
        f.notes += [f"reference crash: {c}" for c in self.ref.crashes[:10]]
        f.wall_s = time.monotonic() - t0
        f.load_end = os.getloadavg()
        return f

    def _history_cache(self, types, config):
        """A hostile transient-local /tf_static publisher's cache: what the service's history
        query at start-up gets (`HISTORY` replies, genuine and mutated), predicted as taken or
        refused (events `history_taken`, `history_refused`: a reply is no sample in the books)."""
        from smana.services.ros2 import rmw

        typename = fuzz_ros2.TYPES_OF["tf_static"]
        rc = config.ros2
        tf_key = rmw.data_key(rc.domain_id, rc.tf_static_topic, typename, types.hash(typename))
        cases = [self.inputs.case("tf_static") for _ in range(HISTORY)]
        f = self.fig
        for case in cases:  # handled in the service's set-up, before any live input
            fate = self.ref.fate(case)
            what = "history_taken" if fate == "accepted" else "history_refused"
            f.history[what] = f.history.get(what, 0) + 1

        def answer(query):
            for i, case in enumerate(cases):  # a key each: replies on one key are consolidated
                query.reply(f"{tf_key}/@adv/pub/fuzz/{i}", case.payload)

        return self.session.declare_queryable(f"{tf_key}/@adv/pub/fuzz/**", answer)

    def _declare(self, types, config, declared) -> None:
        """The robot's publishers on rmw_zenoh's keys, matched by the service's subscribers."""
        import zenoh

        from smana.services.ros2 import rmw

        rc = config.ros2
        self.pubs = {}
        for topic, name in (
            ("odom", rc.odom_topic),
            ("cloud", rc.cloud_topic),
            ("tf_static", rc.tf_static_topic),
        ):
            typename = fuzz_ros2.TYPES_OF[topic]
            key = rmw.data_key(rc.domain_id, name, typename, types.hash(typename))
            pub = self.session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            declared.append(pub)
            deadline = time.monotonic() + self.settle_timeout_s
            while not pub.matching_status.matching:
                if time.monotonic() > deadline:
                    raise Ros2FuzzError(f"no subscriber for {key}")
                time.sleep(0.02)
            self.pubs[topic] = pub
        srv = "nav_msgs/srv/GetPlan"
        self.plan_key = rmw.data_key(
            rc.domain_id, f"/smana/{self.robot}/plan", srv, types.hash(srv)
        )

    def _establish(self) -> None:
        """The sensor's frame on the robot, and odometry until the gates have settled."""
        self.send(self.inputs.genuine("tf_static"))
        for _ in range(3):
            self.send(self.inputs.genuine("odom"))
        self.settle()

    def _fuzz(self) -> None:
        topics = [t for t, w in TOPIC_WEIGHTS.items() for _ in range(w)]
        t_print = time.monotonic()
        i = 0
        while i < self.n:
            if i < self.n_oversize:  # first, one per topic in turn
                cases = [self.inputs.oversize(fuzz_ros2.TOPICS[i % len(fuzz_ros2.TOPICS)])]
            elif self.draw.integer(0, HIJACK_ONE_IN - 1) == 0:
                cases = self.inputs.hijack()[: self.n - i]
            else:
                cases = [self.inputs.case(self.draw.choice(topics))]
            for case in cases:
                self.send(case)
            i += len(cases)
            if self.progress and time.monotonic() - t_print > 10.0:
                t_print = time.monotonic()
                print(f"fuzz ros2: {i}/{self.n} inputs", flush=True)
        self.settle()

    def _after(self) -> None:
        """Genuine input works again: odometry reaches robot/pose (the pose gate may have locked
        onto a hostile place: bounded by its relock rule), a GetPlan gets the planner's path."""
        f = self.fig
        through = False
        for _ in range(2 * RELOCK + 4):  # the stamp gate's relock, then the pose gate's
            case = self.inputs.genuine("odom")
            self.send(case)
            self.settle()
            x = self.inputs.x
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not through:
                through = any(abs(float(p.position[0]) - x) < 1e-9 for p in self.poses[-5:])
                time.sleep(0.01)
            if through:
                break
        f.check("a genuine Odometry reaches robot/pose after the fuzz", through)
        case = self.inputs.genuine("plan")
        replies = self.send(case)
        ok = bool(replies) and replies[0].ok is not None
        if ok:
            from smana.services.ros2 import rmw

            types = self.inputs.types
            body = types.deserialize(
                replies[0].ok.payload.to_bytes(), "nav_msgs/srv/GetPlan_Response"
            )
            xy = [(p.pose.position.x, p.pose.position.y) for p in body.plan.poses]
            seq, _, gid = rmw.parse_attachment(replies[0].ok.attachment.to_bytes())
            asked, _, _ = rmw.parse_attachment(case.attachment)
            ok = np.allclose(xy, PLANNER_PATH[:, :2]) and seq == asked and gid == self.inputs.gid
        f.check("a genuine GetPlan is answered with the planner's path after the fuzz", ok)

    def _books(self) -> None:
        f = self.fig
        st = self.settle()
        echoed = self.ref.received["odometry"]
        deadline = time.monotonic() + 10.0  # the echoes come back through the router
        while len(self.poses) < echoed and time.monotonic() < deadline:
            time.sleep(0.01)
        f.echoes = len(self.poses)
        b = self.base
        f.msgs_in = st.msgs_in - b.msgs_in
        f.accepted = st.accepted - b.accepted
        f.dropped = _diff(st.dropped, b.dropped)
        f.rejected = _diff(st.rejected, b.rejected)
        f.events = _diff(st.events, b.events)
        f.received = dict(st.details.get("received", {}))
        f.received_predicted = dict(self.ref.received)
        f.check("same process (no restart)", st.pid == self.proc.pid, f"pid {st.pid}")
        history = {k: v for k, v in b.events.items() if k.startswith("history_")}
        f.check(
            "the /tf_static history taken and refused as predicted",
            history == dict(sorted(f.history.items())),
            f"events {history}, predicted {f.history}",
        )
        f.check("alive after the fuzz", self.proc.poll() is None)
        f.check(
            "msgs_in = inputs + queries + the poses it echoed",
            f.msgs_in == self.mine + echoed,
            f"{f.msgs_in} received, {self.mine} sent + {echoed} accepted odometry",
        )
        f.check(
            "every pose it published came back to it",
            f.echoes == echoed,
            f"{f.echoes} poses on robot/pose, {echoed} accepted odometry",
        )
        settled = f.accepted + sum(f.dropped.values()) + sum(f.rejected.values())
        f.check(
            "every message settled",
            settled == f.msgs_in and st.pending == 0,
            f"{settled} settled of {f.msgs_in}, {st.pending} pending",
        )
        f.check("nothing dropped", not f.dropped, str(f.dropped))
        f.check(
            "rejections by kind == the reference's",
            f.rejected == dict(sorted(f.predicted.items())),
            f"counted {f.rejected}, predicted {f.predicted}",
        )
        want_accepted = f.inputs - sum(f.predicted.values()) + f.status_polls + echoed
        # the status poll that reads the books is still in flight: it counts itself accepted
        f.check(
            "accepted == the reference's + status polls + echoed poses",
            f.accepted == want_accepted,
            f"{f.accepted} accepted, {want_accepted} predicted",
        )
        f.check(
            "received counters == the reference's",
            f.received == f.received_predicted,
            f"{f.received} vs {f.received_predicted}",
        )
        internal = f.rejected.get("internal", 0) + sum(
            v for k, v in f.events.items() if k.startswith("internal")
        )
        f.crashes += internal
        f.check("no internal rejection or event", internal == 0, str(f.events))


def _diff(now: dict, before: dict) -> dict:
    out = {k: now.get(k, 0) - before.get(k, 0) for k in set(now) | set(before)}
    return {k: v for k, v in sorted(out.items()) if v}


def table(f: Ros2Figures) -> str:
    lines = [
        f"ROS 2 family: {f.inputs} inputs to `smana ros2` ({f.status_polls} status polls, "
        f"{f.echoes} own poses echoed)",
        "",
        "| topic | inputs | by kind | predicted fates |",
        "|---|---:|---|---|",
    ]
    for topic in fuzz_ros2.TOPICS:
        kinds = {k.split(":")[1]: v for k, v in f.by_kind.items() if k.startswith(topic + ":")}
        fates = {k.split(":")[1]: v for k, v in f.fates.items() if k.startswith(topic + ":")}
        lines.append(
            f"| {topic} | {sum(kinds.values())} | "
            + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))
            + " | "
            + ", ".join(f"{k} {v}" for k, v in sorted(fates.items()))
            + " |"
        )
    rej = ", ".join(f"{k} {v}" for k, v in f.rejected.items()) or "-"
    lines += [
        "",
        f"books: msgs_in {f.msgs_in} = accepted {f.accepted} + dropped "
        f"{sum(f.dropped.values())} + rejected {sum(f.rejected.values())} ({rej})",
        f"/tf_static history replies {f.history}; "
        f"received {f.received} (reference {f.received_predicted}); GetPlan replies "
        f"{dict(f.plan_replies)}; generator's intent held in {f.intent_held} cases",
        f"crashes {f.crashes}, tracebacks {f.tracebacks}, exit {f.exit_code}; wall {f.wall_s:.1f}"
        f" s; load average {_load(f.load_start)} at start, {_load(f.load_end)} at the end",
        "",
        "| check | result |",
        "|---|---|",
    ]
    lines += [f"| {k} | {'pass' if v else 'FAIL'} |" for k, v in f.checks.items()]
    if f.notes:
        lines += ["", "notes:"] + [f"- {n}" for n in f.notes[:30]]
    return "\n".join(lines)


def _load(la) -> str:
    return "/".join(f"{x:.2f}" for x in la) if la else "?"
