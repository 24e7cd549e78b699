"""The access-control policy of `smana deploy init-certs` (the table in docs/deployment.md), checked
cell by cell against a real router (`python -m smana.deploy.router`) on both of its listeners: tcp,
and TLS where every client presents a valid host certificate (the robot's or the base's), which
must grant nothing by itself (issue 11).

Each role logs in once per link under its own robot name (`smana/<role>-<link>/...`), so whatever
comes through names its sender. For every key family it puts a payload, declares a queryable that
replies, and declares a liveliness token; an observer logged in as `router` (it sees everything the
router lets through) subscribes, queries and asks for the tokens. What may pass is written below as
data, independently of `acl_policy`. Nothing is taken as denied before the same session's later,
allowed traffic was seen to arrive (a positive control), so a loaded machine cannot fake a denial.
"""

from __future__ import annotations

import dataclasses
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from smana.common.config import ZenohConfig
from smana.common.zenoh_config import make_zenoh_config
from smana.deploy.security import init_certs
from smana.deploy.supervisor import die_with_parent
from tests.conftest import free_port, wait_for, wait_port

pytestmark = pytest.mark.multiprocess

# -- the table -------------------------------------------------------------------------------------
# Key families, after `smana/<robot>/`. p: put; d: delete; r: declare a queryable and reply; t:
# liveliness token. A role a row does not name may do none of them there; `router` may do all of
# them on every row.
SENSORS = (
    "robot/cloud",
    "robot/scan",
    "robot/pose",
    "robot/pose_truth",
    "robot/clock",
    "robot/image/rgb",
)
OWNERS = ("sim", "replay", "driver", "mapper", "navgraph", "planner", "explorer", "recorder")
TABLE = {
    **{family: {"sim": "p", "replay": "p", "driver": "p"} for family in SENSORS},
    "robot/cmd_vel": {"explorer": "p", "operator": "p"},
    "robot/status": {},  # the robot's key space holds only the streams above
    "sim/status": {"sim": "pdr"},
    "replay/status": {"replay": "pdr"},
    "driver/status": {"driver": "pdr"},
    "mapper/delta": {"mapper": "pdr"},
    "mapper/status": {"mapper": "pdr"},
    "navgraph/patch": {"navgraph": "pdr"},
    "navgraph/status": {"navgraph": "pdr"},
    "planner/path": {"planner": "pdr"},
    "planner/status": {"planner": "pdr"},
    "explorer/state": {"explorer": "pdr"},
    "explorer/status": {"explorer": "pdr"},
    "recorder/status": {"recorder": "pdr"},
    "tool/status": {},  # tools and operators own no key space
    "operator/status": {},
    "alive/robot": {"sim": "t", "replay": "t", "driver": "t"},
    **{f"alive/{owner}": {owner: "t"} for owner in OWNERS},
    "alive/tool": {},
    "nobody/x": {},  # a segment no role owns
}
# `visitor`: a user the routers know (it logs in) whom the policy does not name.
ROLES = (*OWNERS, "operator", "tool", "router", "visitor")
READERS = set(ROLES) - {"visitor"}  # may subscribe, query, list tokens
SAVERS = {"operator", "router"}  # may ask the mapper to save (a query that writes a file)
LINKS = {"tcp": None, "tls-robot": "robot", "tls-base": "base"}  # link -> certificate presented


def allowed(role: str, family: str) -> str:
    return "pdrt" if role == "router" else TABLE[family].get(role, "")


# -- a router with both listeners, and sessions against it -----------------------------------------
@dataclasses.dataclass
class Router:
    certs: Path
    dictionary: Path
    endpoints: dict[str, str]  # link -> endpoint

    def config(self, role: str, link: str, credentials: Path | None = None):
        """A client session of `role` over `link`; a router's own login is in the dictionary."""
        if credentials is None:
            credentials = (
                self.dictionary if role == "router" else self.certs / "credentials" / f"{role}.txt"
            )
        zc = ZenohConfig(
            mode="client",
            connect=[self.endpoints[link]],
            user=role,
            credentials_file=str(credentials),
        )
        host = LINKS[link]
        if host:
            zc = dataclasses.replace(
                zc,
                tls_ca=str(self.certs / "ca.pem"),
                tls_cert=str(self.certs / f"{host}.pem"),
                tls_key=str(self.certs / f"{host}.key"),
            )
        return make_zenoh_config(zc)


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("acl")
    certs = tmp / "certs"
    init_certs(certs, ["robot", "base"])
    visitor = f"visitor:{secrets.token_urlsafe(12)}\n"
    (certs / "credentials" / "visitor.txt").write_text(visitor)
    dictionary = tmp / "dictionary.txt"
    dictionary.write_text((certs / "dictionary.txt").read_text() + visitor)
    tcp = free_port()
    tls = free_port()
    while tls == tcp:
        tls = free_port()
    zenoh_section = {
        "tls_ca": certs / "ca.pem",
        "tls_cert": certs / "base.pem",
        "tls_key": certs / "base.key",
        "credentials_file": dictionary,
        "acl_file": certs / "acl.json5",
    }
    config = tmp / "router.toml"
    config.write_text("[zenoh]\n" + "".join(f'{k} = "{v}"\n' for k, v in zenoh_section.items()))
    endpoints = {"tcp": f"tcp/127.0.0.1:{tcp}"}
    endpoints |= {link: f"tls/127.0.0.1:{tls}" for link in LINKS if link != "tcp"}
    log = open(tmp / "router.log", "ab")  # noqa: SIM115 - the child owns it
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "smana.deploy.router",
            "--config",
            str(config),
            "--listen",
            endpoints["tcp"],
            "--listen",
            endpoints["tls-robot"],
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        preexec_fn=die_with_parent,
    )
    log.close()
    try:
        for port in (tcp, tls):
            wait_port(port, 60.0)
        yield Router(certs, dictionary, endpoints)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


