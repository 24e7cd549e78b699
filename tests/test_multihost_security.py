"""Robot and base station on two network namespaces, linked by their routers over mutual TLS with
user/password authentication and the access-control policy of `smana deploy init-certs`: each
host with its own folder of the set (`certs/r1/`, `certs/base/`), as if copied there."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from smana.deploy.security import init_certs, revoke_robot
from tests.multihost import BASE_IP, make_two_hosts, wait_for

pytestmark = pytest.mark.multiprocess

PROBE = str(Path(__file__).parent / "support" / "zenoh_probe.py")
LOCAL = "tcp/127.0.0.1:7447"
TLS = f"tls/{BASE_IP}:7448"
FOLDER = {"robot": "r1", "base": "base"}  # namespace -> its folder of the set


def login(user: str, folder: str) -> list[str]:
    """A client logs in with its own file: clients never need a router's dictionary."""
    return ["--user", user, "--credentials", f"certs/{folder}/credentials/{user}.txt"]


def host_config(tmp: Path, host: str) -> list[str]:
    """`--config` for a namespace's router: the profile's [zenoh] files, from its own folder."""
    d = f"certs/{FOLDER[host]}"
    files = {
        "tls_ca": f"{d}/ca.pem",
        "tls_cert": f"{d}/host.pem",
        "tls_key": f"{d}/host.key",
        "credentials_file": f"{d}/dictionary.txt",
        "acl_file": f"{d}/acl.json5",
    }
    path = tmp / f"{host}-host.toml"
    path.write_text("[zenoh]\n" + "".join(f'{k} = "{v}"\n' for k, v in files.items()))
    return ["--config", str(path)]


@pytest.fixture
def hosts(tmp_path):
    init_certs(tmp_path / "certs", ["r1", "r2"])
    init_certs(tmp_path / "foreign", ["r1"])  # a CA the deployment does not trust
    h = make_two_hosts(tmp_path)
    try:
        yield h
    finally:
        h.down()


def start_routers(hosts):
    hosts.run(
        "base",
        "router-base",
        *("-m", "smana.deploy.router", "--profile", "base"),
        *host_config(hosts.tmp, "base"),
    )
    hosts.run(
        "robot",
        "router-robot",
        *("-m", "smana.deploy.router", "--profile", "robot"),
        *host_config(hosts.tmp, "robot"),
        "--set",
        f'deploy.router_connect=["tls/{BASE_IP}:7448"]',
    )
    # The base's router is reachable from the robot's namespace only through the TLS link: a
    # client on the robot that can query the base's liveliness proves the link is up.
    ok = wait_for(
        lambda: (
            hosts.call("robot", "probe-open", PROBE, "open", LOCAL, *login("r1.tool", "r1")) == 0
        ),
        30,
    )
    assert ok, hosts.log("router-robot") + hosts.log("router-base")


def test_only_the_robots_own_commanders_publish_its_velocity_commands(hosts):
    start_routers(hosts)
    out = hosts.tmp / "cmd_vel.txt"
    key = "smana/r1/robot/cmd_vel"
    hosts.run("robot", "sub", PROBE, "sub", LOCAL, key, str(out), *login("r1.sim", "r1"))
    assert wait_for(lambda: "subscribed" in hosts.log("sub"), 20), hosts.log("sub")

    def pub(host: str, name: str, payload: str, *auth: str, endpoint: str = LOCAL) -> None:
        hosts.call(host, name, PROBE, "pub", endpoint, key, payload, *auth)

    def sent_through():
        pub("base", "pub-explorer", "from-explorer", *login("r1.explorer", "base"))
        return out.exists() and "from-explorer" in out.read_text()

    # Routes take a moment to propagate across the TLS link.
    assert wait_for(sent_through, 30, 0.5), hosts.log("router-base")
    # On the base: the read-only tool, and identities the base holds that do not command r1.
    for user in ("tool", "r1.navgraph", "r2.explorer"):
        pub("base", f"pub-{user}", f"from-{user}", *login(user, "base"))
    # From the robot, straight to the base's TLS port with a host certificate (issue 11), which
    # identifies the link and grants nothing; and robot r2's explorer with r2's own certificate
    # and password (issue 25): it commands r2, not r1.
    for user, folder, host in (
        ("r1.tool", "r1", "r1"),
        ("r1.mapper", "r1", "r1"),
        ("r2.explorer", "r2", "r2"),
        ("r2.router", "r2", "r2"),
    ):
        auth = [*login(user, folder), "--tls-dir", "certs", "--host", host]
        if user.endswith(".router"):  # a router's login is only in its host's dictionary
            auth[3] = f"certs/{folder}/dictionary.txt"
        pub("robot", f"pub-{user}-tls", f"from-{user}-tls", *auth, endpoint=TLS)
    tls = ["--tls-dir", "certs", "--host", "r1"]
    pub(
        "robot", "pub-explorer-tls", "explorer-tls", *login("r1.explorer", "r1"), *tls, endpoint=TLS
    )
    pub("base", "pub-explorer2", "explorer-again", *login("r1.explorer", "base"))
    assert wait_for(lambda: {"explorer-tls", "explorer-again"} <= set(out.read_text().split()), 10)
    received = set(out.read_text().split())
    assert received == {"from-explorer", "explorer-tls", "explorer-again"}


