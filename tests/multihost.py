"""Two hosts on one machine for the multi-host tests: Linux network namespaces `robot` and `base`
joined by a veth pair (10.213.7.1 <-> 10.213.7.2), made and removed by the test itself. Skipped,
with the reason, where the machine does not allow namespaces (not root, no iproute2)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from smana.deploy.supervisor import die_with_parent
from tests.conftest import (
    stop_group,
    stop_together,
    wait_for,  # noqa: F401 - the multi-host tests import it from here
)

ROBOT_IP, BASE_IP = "10.213.7.1", "10.213.7.2"


def _ip(*args, check=True):
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


class TwoHosts:
    def __init__(self, tmp: Path):
        self.tmp = tmp
        tag = f"{os.getpid() % 100000}"
        self.ns = {"robot": f"smana-r{tag}", "base": f"smana-b{tag}"}
        self.dev = {"robot": f"vr{tag}", "base": f"vb{tag}"}
        self.addr = {"robot": ROBOT_IP, "base": BASE_IP}
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def up(self) -> None:
        for ns in self.ns.values():
            _ip("netns", "add", ns)
        _ip("link", "add", self.dev["robot"], "type", "veth", "peer", "name", self.dev["base"])
        for host, ns in self.ns.items():
            dev = self.dev[host]
            _ip("link", "set", dev, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{self.addr[host]}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")

    def down(self, timeout_s: float = 5.0) -> None:
        stop_together([p for _, p in self.procs], timeout_s)
        for ns in self.ns.values():
            _ip("netns", "del", ns, check=False)

    def set_link(self, up: bool) -> None:
        """Cut or restore the link between the hosts (the robot's end of the veth)."""
        _ip("-n", self.ns["robot"], "link", "set", self.dev["robot"], "up" if up else "down")

    def run(self, host: str, name: str, *argv: str) -> subprocess.Popen:
        """Start `python <argv>` inside a host's namespace; its output goes to <tmp>/<name>.log."""
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - the child owns it
        proc = subprocess.Popen(
            ["ip", "netns", "exec", self.ns[host], sys.executable, *argv],
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            cwd=self.tmp,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
            preexec_fn=die_with_parent,
        )
        log.close()
        proc.log_name = name
        self.procs.append((name, proc))
        return proc

    def call(self, host: str, name: str, *argv: str, timeout_s: float = 60.0) -> int:
        p = self.run(host, name, *argv)
        try:
            return p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.stop(p)
            raise

    def log(self, name: str) -> str:
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    @staticmethod
    def stop(p: subprocess.Popen, timeout_s: float = 5.0) -> None:
        stop_group(p, timeout_s=timeout_s)


def make_two_hosts(tmp: Path) -> TwoHosts:
    if shutil.which("ip") is None:
        pytest.skip("iproute2 (`ip`) is not installed: cannot make network namespaces")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    hosts = TwoHosts(tmp)
    try:
        hosts.up()
    except subprocess.CalledProcessError as exc:
        hosts.down()
        pytest.skip(f"this machine does not allow network namespaces: {exc.stderr.strip()}")
    return hosts