class Observer:
    """What came through the router, from a session that may see everything (user `router`)."""

    def __init__(self, session):
        self.session = session
        self._lock = threading.Lock()
        self.puts: set[tuple[str, str]] = set()  # (robot, family)
        self.deletes: set[tuple[str, str]] = set()
        self.after_puts: set[str] = set()  # robots whose end-of-puts query arrived
        self.strays: list[str] = []
        self._declared = [
            session.declare_subscriber("smana/**", self._on_sample),
            session.declare_queryable("smana/*/ready", self._on_ready),
            session.declare_queryable("smana/*/mapper/save", self._on_save),
        ]

    def _on_sample(self, sample) -> None:
        import zenoh

        _, robot, family = str(sample.key_expr).split("/", 2)
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.deletes.add((robot, family))
            elif sample.payload.to_string().startswith(robot):
                self.puts.add((robot, family))
            else:
                self.strays.append(f"{sample.key_expr}: {sample.payload.to_string()}")

    def _on_ready(self, query) -> None:
        # A session's queries travel behind its puts on the same link and priority, so its puts
        # have all been delivered when its query shows up here.
        key = str(query.key_expr)
        if "*" not in key:
            with self._lock:
                self.after_puts.add(key.split("/")[1])
            query.reply(key, b"ready")

    def _on_save(self, query) -> None:
        if "*" not in str(query.key_expr):
            query.reply(query.key_expr, b"saved")

    def close(self) -> None:
        for d in self._declared:
            d.undeclare()
        self.session.close()

    def seen(self) -> set[tuple[str, str, str]]:
        """(robot, family, "p" or "d") of every put and delete that came through."""
        with self._lock:
            return {(*k, "p") for k in self.puts} | {(*k, "d") for k in self.deletes}


class Probe:
    """One role logged in over one link, with a queryable and a token on every key family."""

    def __init__(self, router: Router, role: str, link: str):
        import zenoh

        self.role, self.link = role, link
        self.robot = f"{role}-{link}"
        self.session = zenoh.open(router.config(role, link))
        s, robot = self.session, self.robot
        self.declared = []
        for family in TABLE:
            key = f"smana/{robot}/{family}"
            self.declared.append(s.declare_queryable(key, lambda q, k=key: q.reply(k, robot)))
            self.declared.append(s.liveliness().declare_token(key))
        # Declared last: a router takes a session's declarations in order, so once this one is
        # visible, every queryable and token above has been decided on.
        self.declared.append(s.declare_subscriber(f"smana/{robot}/ready", lambda _sample: None))

    def put_all(self, tag: str) -> None:
        """Put, then delete, on every key family."""
        import zenoh

        block = zenoh.CongestionControl.BLOCK
        for family in TABLE:
            key = f"smana/{self.robot}/{family}"
            self.session.put(key, f"{self.robot} {tag}", congestion_control=block)
            self.session.delete(key, congestion_control=block)

    def close(self) -> None:
        for d in self.declared:
            d.undeclare()
        self.session.close()


def render(table: dict[tuple[str, str], dict[str, str]]) -> str:
    """One line per session, its allowed cells only."""
    lines = []
    for (role, link), cells in table.items():
        allowed_cells = " ".join(f"{f}={c}" for f, c in cells.items() if c)
        lines.append(f"{role}@{link}: {allowed_cells or '-'}")
    return "\n".join(lines)


