"""`smana deploy init-certs` and the security config, in process: which host's folder holds which
password, how a session finds its login, where a router trusts the routers it links to by
certificate, and the services' own checks on the queries that change state (a save, a claim),
which hold with or without a policy. The policy itself is tested against a real router in
test_acl_table.py."""

from __future__ import annotations

import dataclasses
import json
import math
import stat
import subprocess
import sys

import pytest

from smana.common import keys
from smana.common.cli import UsageError
from smana.common.config import ConfigError, ZenohConfig
from smana.common.query import QueryError, request
from smana.common.zenoh_config import make_zenoh_config, read_credentials
from smana.deploy.acl import OWNERS, acl_policy, uplink_policy
from smana.deploy.router import router_config
from smana.deploy.security import add_robot, init_certs, revoke_robot
from tests.conftest import REPO, saved_maps

ROBOTS = ["r1", "r2"]


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    out = tmp_path_factory.mktemp("certs")
    init_certs(out, ROBOTS)
    return out


def mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def every_file(folder):
    return [p for p in folder.rglob("*") if p.is_file()]


def test_each_host_holds_only_its_own_secrets(certs):
    every = read_credentials(str(certs / "users.txt"))
    assert len(set(every.values())) == len(every)  # no password twice
    for robot in ROBOTS:
        folder = certs / robot
        mine = read_credentials(str(folder / "dictionary.txt"))
        assert set(mine) == {f"{robot}.{r}" for r in (*OWNERS, "tool", "router", "ros2peer")}
        # No other robot's, no operator's, no base router's password, in any file of the folder
        text = b"".join(p.read_bytes() for p in every_file(folder))
        leaked = [u for u, pw in every.items() if u not in mine and pw.encode() in text]
        assert leaked == [], leaked
        for f in (folder / "credentials").iterdir():
            assert read_credentials(str(f)) == {f.stem: mine[f.stem]} and mode(f) == 0o600
        assert not (folder / "credentials" / f"{robot}.router.txt").exists()
        # the robot's own ROS 2 nodes log in with this one (docs/ros2.md)
        assert (folder / "credentials" / f"{robot}.ros2peer.txt").is_file()
        assert mode(folder / "dictionary.txt") == 0o600 and mode(folder / "host.key") == 0o600
        assert mode(folder) == 0o700 and mode(folder / "credentials") == 0o700
    base = read_credentials(str(certs / "base" / "dictionary.txt"))
    # what the base runs (its own, the fleet's, the robots' base-side services) and the robots'
    # router logins it checks; none of a robot's sensors' or mapper's
    assert {"operator", "tool", "router", "fleet.coordinator", "r2.explorer", "r2.router"} <= set(
        base
    )
    assert not {u for u in base if u.split(".")[-1] in ("sim", "driver", "replay", "mapper")} - {
        "fleet.mapper"
    }
    assert all(base[u] == every[u] for u in base)
    assert mode(certs / "ca.key") == 0o600 and mode(certs / "users.txt") == 0o600


def snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in every_file(folder)}


def test_adding_or_revoking_a_robot_leaves_the_others_alone(tmp_path):
    init_certs(tmp_path, ROBOTS)
    r1, base_cert = snapshot(tmp_path / "r1"), (tmp_path / "base" / "host.pem").read_bytes()
    add_robot(tmp_path, "r3")
    base = read_credentials(str(tmp_path / "base" / "dictionary.txt"))
    assert "r3.router" in base and "r3.explorer" in base
    assert "smana/r3/robot/cmd_vel" in (tmp_path / "base" / "acl.json5").read_text()
    r3 = read_credentials(str(tmp_path / "r3" / "dictionary.txt"))
    assert set(r3) == {f"r3.{r}" for r in (*OWNERS, "tool", "router", "ros2peer")}
    revoke_robot(tmp_path, "r2")
    assert not (tmp_path / "r2").exists()
    base = read_credentials(str(tmp_path / "base" / "dictionary.txt"))
    assert not [u for u in base if u.startswith("r2.")]
    assert "smana/r2/" not in (tmp_path / "base" / "acl.json5").read_text()
    assert not (tmp_path / "base" / "credentials" / "r2.explorer.txt").exists()
    assert snapshot(tmp_path / "r1") == r1  # untouched, byte for byte
    assert (tmp_path / "base" / "host.pem").read_bytes() == base_cert


