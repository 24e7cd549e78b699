"""Zenoh sessions: the shared command-line flags and the one function that turns them into a
`zenoh.Config` (after zenoh-python's `examples/common/common.py`).

The embedded default is loopback only: every process is a client of the supervisor's router on
tcp/127.0.0.1:7447, with multicast scouting and gossip off, so nothing leaves the machine and two
stacks on one machine never meet unless told to (give them different ports or robot names).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from smana.common.config import ConfigError, ZenohConfig


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """The zenoh flags every smana command shares. They override the [zenoh] config section."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh session mode")
    g.add_argument(
        "--connect", "-e", action="append", metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )  # fmt: skip
    g.add_argument(
        "--listen", "-l", action="append", metavar="ENDPOINT",
        help="endpoint to listen on (repeatable)",
    )  # fmt: skip
    g.add_argument(
        "--zenoh-config", metavar="FILE",
        help="zenoh JSON5 config file (TLS, access control, ...); the flags above override it",
    )  # fmt: skip
    g.add_argument(
        "--no-multicast-scouting", dest="multicast_scouting", action="store_false", default=None,
        help="disable multicast scouting (the default)",
    )  # fmt: skip
    g.add_argument(
        "--multicast-scouting", dest="multicast_scouting", action="store_true",
        help="enable multicast scouting (find peers on the LAN)",
    )  # fmt: skip


def apply_zenoh_args(zc: ZenohConfig, args: argparse.Namespace) -> ZenohConfig:
    """The [zenoh] section with the command-line flags applied on top."""
    changes = {}
    if getattr(args, "mode", None):
        changes["mode"] = args.mode
    if getattr(args, "connect", None):
        changes["connect"] = list(args.connect)
    if getattr(args, "listen", None):
        changes["listen"] = list(args.listen)
    if getattr(args, "zenoh_config", None):
        changes["config_file"] = args.zenoh_config
    if getattr(args, "multicast_scouting", None) is not None:
        changes["multicast_scouting"] = args.multicast_scouting
    return dataclasses.replace(zc, **changes)


def make_zenoh_config(zc: ZenohConfig):
    """Build a `zenoh.Config` from the [zenoh] section."""
    import zenoh  # imported here so that cores and config code never need zenoh

    if zc.config_file:
        path = Path(zc.config_file)
        if not path.is_file():
            raise ConfigError(f"zenoh.config_file not found: {path}")
        conf = zenoh.Config.from_file(str(path))
    else:
        conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(zc.mode))
    if zc.connect:
        conf.insert_json5("connect/endpoints", json.dumps(zc.connect))
    if zc.listen:
        conf.insert_json5("listen/endpoints", json.dumps(zc.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(zc.gossip))
    _apply_security(conf, zc)
    return conf


def _require(path: str, what: str) -> str:
    if not Path(path).is_file():
        raise ConfigError(f"zenoh.{what}: file not found: {path}")
    return str(Path(path).resolve())


def read_credentials(path: str) -> dict[str, str]:
    """`user:password` lines (zenoh's usrpwd dictionary format) as a dict."""
    users = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ConfigError(f"{path}:{n}: expected user:password")
        users[user] = password
    return users


def _apply_security(conf, zc: ZenohConfig) -> None:
    """TLS (mutual when `mtls`), user/password authentication and access control, as zenoh's own
    config keys (transport/link/tls, transport/auth/usrpwd, access_control)."""
    if zc.tls_ca or zc.tls_cert or zc.tls_key:
        if not (zc.tls_ca and zc.tls_cert and zc.tls_key):
            raise ConfigError("zenoh.tls_ca, tls_cert and tls_key go together")
        ca, cert, key = (_require(zc.tls_ca, "tls_ca"), _require(zc.tls_cert, "tls_cert"),
                         _require(zc.tls_key, "tls_key"))  # fmt: skip
        tls = {
            "root_ca_certificate": ca,
            "listen_certificate": cert,
            "listen_private_key": key,
            "connect_certificate": cert,
            "connect_private_key": key,
            "enable_mtls": zc.mtls,
            # Hosts are named by their certificates' common names, not by DNS: robots move
            # between networks and addresses, so the CA signature is what identifies them.
            "verify_name_on_connect": False,
        }
        conf.insert_json5("transport/link/tls", json.dumps(tls))
    usrpwd = {}
    if zc.credentials_file:
        # A router's file is its dictionary (every user it accepts, and its own `router` line); a
        # client's may be one role's file (`credentials/<role>.txt`), whose one line names the user.
        path = _require(zc.credentials_file, "credentials_file")
        users = read_credentials(path)
        user = zc.user
        if zc.mode == "router":
            usrpwd["dictionary_file"] = path
        elif not user and len(users) == 1:
            user = next(iter(users))
        if user:
            if user not in users:
                raise ConfigError(f"zenoh.user {user!r} has no line in {path}")
            usrpwd["user"], usrpwd["password"] = user, users[user]
    elif zc.user:
        raise ConfigError("zenoh.user needs zenoh.credentials_file (where its password is)")
    if usrpwd:
        conf.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))
    # The policy is enforced where links arrive: routers (and peers, which accept links too). A
    # client given the policy would apply default-deny to its own traffic.
    if zc.acl_file and zc.mode != "client":
        conf.insert_json5("access_control", Path(_require(zc.acl_file, "acl_file")).read_text())
