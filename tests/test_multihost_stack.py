"""The robot/base deployment end to end on two network namespaces: the robot runs `smana up
--profile robot` (router + mapper), the base `smana up --profile base` (router + navgraph +
planner), linked by mutual TLS with users and the ACL. A path query on the base is answered from
the robot's map; after the link is cut for a few seconds (the robot keeps mapping) and restored,
the base's navigation graph equals the graph of the robot's whole map. The same for a fleet (issue
17): a member on the robot host, the fleet mapper and graph on the base."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import GraphPatch, MapDelta, from_json
from smana.deploy.security import init_certs
from smana.services.navgraph.graph import NavGraph
from tests.multihost import BASE_IP, make_two_hosts, wait_for

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

SUPPORT = Path(__file__).parent / "support"
PROBE, PUBLISH = str(SUPPORT / "zenoh_probe.py"), str(SUPPORT / "publish_clouds.py")
LOCAL = "tcp/127.0.0.1:7447"


def login(user: str, host: str = "base") -> list[str]:
    """A client's login from its host's folder of the set (`certs/r1/`, `certs/base/`)."""
    folder = "r1" if host == "robot" else "base"
    return ["--user", user, "--credentials", f"certs/{folder}/credentials/{user}.txt"]


def host_config(tmp: Path, host: str) -> list[str]:
    """`--config` for a namespace's `smana up`: the profile's [zenoh] files from its own folder."""
    d = f"certs/{'r1' if host == 'robot' else 'base'}"
    files = ("tls_ca", "ca.pem"), ("tls_cert", "host.pem"), ("tls_key", "host.key")
    files += ("credentials_file", "dictionary.txt"), ("acl_file", "acl.json5")
    path = tmp / f"{host}-host.toml"
    path.write_text("[zenoh]\n" + "".join(f'{k} = "{d}/{v}"\n' for k, v in files))
    return ["--config", str(path)]


@pytest.fixture
def hosts(tmp_path):
    init_certs(tmp_path / "certs", ["r1"])
    h = make_two_hosts(tmp_path)
    try:
        yield h
    finally:
        h.down()


def ask(hosts, host, key, body=None, name="q"):
    """Query from inside a namespace as the read-only `tool` user; the JSON reply, or None."""
    out = hosts.tmp / f"{name}.json"
    out.unlink(missing_ok=True)
    extra = ["--json", json.dumps(body)] if body is not None else []
    who = login("r1.tool" if host == "robot" else "tool", host)
    code = hosts.call(host, name, PROBE, "get", LOCAL, key, str(out), *who, *extra)
    if code != 0 or not out.exists():
        return None
    first = json.loads(out.read_text().splitlines()[0])
    return json.loads(first["body"]) if first["ok"] else None


def base_graph(hosts):
    reply = ask(hosts, "base", "smana/r1/navgraph/graph?format=json", name="graph")
    return from_json(json.dumps(reply), GraphPatch) if reply else None


def graph_of_robot_map(hosts):
    """The graph a fresh navgraph builds from the robot's whole map (its snapshot)."""
    snap = ask(hosts, "base", "smana/r1/mapper/snapshot?format=json", name="snapshot")
    if snap is None:
        return None
    nc = SmanaConfig().navgraph
    g = NavGraph(ClassTable.load("garden3drms"), nc)
    g.integrate_delta(from_json(json.dumps(snap), MapDelta))
    return g.export()


def same_graph(patch: GraphPatch, export) -> bool:
    cells, labels, heights, flags = export
    a = {
        tuple(c): (int(lab), int(f))
        for c, lab, f in zip(patch.cells.tolist(), patch.labels, patch.flags)
    }
    b = {tuple(c): (int(lab), int(f)) for c, lab, f in zip(cells.tolist(), labels, flags)}
    return len(a) > 0 and a == b


