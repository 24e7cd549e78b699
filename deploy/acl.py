"""Who may do what in a secured deployment: the identities (`<robot>.<role>` for what belongs to
one robot, `<fleet>.<role>` for the fleet's shared services, `operator`, `tool` and `router` on
the base; `user`), whose passwords each host holds (`robot_users`, `base_users`), and the
access-control policy each router enforces (`acl_policy`; `uplink_policy` for the links a router
opens; the ROS 2 peers' rules), all from the table of services. security.py writes them into the
hosts' folders (`smana deploy`); docs/deployment.md has the policy as a table.
"""

from __future__ import annotations

import copy

from smana.common import service_table
from smana.common.keys import check_robot

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
SENSOR_TOPICS = ("cloud", "scan", "safety_scan", "pose", "pose_truth", "clock", "image/**")
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