def test_force_replaces_the_set_and_removes_old_files(tmp_path):
    init_certs(tmp_path, ["r1"])
    (tmp_path / "credentials.txt").write_text("router:old\n")  # what old versions wrote
    with pytest.raises(FileExistsError):
        init_certs(tmp_path, ["r1"])
    init_certs(tmp_path, ["r7"], force=True)
    assert not (tmp_path / "credentials.txt").exists() and not (tmp_path / "r1").exists()


def deploy(*args, cwd=REPO):
    return subprocess.run(
        [sys.executable, "-m", "smana.deploy", "deploy", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        stdin=subprocess.DEVNULL,
    )


@pytest.mark.parametrize(
    "args, words",
    [
        (["init-certs", "--days", "-1"], ["--days"]),
        (["init-certs", "--days", "99999999"], ["--days"]),
        (["init-certs", "--out", "/proc/nope"], ["/proc/nope"]),
        (["init-certs", "--robots", "r1,a/b"], ["a/b"]),
        (["init-certs", "--robots", "r1,r1"], ["differ"]),
        (["add-robot", "r3", "--out", "/nonexistent/set"], ["/nonexistent/set"]),
    ],
)
def test_init_certs_misuse_is_one_line_and_status_2(tmp_path, args, words):
    r = deploy(*args, cwd=tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("smana deploy") and all(w in lines[0] for w in words), lines[0]


def test_deploy_acl_prints_the_bases_policy(tmp_path):
    r = deploy("acl", "--robots", "r1,r2", cwd=tmp_path)
    assert r.returncode == 0 and json.loads(r.stdout) == acl_policy(ROBOTS)


def test_init_certs_refuses_to_overwrite_a_set(tmp_path):
    assert deploy("init-certs", "--out", "c", cwd=tmp_path).returncode == 0
    r = deploy("init-certs", "--out", "c", cwd=tmp_path)
    assert r.returncode == 2 and "--force" in r.stderr and len(r.stderr.splitlines()) == 1


def usrpwd(conf) -> dict:
    return json.loads(conf.get_json("transport/auth/usrpwd"))


def test_a_client_logs_in_from_its_own_file(certs):
    tool = certs / "base" / "credentials" / "tool.txt"
    password = read_credentials(str(tool))["tool"]
    # The file's one line names the user; naming it again changes nothing.
    for user in ("", "tool"):
        auth = usrpwd(make_zenoh_config(ZenohConfig(user=user, credentials_file=str(tool))))
        assert (auth["user"], auth["password"], auth["dictionary_file"]) == ("tool", password, None)
    with pytest.raises(ConfigError, match="'mapper' has no line"):
        make_zenoh_config(ZenohConfig(user="mapper", credentials_file=str(tool)))


def test_a_router_logs_in_as_its_hosts_router(certs):
    for host, user in (("base", "router"), ("r2", "r2.router")):
        zc = ZenohConfig(credentials_file=str(certs / host / "dictionary.txt"))
        auth = usrpwd(router_config(["tcp/127.0.0.1:0"], zc))
        assert auth["user"] == user and auth["dictionary_file"].endswith("dictionary.txt")
    # A host that got only one client's file cannot run a router that links to others.
    with pytest.raises(ConfigError, match="router login"):
        router_config(
            ["tcp/127.0.0.1:0"],
            dataclasses.replace(zc, credentials_file=str(certs / "base/credentials/tool.txt")),
        )


def test_no_certificate_alone_names_a_subject():
    for s in acl_policy(ROBOTS)["subjects"]:
        if s.get("cert_common_names"):
            assert s["usernames"] and s["usernames"][0].split(".")[-1] == "router", s


def test_no_rule_but_a_routers_grants_a_wildcard_query_that_could_reach_a_write():
    """The static half of the selector matrix in test_acl_table.py: every query rule's key either
    names a query that only reads or is one exact key; only a router's relays `**`. A ROS 2 rule's
    wildcard key (`*/**/@adv/**`, `*/smana/<robot>/<action>/**`) includes no selector of a
    query that writes, its wildcard forms included."""
    import zenoh

    policy = acl_policy(ROBOTS)
    writes = [
        w
        for r in ROBOTS
        for key in (f"smana/{r}/mapper/save", f"smana/fleet/coordinator/claim/{r}")
        for w in (key, key.rsplit("/", 1)[0] + "/*", "smana/**", f"smana/{r}/**", "**")
    ]
    assert {rule["permission"] for rule in policy["rules"]} == {"allow"}  # no deny to get past
    for rule in policy["rules"]:
        if "query" not in rule["messages"] or "ingress" not in rule["flows"]:
            continue
        for k in rule["key_exprs"]:
            if rule["id"] == "read-queries":
                assert k.startswith("smana/*/") and "save" not in k and "claim/" not in k, k
            elif rule["id"] in ("relay",) or rule["id"].startswith("relay-"):
                continue
            elif rule["id"].startswith("ros2-") and k.startswith("*/"):
                assert not [w for w in writes if zenoh.KeyExpr(k).includes(w)], (rule["id"], k)
            else:
                assert "*" not in k and "$" not in k, (rule["id"], k)


def enforced(certs, listen, connect, host="r1") -> dict:
    zc = ZenohConfig(
        tls_ca=str(certs / host / "ca.pem"),
        tls_cert=str(certs / host / "host.pem"),
        tls_key=str(certs / host / "host.key"),
        credentials_file=str(certs / host / "dictionary.txt"),
        acl_file=str(certs / host / "acl.json5"),
    )
    return json.loads(router_config(listen, zc, connect).get_json("access_control"))


def relayed_by_certificate(policy) -> set[str]:
    """Common names that get a relay rule with no user name attached."""
    subjects = {s["id"]: s for s in policy["subjects"]}
    names = set()
    for p in policy["policies"]:
        if any(r == "relay" or r.startswith("relay-") for r in p["rules"]):
            for sid in p["subjects"]:
                if not subjects[sid].get("usernames"):
                    names |= set(subjects[sid].get("cert_common_names") or [])
    return names


def test_a_router_trusts_a_certificate_only_on_links_it_opened(certs):
    lo, tls_in, tls_out = ["tcp/127.0.0.1:7447"], ["tls/0.0.0.0:7448"], ["tls/10.0.0.2:7448"]
    # A robot: loopback for its services, a TLS link out to the base, which it trusts.
    assert relayed_by_certificate(enforced(certs, lo, tls_out)) == {"base"}
    # The base listens on TLS, where anyone with a host certificate can connect: no such trust.
    assert relayed_by_certificate(enforced(certs, lo + tls_in, [], "base")) == set()
    assert relayed_by_certificate(enforced(certs, lo + tls_in, tls_out, "base")) == set()
    assert relayed_by_certificate(enforced(certs, lo, [])) == set()


def test_uplink_policy_adds_a_twin_to_the_routers_policies():
    policy = acl_policy(["r1"], base_identities=False)
    twin = uplink_policy(policy)
    assert policy == acl_policy(["r1"], base_identities=False)  # the input is left alone
    assert {"id": "router@tls-uplink", "cert_common_names": ["base"]} in twin["subjects"]
    routers = next(p for p in twin["policies"] if p["id"] == "router")
    assert routers["subjects"] == ["router@tcp", "router@tls", "router@tls-uplink"]


# -- the services' own checks on a save and a claim, on an unsecured (fake) network -------------


def test_a_save_by_a_wildcard_or_past_the_quota_writes_nothing(fake_stack, tmp_path):
    st = fake_stack
    st.service(
        "mapper",
        "--save",
        str(tmp_path / "map.npz"),
        "--set",
        "mapper.autosave_period_s=0",
        "--set",
        "mapper.save_max_files=3",
    )
    st.wait_alive("mapper")
    s, r = st.session, st.robot
    exact = keys.query(r, "mapper", "save")
    shapes = ("mapper/*", "mapper/**", "*/save", "**", "mapper/sav$*", "**/save")
    for sel in shapes:  # each reaches the save queryable, which refuses it
        list(s.get(f"smana/{r}/{sel}", timeout=5.0))
    assert saved_maps(tmp_path) == []  # (the mapper's own journal aside)
    # the exact key saves, within the quota: map.npz and two more files, then `quota`
    for name in ("a.npz", "b.npz"):
        assert request(s, exact, {"name": name})["ok"]
    assert request(s, exact)["ok"]  # map.npz itself
    with pytest.raises(QueryError) as err:
        request(s, exact, {"name": "c.npz"})
    assert err.value.kind == "quota"
    assert request(s, exact, {"name": "a.npz"})["ok"]  # rewriting one adds nothing
    assert saved_maps(tmp_path) == ["a.npz", "b.npz", "map.npz"]
    assert st.drained("mapper")
    status = st.status("mapper")
    assert status.rejected.get("selector") == 6 and status.rejected.get("quota") == 1
    assert status.books_add_up()


def test_a_claim_from_a_stranger_by_a_wildcard_or_off_the_map_is_refused(fake_stack):
    st = fake_stack
    st.service("coordinator", "--set", 'fleet.robots=["r1", "r2"]')
    st.wait_alive("coordinator")
    s, fleet = st.session, st.robot
    assert request(s, keys.claim(fleet, "r1"), {"goal": [1.0, 1.0]})["granted"]
    refused = {
        "member": [(keys.claim(fleet, "r2"), {"robot": "r1", "goal": [9.0, 9.0]})],
        "value": [
            (keys.claim(fleet, "r2"), {"goal": [1e308, 1e308]}),
            (keys.claim(fleet, "r2"), {"goal": [math.inf, 0.0]}),
            (keys.claim(fleet, "r2"), {"goal": [0.0, 51.0]}),  # navgraph bounds: +-50 m
        ],
    }
    for kind, cases in refused.items():
        for key, body in cases:
            with pytest.raises(QueryError) as err:
                request(s, key, body)
            assert err.value.kind == kind, (key, body, err.value)
    # a stranger: no member's key is its own, and a wildcard reaches every member's queryable,
    # each of which refuses it
    with pytest.raises(QueryError):
        request(s, keys.query(fleet, "coordinator", "claim/r9"), {"goal": [20.0, 20.0]})
    for sel in ("claim/*", "**", "claim/r$*"):  # 2 members' queryables each
        release = json.dumps({"goal": None}).encode()
        list(s.get(f"smana/{fleet}/coordinator/{sel}", payload=release, timeout=5.0))
    assert st.drained("coordinator")
    claims = request(s, keys.claims(fleet))["claims"]
    assert claims == {"r1": [1.0, 1.0]}  # nothing a stranger or a wildcard sent changed it
    status = st.status("coordinator")
    assert status.rejected.get("member") == 1 and status.rejected.get("value") == 3
    assert status.rejected.get("selector") == 6 and status.books_add_up()


@pytest.mark.parametrize(
    "profile, host",
    [
        ("robot", "r1"),
        ("fleet-robot", "r1"),
        ("base", "base"),
        ("multi-robot", "base"),
        ("fleet", "base"),
    ],
)
def test_each_secured_profile_runs_on_its_hosts_folder(certs, tmp_path, profile, host):
    """A profile's [zenoh] files are in its host's folder once copied as `certs/`, and every
    service the profile starts finds its own `<robot>.<service>` login there."""
    from smana.common.config import SmanaConfig
    from smana.deploy.supervisor import Supervisor, profile_path

    (tmp_path / "certs").symlink_to(certs / host)
    cfg = SmanaConfig.load(layers=[profile_path(profile)])
    for field in ("tls_ca", "tls_cert", "tls_key", "credentials_file", "acl_file"):
        assert (tmp_path / getattr(cfg.zenoh, field)).is_file(), (profile, field)
    users = read_credentials(str(certs / host / "dictionary.txt"))
    cfg = dataclasses.replace(
        cfg,
        zenoh=dataclasses.replace(
            cfg.zenoh, credentials_file=str(tmp_path / cfg.zenoh.credentials_file)
        ),
    )
    procs = Supervisor(cfg, tmp_path / "run").procs.values()
    logins = [[a for a in p.argv if a.startswith("zenoh.user=")] for p in procs]
    assert logins and all(len(one) == 1 for one in logins), logins
    missing = {s for (s,) in logins if s.split("=", 1)[1].strip('"') not in users}
    assert not missing, (profile, missing)


def test_a_client_host_gets_a_certificate_and_no_password(tmp_path):
    init_certs(tmp_path, ["r1"], clients=["laptop"])
    folder = tmp_path / "laptop"
    assert sorted(p.name for p in folder.iterdir()) == ["ca.pem", "host.key", "host.pem"]
    text = b"".join(p.read_bytes() for p in every_file(folder))
    every = read_credentials(str(tmp_path / "users.txt"))
    assert not [u for u, pw in every.items() if pw.encode() in text]
    with pytest.raises(UsageError):  # a client's name is taken like a robot's
        add_robot(tmp_path, "laptop")


def test_the_policy_grants_nothing_outside_smana_and_ros2():
    """Default deny, and every allow rule's key is under `smana/` or one of ROS 2's (a data key
    `<domain>/...`, a liveliness token `@ros2_lv/...`) in a rule named `ros2-*`: the secured
    profile admits smana's keys and ROS 2's (docs/ros2.md, docs/deployment.md)."""
    for base_identities in (True, False):
        policy = acl_policy(["r1", "r2"], "fleet", "base", base_identities=base_identities)
        assert policy["enabled"] is True and policy["default_permission"] == "deny"
        keys = [
            k
            for rule in policy["rules"]
            for k in rule["key_exprs"]
            if not (rule["id"].startswith("ros2-") and k.startswith(("*/", "@ros2_lv/")))
        ]
        assert keys and all(k.startswith("smana/") for k in keys), keys
        assert all(rule["permission"] == "allow" for rule in policy["rules"])


def test_only_a_robots_drive_role_ros2_identities_and_operator_may_send_its_goals():
    """The policy's side of `explorer/goal` and `goal/cancel` (the router's side, every identity
    on every listener, is test_acl_table.py): exact keys, granted to the robot's explorer, its
    router and the base's operator; no other robot's identity, no other role of the robot."""
    policy = acl_policy(["r1", "r2"])
    rules = {r["id"]: r for r in policy["rules"]}
    goal_keys = ["smana/r1/explorer/goal", "smana/r1/explorer/goal/cancel"]

    def granted(user: str) -> set[str]:
        subjects = {s["id"] for s in policy["subjects"] if user in (s.get("usernames") or [])}
        out = set()
        for p in policy["policies"]:
            if subjects & set(p["subjects"]):
                for rid in p["rules"]:
                    r = rules[rid]
                    if "query" in r["messages"] and "ingress" in r["flows"]:
                        out |= {k for k in r["key_exprs"] if "/explorer/goal" in k}
        return out

    assert rules["goal-r1"]["key_exprs"] == goal_keys
    assert granted("r1.explorer") == set(goal_keys)
    assert granted("r1.router") == set(goal_keys)
    assert granted("operator") == set(goal_keys) | {k.replace("r1", "r2") for k in goal_keys}
    # the ros2 service forwards its Nav2 actions' goals; the robot's ROS 2 peer may send them too
    assert granted("r1.ros2") == set(goal_keys)
    assert granted("r1.ros2peer") == set(goal_keys)
    for other in (
        "r2.explorer",
        "r2.router",
        "r2.ros2",
        "r2.ros2peer",
        "r1.mapper",
        "r1.tool",
        "tool",
    ):
        assert not granted(other) & set(goal_keys), other


def test_no_router_is_granted_a_ros2_key():
    """docs/deployment.md: "Routers do not relay ROS 2 keys between hosts": no policy that names
    a router (the base's `router`, a robot's `<r>.router`) holds a ROS 2 rule, and every key of
    its rules is smana's."""
    for base_identities in (True, False):
        policy = acl_policy(["r1", "r2"], "fleet", "base", base_identities=base_identities)
        rules = {r["id"]: r for r in policy["rules"]}
        routers = {
            s["id"]
            for s in policy["subjects"]
            if any(u == "router" or u.endswith(".router") for u in s.get("usernames") or [])
        }
        assert routers
        names = [p for p in policy["policies"] if routers & set(p["subjects"])]
        assert names
        for p in names:
            assert not [r for r in p["rules"] if r.startswith("ros2-")], p
            keys = [k for r in p["rules"] for k in rules[r]["key_exprs"]]
            assert keys and all(k.startswith("smana/") for k in keys), (p["id"], keys)


def test_every_identity_but_a_router_may_read_ros2():
    """docs/deployment.md and docs/ros2.md: every identity but a router may subscribe to every ROS
    2 topic, list the ROS graph and ask a cache for its history (the real router's side, for the
    ros2 service, a robot's peer and its tool: tests/test_acl_ros2.py)."""
    policy = acl_policy(["r1", "r2"], "fleet", "base")
    rules = {r["id"]: r for r in policy["rules"]}
    (read,) = [p for p in policy["policies"] if p["id"] == "read"]
    assert {"ros2-read", "ros2-history", "ros2-deliver"} <= set(read["rules"])
    assert {"@ros2_lv/**", "*/**"} <= set(rules["ros2-read"]["key_exprs"])
    users = {u for s in policy["subjects"] for u in s.get("usernames") or []}
    routers = {u for u in users if u == "router" or u.endswith(".router")}
    assert routers and set(read["subjects"]) == users - routers


def test_a_revoked_robots_certificate_is_denied_everything_at_the_base(tmp_path):
    # zenoh checks a certificate against the CA only: the base's policy denies the revoked
    # robot's common name every message, both ways, and zenoh's explicit denies win over allows
    init_certs(tmp_path, ["r1", "r2"])
    revoke_robot(tmp_path, "r2")
    policy = json.loads((tmp_path / "base" / "acl.json5").read_text())
    subject = next(s for s in policy["subjects"] if s["id"] == "revoked-certs")
    assert subject == {"id": "revoked-certs", "cert_common_names": ["r2"]}
    rule = next(r for r in policy["rules"] if r["id"] == "revoked")
    assert rule["permission"] == "deny" and rule["key_exprs"] == ["**"]
    assert set(rule["flows"]) == {"ingress", "egress"} and set(rule["messages"]) >= {
        "put",
        "query",
        "declare_subscriber",
        "reply",
        "liveliness_token",
    }
    assert {"id": "revoked", "rules": ["revoked"], "subjects": ["revoked-certs"]} in policy[
        "policies"
    ]
    # no subject of r1 names r2's certificate; and r2 cannot be issued again under its name
    assert not [s for s in policy["subjects"] if "r2" in s.get("cert_common_names", [])][1:]
    with pytest.raises(UsageError, match="revoked"):
        add_robot(tmp_path, "r2")
    revoke_robot(tmp_path, "r1")
    policy = json.loads((tmp_path / "base" / "acl.json5").read_text())
    subject = next(s for s in policy["subjects"] if s["id"] == "revoked-certs")
    assert subject["cert_common_names"] == ["r1", "r2"]


def test_with_a_revoked_name_every_identity_is_bound_to_plain_links_or_valid_certificates(tmp_path):
    # zenoh allows a session what any subject it matches allows (a deny wins only inside one
    # subject): a subject naming neither a link nor a certificate would let a revoked
    # certificate in with any password it got hold of. Checked on two hosts in
    # tests/test_multihost_security.py.
    init_certs(tmp_path, ["r1", "r2"], clients=["laptop"])
    revoke_robot(tmp_path, "r2")
    policy = json.loads((tmp_path / "base" / "acl.json5").read_text())
    by_id = {s["id"]: s for s in policy["subjects"]}
    for s in policy["subjects"]:
        assert "cert_common_names" in s or set(s["link_protocols"]) <= {
            "tcp",
            "udp",
            "ws",
            "unixsock-stream",
            "unixpipe",
            "serial",
            "vsock",
        }, s
        assert "r2" not in s.get("cert_common_names", []) or s["id"] == "revoked-certs"
    assert set(by_id["r1.explorer@cert"]["cert_common_names"]) == {"r1", "laptop", "base"}
    for pol in policy["policies"]:  # every identity keeps its rules on both variants
        ids = set(pol["subjects"])
        assert all(f"{i}@cert" in ids for i in ids if f"{i}@cert" in by_id), pol["id"]
