"""`smana deploy`: the files that secure a multi-host deployment (zenoh features), one identity
per robot (as SROS2 gives each node an enclave).

`smana deploy init-certs --robots r1,r2` writes into one folder (`--out`):

- `ca.pem` / `ca.key`: a local certificate authority, and `users.txt`, every identity's password,
  with `issued.json` (the robots, the fleet, the base): the issuer's own books, they go to no host;
- one folder per host, to be copied to that host as `certs/`: `<base>/` and `<robot>/` for each
  robot, holding `ca.pem`, the host's certificate `host.pem` / `host.key` (its common name is the
  host's name; good for both ends of a link, so TLS between routers is mutual), `acl.json5` (the
  policy its router enforces, `acl_policy`), `dictionary.txt` (the passwords of the users that log
  in to its router and of what runs there, in zenoh's usrpwd format) and `credentials/<user>.txt`
  (one user's line, for a client on a computer of its own: a driver, an operator's laptop).

Identities: `<robot>.<role>` for what belongs to one robot (`r2.sim`, `r2.mapper`, ..., `r2.tool`,
and `r2.router`, the robot's router when it links to the base), `<fleet>.<role>` for the fleet's
shared services, and `operator`, `tool` and `router` (the base's router) on the base. A robot's
folder holds only that robot's secrets; the base's folder holds the fleet's and base's own, and
per robot the services a base may run for it (navgraph, planner, explorer, recorder) and its
router's login (the base checks it). `smana deploy add-robot r3` and `revoke-robot r2` rewrite
the base's dictionary and policy and that robot's folder, and no other robot's.

Point the `[zenoh]` section at a host's folder (`tls_ca`, `tls_cert`, `tls_key`,
`credentials_file`, `acl_file`); the `robot`, `base`, `multi-robot`, `fleet` and `fleet-robot`
profiles do (see `docs/deployment.md`, which also has the policy as a table).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import secrets
import shutil
from pathlib import Path

from smana.common import service_table
from smana.common.cli import ArgumentParser, UsageError
from smana.common.keys import check_robot
from smana.common.zenoh_config import read_credentials
from smana.deploy.certs import issue_host_cert, new_ca, write_cert, write_key, write_secret

# Who may do what, from the table of services (common/service_table.py: each row's `acl` and
# `reads`). Roles become zenoh user names `<robot>.<role>`; `router` is a router's login when it
# links to another (robot -> base); `operator` a human with a joystick on the base, `tool` any
# external zenoh tool (a robot has its own, `<robot>.tool`); `driver` a real robot's driver, not a
# service of smana, which publishes the robot's sensors as the sim and the replay do.
SENSOR_ROLES = (*service_table.with_acl("sensor"), "driver")
OWNERS = (*SENSOR_ROLES, *(r for r in service_table.with_acl("robot") if r not in SENSOR_ROLES))
# `ros2peer`: the robot's own ROS 2 nodes over rmw_zenoh (its drivers, RViz2, a Nav2 client).
ROBOT_ROLES = (*OWNERS, "tool", "router", "ros2peer")  # every robot's identities
DRIVERS = service_table.with_acl("drive")  # they publish cmd_vel, claim goals, send explorer goals
# the ros2 service sends the explorer the goals of the Nav2 actions it serves (NavigateToPose)
GOAL_SENDERS = (*DRIVERS, "ros2")
BASE_RUNS = service_table.with_acl("base")  # a robot's, that a base may run
FLEET_ROLES = service_table.with_acl("fleet")  # the fleet's, on the base
BASE_ROLES = ("operator", "tool", "router")
SENSOR_TOPICS = ("cloud", "scan", "pose", "pose_truth", "clock", "image/**")
# The queries that only read, on every namespace: `smana/*/<service>/<query>`. An allow rule
# grants a query only when its key expression includes the query's whole selector (zenoh 1.x,
# tested in tests/test_acl_table.py), so `smana/r1/mapper/*` or `smana/**` match none of these,
# and a query that writes (`mapper/save`, `coordinator/claim/<member>`) is granted by its exact
# key only. A deny rule would not do: it too applies only to selectors its key includes.
READ_QUERIES = (*(f"{r.name}/{q}" for r in service_table.rows() for q in r.reads), "*/status")

READ = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
OWN = ["put", "delete", "declare_queryable", "reply"]
ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]

RELAY_MESSAGES = [m for m in ALL_MESSAGES if m != "query"]

# ROS 2 over rmw_zenoh (docs/ros2.md, "The secured profile"). Data keys are `<domain>/<topic>/
# <type>/<hash>` (any domain: `*`); a robot's own topics are in its ROS namespace `/<robot>`
# (Nav2's multi-robot convention), smana's in `/smana/<robot>`, a simulated robot's frames too
# (`/smana/<robot>/tf`, ros2.tf_topic "auto": a shared /tf any robot could write is granted to
# none). Liveliness tokens are `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/
# <namespace>/...`: scoped by their namespace chunk, `%<robot>` or below it. A transient-local
# publisher's cache, heartbeat and detection token hang below its data key under `@adv/`, which
# `**` never matches (a chunk that starts with `@` is matched only by itself), so each rule
# names them too.
ROS2_PEER_TOPICS = ("points", "odom", "tf_static", "goal_pose")  # the robot's peer publishes
ROS2_CALLS = ("navigate_to_pose/_action", "compute_path_to_pose/_action", "plan")  # /smana/<r>/
EXPLORER_GOAL_QUERIES = ("explorer/goal", "explorer/goal/cancel")  # smana/<robot>/...
ROS2_ADV = "**/@adv/**"


def ROS2_PEER_RULES(r: str) -> list[str]:  # noqa: N802 - the ids of `_ros2_rules`
    return [f"ros2-peer-{r}{part}" for part in ("", "-own", "-tokens", "-calls")]


def ROS2_SMANA_RULES(r: str) -> list[str]:  # noqa: N802
    return [f"ros2-smana-{r}", f"ros2-smana-{r}-tokens"]


def ros2_tokens(namespace: str) -> list[str]:
    """The liveliness tokens of nodes (and their endpoints) in ROS namespace `namespace` and
    below it: the namespace chunk is `%a%b` for `/a/b`."""
    ns = namespace.strip("/").replace("/", "%")
    head = "@ros2_lv/" + "/".join(["*"] * 6)  # domain, zid, node id, entity id, kind, enclave
    return [f"{head}/%{ns}/**", f"{head}/%{ns}%$*/**"]


def user(robot: str, role: str) -> str:
    """A robot's (or the fleet's) identity: `r2.mapper`."""
    return f"{robot}.{role}"


def save_key(robot: str) -> str:
    return f"smana/{robot}/mapper/save"


def claim_key(fleet: str, member: str) -> str:
    return f"smana/{fleet}/coordinator/claim/{member}"


def goal_keys(robot: str) -> list[str]:
    """The explorer's goal and cancel queries of one robot (its drive role's)."""
    return [f"smana/{robot}/explorer/goal", f"smana/{robot}/explorer/goal/cancel"]


def _rule(
    id_: str, flows: list[str], messages: list[str], key_exprs: list[str], permission: str = "allow"
) -> dict:
    return {
        "id": id_,
        "permission": permission,
        "flows": flows,
        "messages": messages,
        "key_exprs": key_exprs,
    }


def acl_policy(
    robots: list[str] = ("r1",),
    fleet: str | None = "fleet",
    base: str = "base",
    base_identities: bool = True,
    revoked: list[str] = (),
    certified: list[str] | None = None,
) -> dict:
    """The access-control policy (the table in docs/deployment.md), default deny:

    - every identity may subscribe, list liveliness tokens and ask the read-only queries
      (`READ_QUERIES`) of every namespace;
    - each robot's identities write only under `smana/<its robot>/`: each service (and a driver)
      publishes, serves queries, replies and shows liveliness under its own name; the sensor roles
      publish the robot's sensor streams and pose (and `alive/robot`); its explorer publishes its
      velocity commands and claims goals at `smana/<fleet>/coordinator/claim/<robot>`, its own
      claim key only; the robot's drive role (its explorer) may send its explorer goals and
      cancel them (`explorer/goal`, `explorer/goal/cancel`, exact keys, its own robot's only);
      `<robot>.tool` only reads; its router relays everything of `smana/<robot>/**` but
      queries, and its explorer's claim and goal queries, and nothing of another robot's;
    - the fleet's identities write under `smana/<fleet>/` as each service under its own name;
    - with `base_identities` (the base's policy): `operator` may also publish every robot's
      velocity commands, send every robot's explorer goals and cancel them, and ask every
      robot's mapper to save (exact keys); `tool` only reads;
      `router` (the base's router) relays everything.

    - `revoked` robots: every message of a session presenting such a robot's certificate (its
      common name) is denied, both ways, whatever user it logs in as. zenoh checks certificates
      against the CA alone (no revocation list), and its deny rules win only within one subject:
      a session that matches several subjects is allowed what any of them allows. So with
      revoked names every identity's subject is bound to the links that carry no certificate
      (tcp, ...) or to the certificates still valid (`certified`: the robots' and the base's
      unless given), and a revoked certificate matches no subject but `revoked-certs`.

    Routers are named by user and link: user `<name>` on a tcp link, or the same user presenting
    its host's certificate (common name `<robot>`, or `base`) on TLS; a certificate alone grants
    nothing, since every TLS client must present one. A router that opened a TLS link cannot see
    a user name on it (user/password only authenticates the side that connects): `uplink_policy`
    trusts the far router by its certificate there."""
    robots = [check_robot(r) for r in robots]
    rules = [
        _rule("read", ["ingress"], READ, ["smana/**"]),
        _rule("read-queries", ["ingress"], ["query"], [f"smana/*/{q}" for q in READ_QUERIES]),
        # What routers send out to their clients: samples, replies, queries to queryables.
        _rule("deliver", ["egress"], ALL_MESSAGES, ["smana/**"]),
        _rule("relay", ["ingress", "egress"], ALL_MESSAGES, ["smana/**"]),
        # ROS 2: every identity may see the graph, subscribe to every topic and ask a
        # transient-local publisher's cache (a query under `@adv/` only: `*/**` would include
        # the selectors of the queries that write, `smana/<robot>/mapper/save` among them).
        _rule("ros2-read", ["ingress"], READ, ["@ros2_lv/**", "*/**", f"*/{ROS2_ADV}"]),
        _rule("ros2-history", ["ingress"], ["query"], [f"*/{ROS2_ADV}"]),
        _rule("ros2-deliver", ["egress"], ALL_MESSAGES, ["@ros2_lv/**", "*/**", f"*/{ROS2_ADV}"]),
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    readers: list[str] = []

    def identity(name: str, rule_ids: list[str]) -> None:
        subjects.append({"id": name, "usernames": [name]})
        readers.append(name)
        if rule_ids:
            policies.append({"id": name, "rules": rule_ids, "subjects": [name]})

    def router(name: str, host: str, rule_ids: list[str]) -> None:
        ids = [f"{name}@tcp", f"{name}@tls"]
        subjects.append({"id": ids[0], "usernames": [name], "link_protocols": ["tcp"]})
        subjects.append({"id": ids[1], "usernames": [name], "cert_common_names": [host]})
        policies.append({"id": name, "rules": rule_ids, "subjects": ids})

    def owners(ns: str, roles) -> None:
        for owner in roles:
            u = user(ns, owner)
            alive = [f"smana/{ns}/alive/{owner}"]
            ids = [f"own-{u}", f"alive-{u}"]
            rules.append(_rule(ids[0], ["ingress"], OWN, [f"smana/{ns}/{owner}/**"]))
            if owner in SENSOR_ROLES:
                alive.append(f"smana/{ns}/alive/robot")  # whatever drives the robot shows it
                ids.append(f"sensors-{ns}")
            if owner in DRIVERS:
                ids.append(f"cmd_vel-{ns}")
                if fleet:
                    ids.append(f"claim-{ns}")
            if owner in GOAL_SENDERS:
                ids.append(f"goal-{ns}")
            rules.append(_rule(ids[1], ["ingress"], ["liveliness_token"], alive))
            identity(u, ids)

    for r in robots:
        rules += _ros2_rules(r)
        rules += [
            _rule(
                f"sensors-{r}",
                ["ingress"],
                ["put"],
                [f"smana/{r}/robot/{t}" for t in SENSOR_TOPICS],
            ),
            _rule(f"cmd_vel-{r}", ["ingress"], ["put"], [f"smana/{r}/robot/cmd_vel"]),
            _rule(f"goal-{r}", ["ingress"], ["query"], goal_keys(r)),
            # All but queries: those a robot's router passes on are read-only or its claim.
            _rule(f"relay-{r}", ["ingress"], RELAY_MESSAGES, [f"smana/{r}/**"]),
        ]
        if fleet:
            rules.append(_rule(f"claim-{r}", ["ingress"], ["query"], [claim_key(fleet, r)]))
        owners(r, OWNERS)
        policies.append(
            {"id": f"ros2-{r}", "rules": ROS2_SMANA_RULES(r), "subjects": [user(r, "ros2")]}
        )
        identity(user(r, "ros2peer"), ROS2_PEER_RULES(r))
        identity(user(r, "tool"), [])
        relay = [f"relay-{r}", f"goal-{r}", *([f"claim-{r}"] if fleet else [])]
        router(user(r, "router"), r, ["read", "read-queries", "deliver", *relay])
    if fleet:
        owners(check_robot(fleet), FLEET_ROLES)
    if base_identities:
        save = [save_key(r) for r in robots] + ([save_key(fleet)] if fleet else [])
        rules += [
            _rule(
                "operator-cmd_vel",
                ["ingress"],
                ["put"],
                [f"smana/{r}/robot/cmd_vel" for r in robots],
            ),
            _rule("operator-save", ["ingress"], ["query"], save),
            _rule(
                "operator-goal", ["ingress"], ["query"], [k for r in robots for k in goal_keys(r)]
            ),
        ]
        identity("operator", ["operator-cmd_vel", "operator-save", "operator-goal"])
        identity("tool", [])
    router("router", base, ["relay"])
    if revoked:
        names = [check_robot(r) for r in revoked]
        valid = [c for c in (certified or [*robots, base]) if c not in names]
        _bind_to_certificates(subjects, policies, readers, valid)
        rules.append(
            _rule("revoked", ["ingress", "egress"], ALL_MESSAGES, ["**"], permission="deny")
        )
        subjects.append({"id": "revoked-certs", "cert_common_names": names})
        policies.append({"id": "revoked", "rules": ["revoked"], "subjects": ["revoked-certs"]})
    policies.insert(
        0,
        {
            "id": "read",
            "rules": [
                *("read", "read-queries", "deliver"),
                *("ros2-read", "ros2-history", "ros2-deliver"),
            ],
            "subjects": readers,
        },
    )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# zenoh's link kinds (`InterceptorLink`) whose sessions carry no certificate name.
PLAIN_LINKS = ["tcp", "udp", "ws", "unixsock-stream", "unixpipe", "serial", "vsock"]


def _bind_to_certificates(
    subjects: list[dict], policies: list[dict], readers: list[str], valid: list[str]
) -> None:
    """Split every subject that names no certificate and no link in two: on a plain link (no
    certificate to check), and on a link carrying one of the `valid` certificates. A session
    over tls or quic with any other certificate then matches neither."""
    split: dict[str, list[str]] = {}
    for s in list(subjects):
        if "cert_common_names" in s or "link_protocols" in s:
            continue
        tls = {**s, "id": f"{s['id']}@cert", "cert_common_names": list(valid)}
        s["link_protocols"] = list(PLAIN_LINKS)
        subjects.insert(subjects.index(s) + 1, tls)
        split[s["id"]] = [s["id"], tls["id"]]
    for pol in policies:
        pol["subjects"] = [x for sid in pol["subjects"] for x in split.get(sid, [sid])]
    readers[:] = [x for sid in readers for x in split.get(sid, [sid])]


def _ros2_rules(r: str) -> list[dict]:
    """Robot `r`'s ROS 2 rules: `ros2-peer-<r>` for its ROS 2 peer (`<r>.ros2peer`), which
    publishes the robot's topics in `/<r>` and calls smana's actions, plan service and explorer
    goal queries for `r`; `ros2-smana-<r>` for smana's ros2 service of `r` (`<r>.ros2`), which
    publishes and serves everything under `/smana/<r>` and sends `/<r>/cmd_vel`."""
    peer_topics = [f"*/{r}/{t}/**" for t in ROS2_PEER_TOPICS]
    smana_ns = [f"*/smana/{r}/**", f"*/smana/{r}/{ROS2_ADV}"]
    calls = [f"*/smana/{r}/{c}/**" for c in ROS2_CALLS]
    adv = [f"*/{r}/{t}/{ROS2_ADV}" for t in ROS2_PEER_TOPICS]
    return [
        _rule(f"ros2-peer-{r}", ["ingress"], ["put"], peer_topics + adv),
        _rule(f"ros2-peer-{r}-own", ["ingress"], OWN + ["liveliness_token"], adv),
        _rule(f"ros2-peer-{r}-tokens", ["ingress"], ["liveliness_token"], ros2_tokens(f"/{r}")),
        _rule(
            f"ros2-peer-{r}-calls",
            ["ingress"],
            ["query"],
            calls + [f"smana/{r}/{q}" for q in EXPLORER_GOAL_QUERIES],
        ),
        _rule(
            f"ros2-smana-{r}",
            ["ingress"],
            OWN + ["liveliness_token"],
            smana_ns + [f"*/{r}/cmd_vel/**", f"*/{r}/cmd_vel/{ROS2_ADV}"],
        ),
        _rule(
            f"ros2-smana-{r}-tokens",
            ["ingress"],
            ["liveliness_token"],
            ros2_tokens(f"/smana/{r}"),
        ),
    ]


def uplink_policy(policy: dict) -> dict:
    """`policy` as a router enforces it on the TLS links it opens to other routers (robot -> base).

    The far router cannot log in on a link this router opened (user/password authenticates only
    the connecting side), so it is known by its certificate alone: every subject that names user
    `router` with certificate common names gets a twin with only the common names, in the same
    policies. Safe only on a router with no TLS (or QUIC) listener, where no one else can present
    a certificate: `deploy/router.py` applies it there and nowhere else."""
    policy = copy.deepcopy(policy)
    twins = {}
    for s in policy.get("subjects") or []:
        if "router" in (s.get("usernames") or []) and s.get("cert_common_names"):
            twins[s["id"]] = {
                "id": f"{s['id']}-uplink",
                "cert_common_names": list(s["cert_common_names"]),
            }
    if not twins:
        return policy
    policy["subjects"] = [*policy["subjects"], *twins.values()]
    for p in policy.get("policies") or []:
        p["subjects"] += [twins[s]["id"] for s in list(p["subjects"]) if s in twins]
    return policy


def router_user(users: dict[str, str]) -> str:
    """The user a router logs in as, from its host's dictionary: `router` on the base, the one
    `<robot>.router` on a robot."""
    if "router" in users:
        return "router"
    mine = [u for u in users if u.endswith(".router")]
    if len(mine) != 1:
        raise ValueError(f"expected one router login in the dictionary, found {mine or 'none'}")
    return mine[0]


def robot_users(robot: str) -> list[str]:
    return [user(robot, role) for role in ROBOT_ROLES]


def base_users(robots: list[str], fleet: str | None) -> list[str]:
    """Whose passwords the base holds: its own, the fleet's, and per robot what a base may run
    for it and its router's login (checked when the robot links up)."""
    users = list(BASE_ROLES) + ([user(fleet, role) for role in FLEET_ROLES] if fleet else [])
    for r in robots:
        users += [user(r, role) for role in (*BASE_RUNS, "router")]
    return users


def _write_users(path: Path, passwords: dict[str, str], users: list[str]) -> None:
    write_secret(path, "".join(f"{u}:{passwords[u]}\n" for u in users))


def _write_host(
    out: Path, host: str, passwords: dict, users: list[str], policy: dict
) -> list[Path]:
    """A host's folder, its certificate aside: what its router and its clients need, no more."""
    folder = out / host
    folder.mkdir(exist_ok=True)
    os.chmod(folder, 0o700)
    shutil.copyfile(out / "ca.pem", folder / "ca.pem")
    _write_users(folder / "dictionary.txt", passwords, users)
    creds = folder / "credentials"
    shutil.rmtree(creds, ignore_errors=True)  # a revoked robot's files go with it
    creds.mkdir()
    os.chmod(creds, 0o700)
    written = [folder / "ca.pem", folder / "dictionary.txt"]
    for u in users:
        if u != "router" and not u.endswith(".router"):  # a router's login stays in the dictionary
            _write_users(creds / f"{u}.txt", passwords, [u])
            written.append(creds / f"{u}.txt")
    (folder / "acl.json5").write_text(json.dumps(policy, indent=2) + "\n")
    return [*written, folder / "acl.json5"]


def _books(out: Path) -> tuple[dict, dict[str, str]]:
    try:
        issued = json.loads((out / "issued.json").read_text())
        return issued, read_credentials(str(out / "users.txt"))
    except (OSError, ValueError) as exc:
        raise UsageError(f"{out} holds no set of `smana deploy init-certs` ({exc})") from None


def _write_books(out: Path, issued: dict, passwords: dict[str, str]) -> Path:
    (out / "issued.json").write_text(json.dumps(issued, indent=2) + "\n")
    _write_users(out / "users.txt", passwords, list(passwords))
    return out / "users.txt"


def _write_base(out: Path, issued: dict, passwords: dict[str, str]) -> list[Path]:
    robots, fleet, base = issued["robots"], issued["fleet"], issued["base"]
    certified = [*robots, *issued.get("clients", []), base]
    policy = acl_policy(robots, fleet, base, revoked=issued.get("revoked", []), certified=certified)
    return _write_host(out, base, passwords, base_users(robots, fleet), policy)


def _write_robot(out: Path, issued: dict, passwords: dict[str, str], robot: str) -> list[Path]:
    policy = acl_policy([robot], issued["fleet"], issued["base"], base_identities=False)
    return _write_host(out, robot, passwords, robot_users(robot), policy)


def _check_names(robots: list[str], fleet: str | None, base: str) -> None:
    try:
        for name in [*robots, *([fleet] if fleet else []), base]:
            check_robot(name)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    names = [*robots, *([fleet] if fleet else []), base]
    if len(set(names)) != len(names):
        raise UsageError(f"robot, fleet and base names must all differ, got {', '.join(names)}")


def init_certs(
    out: Path,
    robots: list[str] = ("r1",),
    fleet: str | None = "fleet",
    base: str = "base",
    days: int = 825,
    force: bool = False,
    clients: list[str] = (),
) -> list[Path]:
    """Create the CA, the issuer's books and one folder per host (the base and each robot) in
    `out`, and for each of `clients` (a host that only runs clients over TLS: an operator's
    laptop) a folder with `ca.pem` and its certificate alone, which grants nothing by itself: it
    logs in with a file from the base's `credentials/`. `FileExistsError` when `out` holds a set
    already and not `force`."""
    robots, clients = list(robots), list(clients)
    _check_names([*robots, *clients], fleet, base)
    if not robots:
        raise UsageError("--robots needs at least one name")
    if not 1 <= days <= 36500:
        raise UsageError(f"--days must be from 1 to 36500, got {days}")
    out.mkdir(parents=True, exist_ok=True)
    if (out / "ca.pem").exists() and not force:
        raise FileExistsError(f"{out}/ca.pem exists (use --force to replace the whole set)")
    old = json.loads((out / "issued.json").read_text()) if (out / "issued.json").exists() else {}
    for host in [*old.get("robots", []), *old.get("clients", []), *([old["base"]] if old else [])]:
        shutil.rmtree(out / check_robot(host), ignore_errors=True)
    # What earlier versions wrote: every password in one file, or one file per role for all
    # robots. Their passwords are void now.
    for name in ("credentials.txt", "dictionary.txt", "acl.json5"):
        (out / name).unlink(missing_ok=True)
    shutil.rmtree(out / "credentials", ignore_errors=True)
    ca_key, ca = new_ca(days)
    write_key(ca_key, out / "ca.key")
    write_cert(ca, out / "ca.pem")
    issued = {"robots": robots, "fleet": fleet, "base": base, "days": days, "clients": clients}
    users = base_users(robots, fleet) + [u for r in robots for u in robot_users(r)]
    passwords = {u: secrets.token_urlsafe(18) for u in dict.fromkeys(users)}
    written = [out / "ca.pem", out / "ca.key", _write_books(out, issued, passwords)]
    written += issue_host_cert(out, base, days) + _write_base(out, issued, passwords)
    for r in robots:
        written += issue_host_cert(out, r, days) + _write_robot(out, issued, passwords, r)
    for c in clients:
        written += issue_host_cert(out, c, days)
        shutil.copyfile(out / "ca.pem", out / c / "ca.pem")
        written.append(out / c / "ca.pem")
    return written


def add_robot(out: Path, robot: str) -> list[Path]:
    """Issue one more robot: its folder, and the base's dictionary and policy; nothing else."""
    issued, passwords = _books(out)
    if robot in issued["robots"]:
        raise UsageError(f"{robot} is issued already (revoke-robot it first to re-issue it)")
    if robot in issued.get("revoked", []):  # its old certificate carries the same name
        raise UsageError(f"{robot} was revoked: its name stays denied; issue it under a new name")
    _check_names(
        [*issued["robots"], *issued.get("clients", []), robot], issued["fleet"], issued["base"]
    )
    issued["robots"].append(robot)
    for u in robot_users(robot):
        passwords[u] = secrets.token_urlsafe(18)
    written = [_write_books(out, issued, passwords)]
    written += issue_host_cert(out, robot, issued["days"])
    written += _write_robot(out, issued, passwords, robot)
    return written + _write_base(out, issued, passwords)


def revoke_robot(out: Path, robot: str) -> list[Path]:
    """Forget a robot: its passwords leave the base's dictionary and its rules the base's policy,
    so its router and services can no longer log in; and its certificate's common name joins the
    base policy's `revoked` subjects, whose every message is denied both ways (zenoh has no
    revocation list: the certificate still completes a TLS handshake, and carries nothing)."""
    issued, passwords = _books(out)
    if robot not in issued["robots"]:
        raise UsageError(f"{robot} is not issued (issued: {', '.join(issued['robots'])})")
    issued["robots"].remove(robot)
    issued["revoked"] = sorted({*issued.get("revoked", []), robot})
    for u in robot_users(robot):
        passwords.pop(u, None)
    shutil.rmtree(out / robot, ignore_errors=True)
    return [_write_books(out, issued, passwords), *_write_base(out, issued, passwords)]


def _names(text: str) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()]


def _robot_names(text: str) -> list[str]:
    """An argparse type: one robot name or more, comma-separated (`''` is no robot at all)."""
    names = _names(text)
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated robot names, got {text!r}")
    return names


HANDOUT = (
    "Copy each host's folder to that host as certs/: {base}/ to the base, <robot>/ to each robot. "
    "ca.key, users.txt and issued.json go nowhere."
)


def cli(argv: list[str] | None = None) -> int:
    p = ArgumentParser(
        prog="smana deploy",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    ic = sub.add_parser("init-certs", help="create a CA, host folders (certificates, users, ACL)")
    ic.add_argument("--out", default="certs", help="folder to write into (default ./certs)")
    ic.add_argument(
        "--robots",
        type=_robot_names,
        default="r1",
        help="comma-separated robot names (default r1)",
    )
    ic.add_argument("--fleet", default="fleet", help="the fleet's name (fleet.name)")
    ic.add_argument("--base", default="base", help="the base station's host name")
    ic.add_argument(
        "--clients",
        default="",
        help="comma-separated hosts that only run clients over TLS (an operator's laptop): a "
        "certificate each, no password",
    )
    ic.add_argument("--days", type=int, default=825, help="validity of the certificates (>= 1)")
    ic.add_argument("--force", action="store_true", help="replace an existing set")
    for name, what in (("add-robot", "issue one more robot"), ("revoke-robot", "forget a robot")):
        sp = sub.add_parser(name, help=f"{what}: its folder and the base's; no other robot's")
        sp.add_argument("robot")
        sp.add_argument("--out", default="certs", help="the set's folder (default ./certs)")
    acl = sub.add_parser("acl", help="print the access-control policy (JSON5)")
    acl.add_argument(
        "--robots", type=_robot_names, default="r1", help="comma-separated robot names"
    )
    acl.add_argument("--fleet", default="fleet", help="the fleet's name")
    acl.add_argument("--base", default="base", help="the base station's host name")
    args = p.parse_args(argv)
    if args.cmd == "acl":
        _check_names(args.robots, args.fleet, args.base)
        print(json.dumps(acl_policy(args.robots, args.fleet, args.base), indent=2))
        return 0
    out = Path(args.out)
    try:
        if args.cmd == "init-certs":
            files = init_certs(
                out,
                args.robots,
                args.fleet,
                args.base,
                args.days,
                args.force,
                _names(args.clients),
            )
        elif args.cmd == "add-robot":
            files = add_robot(out, args.robot)
        else:
            files = revoke_robot(out, args.robot)
    except FileExistsError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        where = exc.filename or out
        raise UsageError(f"cannot write {where}: {exc.strerror or exc}") from None
    for f in files:
        print(f)
    issued, _ = _books(out)
    print(HANDOUT.format(base=issued["base"]))
    return 0
