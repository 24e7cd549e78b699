"""Robot and base station on two network namespaces, linked by their routers over mutual TLS with
user/password authentication and the access-control policy of `smana deploy init-certs`."""

from __future__ import annotations

import pytest

from smana.deploy.security import init_certs
from tests.multihost import BASE_IP, make_two_hosts, wait_for

pytestmark = pytest.mark.multiprocess

PROBE = str(__import__("pathlib").Path(__file__).parent / "support" / "zenoh_probe.py")
LOCAL = "tcp/127.0.0.1:7447"
TLS = f"tls/{BASE_IP}:7448"


def login(role: str) -> list[str]:
    """A client logs in with its role's own file: clients never need the routers' dictionary."""
    return ["--user", role, "--credentials", f"certs/credentials/{role}.txt"]


@pytest.fixture
def hosts(tmp_path):
    init_certs(tmp_path / "certs", ["robot", "base"])
    init_certs(tmp_path / "foreign", ["robot"])  # a CA the deployment does not trust
    h = make_two_hosts(tmp_path)
    try:
        yield h
    finally:
        h.down()


def start_routers(hosts):
    hosts.run("base", "router-base", "-m", "smana.deploy.router", "--profile", "base")
    hosts.run(
        "robot",
        "router-robot",
        "-m",
        "smana.deploy.router",
        "--profile",
        "robot",
        "--set",
        f'deploy.router_connect=["tls/{BASE_IP}:7448"]',
    )
    # The base's router is reachable from the robot's namespace only through the TLS link: a
    # client on the robot that can query the base's liveliness proves the link is up.
    ok = wait_for(
        lambda: hosts.call("robot", "probe-open", PROBE, "open", LOCAL, *login("tool")) == 0, 30
    )
    assert ok, hosts.log("router-robot") + hosts.log("router-base")


def test_only_authorised_roles_publish_velocity_commands(hosts):
    start_routers(hosts)
    out = hosts.tmp / "cmd_vel.txt"
    hosts.run(
        "robot", "sub", PROBE, "sub", LOCAL, "smana/r1/robot/cmd_vel", str(out), *login("sim")
    )
    assert wait_for(lambda: "subscribed" in hosts.log("sub"), 20), hosts.log("sub")

    def sent_through():
        hosts.call(
            "base",
            "pub-explorer",
            PROBE,
            "pub",
            LOCAL,
            "smana/r1/robot/cmd_vel",
            "from-explorer",
            *login("explorer"),
        )
        return out.exists() and "from-explorer" in out.read_text()

    # Routes take a moment to propagate across the TLS link.
    assert wait_for(sent_through, 30, 0.5), hosts.log("router-base")
    for role in ("tool", "mapper", "sim"):
        hosts.call(
            "base",
            f"pub-{role}",
            PROBE,
            "pub",
            LOCAL,
            "smana/r1/robot/cmd_vel",
            f"from-{role}",
            *login(role),
        )
    # From the robot, straight to the base's TLS port with the robot's certificate (issue 11):
    # the certificate identifies the link and grants nothing, so the roles' rights are the same.
    robot_cert = ["--tls-dir", "certs", "--host", "robot"]
    for role in ("tool", "mapper"):
        hosts.call(
            "robot",
            f"pub-{role}-tls",
            PROBE,
            "pub",
            TLS,
            "smana/r1/robot/cmd_vel",
            f"from-{role}-tls",
            *login(role),
            *robot_cert,
        )
    hosts.call(
        "robot",
        "pub-explorer-tls",
        PROBE,
        "pub",
        TLS,
        "smana/r1/robot/cmd_vel",
        "explorer-tls",
        *login("explorer"),
        *robot_cert,
    )
    hosts.call(
        "base",
        "pub-explorer2",
        PROBE,
        "pub",
        LOCAL,
        "smana/r1/robot/cmd_vel",
        "explorer-again",
        *login("explorer"),
    )
    assert wait_for(lambda: {"explorer-tls", "explorer-again"} <= set(out.read_text().split()), 10)
    received = set(out.read_text().split())
    assert received == {"from-explorer", "explorer-tls", "explorer-again"}


def test_wrong_password_or_certificate_gets_no_link(hosts):
    start_routers(hosts)
    bad = hosts.tmp / "bad-credentials.txt"
    bad.write_text("explorer:not-the-password\n")
    assert (
        hosts.call(
            "base",
            "probe-badpw",
            PROBE,
            "open",
            LOCAL,
            "--user",
            "explorer",
            "--credentials",
            str(bad),
        )
        == 3
    )
    assert hosts.call("base", "probe-nopw", PROBE, "open", LOCAL) == 3
    good = login("tool")
    # The right certificate and password get a link to the base over TLS...
    assert (
        hosts.call(
            "robot",
            "probe-tls-ok",
            PROBE,
            "open",
            TLS,
            *good,
            "--tls-dir",
            "certs",
            "--host",
            "robot",
        )
        == 0
    )
    # ...a certificate from another CA does not, password or not.
    assert (
        hosts.call(
            "robot",
            "probe-tls-foreign",
            PROBE,
            "open",
            TLS,
            *good,
            "--tls-dir",
            "foreign",
            "--host",
            "robot",
        )
        == 3
    )
    # Nor does a plain TCP connection to the TLS port.
    assert hosts.call("robot", "probe-plain", PROBE, "open", f"tcp/{BASE_IP}:7448", *good) == 3
