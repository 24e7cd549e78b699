"""`smana deploy init-certs` and the security config, in process: which file holds which password,
how a session finds its login, and where a router trusts the routers it links to by certificate.
The policy itself is tested against a real router in test_acl_table.py."""

from __future__ import annotations

import dataclasses
import json
import stat

import pytest

from smana.common.config import ConfigError, ZenohConfig
from smana.common.zenoh_config import make_zenoh_config, read_credentials
from smana.deploy.router import router_config
from smana.deploy.security import ROLES, acl_policy, init_certs, uplink_policy


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    out = tmp_path_factory.mktemp("certs")
    init_certs(out, ["robot", "base"])
    return out


def mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_only_the_routers_dictionary_holds_every_password(certs):
    dictionary = read_credentials(str(certs / "dictionary.txt"))
    assert set(dictionary) == set(ROLES)
    assert not (certs / "credentials.txt").exists()
    files = sorted((certs / "credentials").iterdir())
    assert [f.stem for f in files] == sorted(set(ROLES) - {"router"})
    for f in files:
        assert read_credentials(str(f)) == {f.stem: dictionary[f.stem]}
        assert mode(f) == 0o600
    assert mode(certs / "dictionary.txt") == 0o600 and mode(certs / "credentials") == 0o700
    assert mode(certs / "ca.key") == 0o600 and mode(certs / "robot.key") == 0o600


def test_force_replaces_the_set_and_removes_an_old_all_in_one_file(tmp_path):
    init_certs(tmp_path, ["robot"])
    (tmp_path / "credentials.txt").write_text("router:old\n")
    with pytest.raises(FileExistsError):
        init_certs(tmp_path, ["robot"])
    init_certs(tmp_path, ["robot"], force=True)
    assert not (tmp_path / "credentials.txt").exists()


def usrpwd(conf) -> dict:
    return json.loads(conf.get_json("transport/auth/usrpwd"))


def test_a_client_logs_in_from_its_roles_file(certs):
    tool = certs / "credentials" / "tool.txt"
    password = read_credentials(str(tool))["tool"]
    # The file's one line names the user; naming it again changes nothing.
    for user in ("", "tool"):
        auth = usrpwd(make_zenoh_config(ZenohConfig(user=user, credentials_file=str(tool))))
        assert (auth["user"], auth["password"], auth["dictionary_file"]) == ("tool", password, None)
    with pytest.raises(ConfigError, match="'mapper' has no line"):
        make_zenoh_config(ZenohConfig(user="mapper", credentials_file=str(tool)))
    # The dictionary names many users: a client must say which one it is.
    auth = usrpwd(make_zenoh_config(ZenohConfig(credentials_file=str(certs / "dictionary.txt"))))
    assert auth["user"] is None


def test_a_router_needs_the_dictionary(certs):
    zc = ZenohConfig(credentials_file=str(certs / "dictionary.txt"))
    auth = usrpwd(router_config(["tcp/127.0.0.1:0"], zc))
    assert auth["user"] == "router" and auth["dictionary_file"].endswith("dictionary.txt")
    # A host that got only a role's file cannot run a router that links to others.
    with pytest.raises(ConfigError, match="'router' has no line"):
        router_config(
            ["tcp/127.0.0.1:0"],
            dataclasses.replace(zc, credentials_file=str(certs / "credentials" / "tool.txt")),
        )


def test_no_certificate_alone_names_a_subject():
    for s in acl_policy(hosts=["robot", "base"])["subjects"]:
        if s.get("cert_common_names"):
            assert s["usernames"] == ["router"], s


def enforced(certs, listen, connect) -> dict:
    zc = ZenohConfig(
        tls_ca=str(certs / "ca.pem"),
        tls_cert=str(certs / "robot.pem"),
        tls_key=str(certs / "robot.key"),
        credentials_file=str(certs / "dictionary.txt"),
        acl_file=str(certs / "acl.json5"),
    )
    return json.loads(router_config(listen, zc, connect).get_json("access_control"))


def relayed_by_certificate(policy) -> set[str]:
    """Common names that get the relay rule with no user name attached."""
    subjects = {s["id"]: s for s in policy["subjects"]}
    names = set()
    for p in policy["policies"]:
        if "relay" in p["rules"]:
            for sid in p["subjects"]:
                if not subjects[sid].get("usernames"):
                    names |= set(subjects[sid].get("cert_common_names") or [])
    return names


def test_a_router_trusts_a_certificate_only_on_links_it_opened(certs):
    lo, tls_in, tls_out = ["tcp/127.0.0.1:7447"], ["tls/0.0.0.0:7448"], ["tls/10.0.0.2:7448"]
    # The robot: loopback for its services, a TLS link out to the base.
    assert relayed_by_certificate(enforced(certs, lo, tls_out)) == {"robot", "base"}
    # The base listens on TLS, where anyone with a host certificate can connect: no such trust.
    assert relayed_by_certificate(enforced(certs, lo + tls_in, [])) == set()
    assert relayed_by_certificate(enforced(certs, lo + tls_in, tls_out)) == set()
    assert relayed_by_certificate(enforced(certs, lo, [])) == set()


def test_uplink_policy_adds_a_twin_to_the_routers_policies():
    policy = acl_policy(hosts=["base"])
    twin = uplink_policy(policy)
    assert policy == acl_policy(hosts=["base"])  # the input is left alone
    assert {"id": "routers-tls-uplink", "cert_common_names": ["base"]} in twin["subjects"]
    routers = next(p for p in twin["policies"] if p["id"] == "routers")
    assert routers["subjects"] == ["routers-tcp", "routers-tls", "routers-tls-uplink"]
    assert uplink_policy(acl_policy()) == acl_policy()  # no host names, nothing to trust