def test_wrong_password_or_certificate_gets_no_link(hosts):
    start_routers(hosts)
    bad = hosts.tmp / "bad-credentials.txt"
    bad.write_text("r1.explorer:not-the-password\n")
    assert (
        hosts.call(
            "base",
            "probe-badpw",
            *(PROBE, "open", LOCAL, "--user", "r1.explorer", "--credentials", str(bad)),
        )
        == 3
    )
    assert hosts.call("base", "probe-nopw", PROBE, "open", LOCAL) == 3
    # The base does not hold the passwords of what runs on a robot only: r1's mapper and tool
    # cannot log in there, only through their own robot's router.
    tls = ["--tls-dir", "certs", "--host", "r1"]
    for user in ("r1.mapper", "r1.tool"):
        auth = login(user, "r1")
        assert hosts.call("robot", f"probe-{user}", PROBE, "open", TLS, *auth, *tls) == 3
    good = login("r1.explorer", "r1")  # one the base may run, so it holds its password
    # The right certificate and password get a link to the base over TLS...
    assert hosts.call("robot", "probe-tls-ok", PROBE, "open", TLS, *good, *tls) == 0
    # ...a certificate from another CA does not, password or not.
    foreign = ["--tls-dir", "foreign", "--host", "r1"]
    assert hosts.call("robot", "probe-tls-foreign", PROBE, "open", TLS, *good, *foreign) == 3
    # Nor does a plain TCP connection to the TLS port.
    assert hosts.call("robot", "probe-plain", PROBE, "open", f"tcp/{BASE_IP}:7448", *good) == 3


def test_a_revoked_robots_certificate_gets_nothing_through_while_r1_still_works(hosts):
    """r2 is revoked while its folder is in a thief's hands: its certificate still completes a
    TLS handshake (zenoh has no revocation list), so the base's policy must deny it. Each probe
    of the stolen certificate is paired with the same probe, same login, with r1's certificate:
    only the certificate differs, and r1's gets through."""
    certs, stolen = hosts.tmp / "certs", hosts.tmp / "stolen"
    stolen.mkdir()
    shutil.copyfile(certs / "ca.pem", stolen / "ca.pem")
    shutil.copytree(certs / "r2", stolen / "r2")  # revoke_robot deletes the set's copy
    revoke_robot(certs, "r2")
    start_routers(hosts)
    r2_cert = ["--tls-dir", "stolen", "--host", "r2"]
    r1_cert = ["--tls-dir", "certs", "--host", "r1"]
    # Its own logins are gone from the base: no session at all, over TLS or to the router.
    for user in ("r2.explorer", "r2.tool"):
        auth = ["--user", user, "--credentials", f"stolen/r2/credentials/{user}.txt"]
        assert hosts.call("robot", f"r2-own-{user}", PROBE, "open", TLS, *auth, *r2_cert) == 3
    r2_router = ["--user", "r2.router", "--credentials", "stolen/r2/dictionary.txt"]
    assert hosts.call("robot", "r2-router", PROBE, "open", TLS, *r2_router, *r2_cert) == 3
    # With a login the base does accept (a leaked password: r1's explorer, which commands r1),
    # the certificate's name alone must deny every message, both ways.
    leaked = login("r1.explorer", "r1")
    key = "smana/r1/robot/cmd_vel"
    out = {n: hosts.tmp / f"{n}.txt" for n in ("sim", "sub-r2", "sub-r1", "get-r1", "get-r2")}
    hosts.run("robot", "sim", PROBE, "sub", LOCAL, key, str(out["sim"]), *login("r1.sim", "r1"))
    status = "smana/r1/mapper/status"
    hosts.run("robot", "serve", PROBE, "serve", LOCAL, status, "r1-ok", *login("r1.mapper", "r1"))
    hosts.run("robot", "sub-r2", PROBE, "sub", TLS, key, str(out["sub-r2"]), *leaked, *r2_cert)
    hosts.run("robot", "sub-r1", PROBE, "sub", TLS, key, str(out["sub-r1"]), *leaked, *r1_cert)
    for name in ("sim", "serve", "sub-r2", "sub-r1"):
        assert wait_for(lambda n=name: "subscribed" in hosts.log(n) or "serving" in hosts.log(n))

    def received(name: str) -> set[str]:
        return set(out[name].read_text().split()) if out[name].exists() else set()

    # publish: the stolen certificate first, then r1's on the same path until it arrives
    hosts.call("robot", "pub-r2", PROBE, "pub", TLS, key, "stolen", *leaked, *r2_cert)

    def r1_through() -> bool:
        hosts.call("robot", "pub-r1", PROBE, "pub", TLS, key, "r1-cert", *leaked, *r1_cert)
        return "r1-cert" in received("sim")

    assert wait_for(r1_through, 30, 0.5), hosts.log("router-base")
    # subscribe: a publisher on the robot reaches r1's TLS subscriber, not the stolen one
    sim = login("r1.explorer", "r1")
    pub = (PROBE, "pub", LOCAL, key, "local", *sim)
    assert wait_for(
        lambda: hosts.call("robot", "pub-local", *pub) == 0 and "local" in received("sub-r1"),
        30,
        0.5,
    )
    # query: r1's certificate gets the mapper's answer, the stolen one none (exit 4: no reply)
    get = (PROBE, "get", TLS, status)
    assert hosts.call("robot", "get-r1", *get, str(out["get-r1"]), *leaked, *r1_cert) == 0
    assert "r1-ok" in out["get-r1"].read_text()
    assert hosts.call("robot", "get-r2", *get, str(out["get-r2"]), *leaked, *r2_cert) in (3, 4)
    assert "r1-ok" not in (out["get-r2"].read_text() if out["get-r2"].exists() else "")
    assert "stolen" not in received("sim"), "the revoked certificate published a velocity command"
    assert received("sub-r2") == set(), "the revoked certificate received samples"