def test_base_plans_on_robot_map_and_recovers_from_a_link_drop(hosts):
    hosts.run(
        "robot",
        "up-robot",
        "-m",
        "smana.deploy",
        "up",
        "--profile",
        "robot",
        *host_config(hosts.tmp, "robot"),
        "--only",
        "mapper",
        "--run-dir",
        "robot_run",
        "--set",
        f'deploy.router_connect=["tls/{BASE_IP}:7448"]',
    )
    hosts.run(
        "base",
        "up-base",
        "-m",
        "smana.deploy",
        "up",
        "--profile",
        "base",
        *host_config(hosts.tmp, "base"),
        "--only",
        "navgraph,planner",
        "--run-dir",
        "base_run",
    )

    def logs():
        runs = (("robot_run", "mapper"), ("base_run", "navgraph"), ("base_run", "planner"))
        files = [hosts.tmp / d / "logs" / f"{s}.log" for d, s in runs]
        texts = [f.read_text(errors="replace") for f in files if f.exists()]
        return "\n".join([*texts, hosts.log("up-robot"), hosts.log("up-base")])

    # The robot's mapper answers on the base, through the TLS link and both routers.
    assert wait_for(lambda: ask(hosts, "base", "smana/r1/mapper/stats?format=json"), 90, 1), logs()
    assert wait_for(lambda: ask(hosts, "base", "smana/r1/planner/stats?format=json"), 60, 1), logs()

    assert (
        hosts.call("robot", "publish-1", PUBLISH, LOCAL, "0", "3", *login("r1.sim", "robot")) == 0
    )
    request = {"start": [0.1, 0.1], "goal": [5.9, 1.9]}

    def planned():
        r = ask(hosts, "base", "smana/r1/planner/path", request, name="path")
        return r if r and r.get("ok") else None

    assert wait_for(planned, 30, 1), logs()
    reply = planned()
    assert reply["cost_total"] > 5.8 and len(reply["path"]) > 10
    assert set(reply["label_share"]) == {"terrain"}

    # Cut the link; the robot keeps mapping new ground meanwhile.
    hosts.set_link(False)
    assert (
        hosts.call("robot", "publish-2", PUBLISH, LOCAL, "3", "2", *login("r1.sim", "robot")) == 0
    )
    robot_stats = ask(hosts, "robot", "smana/r1/mapper/stats?format=json", name="rstats")
    assert robot_stats is not None  # the robot side still runs and answers locally
    hosts.set_link(True)

    def converged():
        g, ref = base_graph(hosts), graph_of_robot_map(hosts)
        return g is not None and ref is not None and same_graph(g, ref)

    assert wait_for(converged, 90, 2), logs()
    g = base_graph(hosts)
    assert g.cells[:, 0].max() * g.resolution_m + g.origin_xy[0] > 9.0  # the ground mapped offline
    far = {"start": [0.1, 0.1], "goal": [9.9, 1.9]}
    r = ask(hosts, "base", "smana/r1/planner/path", far, name="path2")
    assert r and r["ok"], r
    assert np.isfinite(r["cost_total"])


def test_fleet_base_merges_a_member_and_fills_its_gap_after_a_link_drop(hosts):
    """The fleet across hosts: the member r1 (profile fleet-robot) maps on its host, the base
    (profile fleet) merges its deltas into the fleet's map and graph. While the link is cut the
    member maps new ground; once it is back, the fleet mapper fills the gap from the member's own
    map, and the fleet's graph equals the graph of the member's whole map."""
    fleet = ["--set", 'fleet.robots=["r1"]']
    hosts.run(
        "robot",
        "up-member",
        "-m",
        "smana.deploy",
        "up",
        "--profile",
        "fleet-robot",
        *host_config(hosts.tmp, "robot"),
        "--robot",
        "r1",
        "--only",
        "mapper",
        "--run-dir",
        "member_run",
        "--set",
        f'deploy.router_connect=["tls/{BASE_IP}:7448"]',
        *fleet,
    )
    hosts.run(
        "base",
        "up-fleet",
        "-m",
        "smana.deploy",
        "up",
        "--profile",
        "fleet",
        *host_config(hosts.tmp, "base"),
        "--only",
        "mapper,navgraph",
        "--run-dir",
        "fleet_run",
        *fleet,
    )

    def logs():
        runs = (("member_run", "mapper@r1"), ("fleet_run", "mapper@fleet"))
        files = [hosts.tmp / d / "logs" / f"{s}.log" for d, s in runs]
        texts = [f.read_text(errors="replace") for f in files if f.exists()]
        return "\n".join([*texts, hosts.log("up-member"), hosts.log("up-fleet")])

    def fleet_graph():
        reply = ask(hosts, "base", "smana/fleet/navgraph/graph?format=json", name="fgraph")
        return from_json(json.dumps(reply), GraphPatch) if reply else None

    def converged():
        g, ref = fleet_graph(), graph_of_robot_map(hosts)
        return g is not None and ref is not None and same_graph(g, ref)

    assert wait_for(lambda: ask(hosts, "base", "smana/r1/mapper/stats?format=json"), 90, 1), logs()
    assert wait_for(lambda: ask(hosts, "base", "smana/fleet/mapper/stats?format=json"), 60, 1)
    assert (
        hosts.call("robot", "publish-1", PUBLISH, LOCAL, "0", "3", *login("r1.sim", "robot")) == 0
    )
    assert wait_for(converged, 60, 1), logs()
    hosts.set_link(False)
    assert (
        hosts.call("robot", "publish-2", PUBLISH, LOCAL, "3", "2", *login("r1.sim", "robot")) == 0
    )
    hosts.set_link(True)
    assert wait_for(converged, 90, 2), logs()
    g = fleet_graph()
    assert g.cells[:, 0].max() * g.resolution_m + g.origin_xy[0] > 9.0  # the ground mapped offline