def test_every_role_over_every_listener_gets_exactly_its_row(router):
    import zenoh

    t0 = time.monotonic()
    obs_session = zenoh.open(router.config("router", "tcp"))
    observer = Observer(obs_session)
    probes: list[Probe] = []

    def ready_publisher(p: Probe):
        # Matches the probe's last subscriber only: not the observer's own `smana/**`.
        return obs_session.declare_publisher(
            f"smana/{p.robot}/ready", allowed_destination=zenoh.Locality.REMOTE
        )

    try:
        probes = [Probe(router, role, link) for role in ROLES for link in LINKS]
        ready_s = time.monotonic() - t0

        # 1. Queryables and tokens: wait until each reading session's last declaration is visible.
        deadline = time.monotonic() + 120
        for p in probes:
            if p.role not in READERS:
                continue  # a visitor may not even subscribe: nothing of it can become visible
            pub = ready_publisher(p)
            ok = wait_for(
                lambda pub=pub: pub.matching_status.matching, max(1.0, deadline - time.monotonic())
            )
            pub.undeclare()
            assert ok, f"{p.robot}: its subscriber never reached the router"
        replies = obs_session.get(
            "smana/**",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            allowed_destination=zenoh.Locality.REMOTE,
            timeout=60.0,
        )
        replied = set()
        for r in replies:
            assert r.ok, r.err.payload.to_string()
            _, robot, family = str(r.ok.key_expr).split("/", 2)
            assert r.ok.payload.to_string() == robot
            replied.add((robot, family))
        tokens = {
            tuple(str(r.ok.key_expr).split("/", 2)[1:])
            for r in obs_session.liveliness().get("smana/**", timeout=60.0)
        }

        # 2. Puts and deletes: repeat until every allowed one has come through at least once...
        expected_samples = {
            (p.robot, f, kind)
            for p in probes
            for f in TABLE
            for kind in "pd"
            if kind in allowed(p.role, f)
        }
        rounds = 0

        def all_allowed_samples_arrived() -> bool:
            nonlocal rounds
            rounds += 1
            for p in probes:
                p.put_all(f"round {rounds}")
            return wait_for(lambda: expected_samples <= observer.seen(), 5.0)

        assert wait_for(all_allowed_samples_arrived, 120.0, 0.0), sorted(
            expected_samples - observer.seen()
        )
        # ...then once more, each session closing its round with a query the observer answers:
        # when the answer is back, whatever the router let through of that round has arrived.
        for p in probes:
            p.put_all("last")
        pending = {p.robot: p.session.get(f"smana/{p.robot}/ready", timeout=60.0) for p in probes}
        may_read = {robot: any(r.ok for r in answers) for robot, answers in pending.items()}
        saves = {
            p.robot: p.session.get(f"smana/{p.robot}/mapper/save", timeout=60.0) for p in probes
        }
        may_save = {robot: any(r.ok for r in answers) for robot, answers in saves.items()}
        samples = observer.seen()
        assert not observer.strays, observer.strays
        assert {r for r, *_ in samples | replied | tokens} <= {p.robot for p in probes}

        actual, wrong = {}, []
        for p in probes:
            row = actual[p.role, p.link] = {}
            for family in TABLE:
                row[family] = cell = (
                    ("p" if (p.robot, family, "p") in samples else "")
                    + ("d" if (p.robot, family, "d") in samples else "")
                    + ("r" if (p.robot, family) in replied else "")
                    + ("t" if (p.robot, family) in tokens else "")
                )
                if cell != allowed(p.role, family):
                    want = allowed(p.role, family)
                    wrong.append(f"{p.role}@{p.link} {family}: got {cell!r}, want {want!r}")
            if may_read[p.robot] != (p.role in READERS):
                wrong.append(f"{p.role}@{p.link} query: got {may_read[p.robot]}")
            if may_save[p.robot] != (p.role in SAVERS):
                wrong.append(f"{p.role}@{p.link} query mapper/save: got {may_save[p.robot]}")
        assert not wrong, "\n".join(wrong) + "\n\nwhat came through:\n" + render(actual)
        # The positive control for the puts of the last round: each reading session's query.
        assert observer.after_puts == {p.robot for p in probes if p.role in READERS}
        # Long after every reader's subscriber showed up, the visitor's still has not.
        for p in probes:
            if p.role not in READERS:
                pub = ready_publisher(p)
                assert not pub.matching_status.matching, f"{p.robot} may subscribe"
                pub.undeclare()
        total_s = time.monotonic() - t0
        print(
            f"{len(probes)} sessions open in {ready_s:.1f} s; table checked in {total_s:.1f} s "
            f"({rounds} round(s) of puts and deletes)"
        )
    finally:
        for p in probes:
            p.close()
        observer.close()


def test_no_session_without_a_known_password(router, tmp_path):
    import zenoh

    wrong = tmp_path / "wrong.txt"
    wrong.write_text("tool:not-the-password\n")
    for link in LINKS:
        with pytest.raises(zenoh.ZError):
            zenoh.open(router.config("tool", link, credentials=wrong))
        conf = router.config("tool", link)
        conf.insert_json5("transport/auth/usrpwd", "{}")  # no login at all
        with pytest.raises(zenoh.ZError):
            zenoh.open(conf)
