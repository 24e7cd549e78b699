"""Zenoh sessions: the shared command-line flags and the one function that turns them into a
`zenoh.Config` (after zenoh-python's `examples/common/common.py`).

The embedded default is loopback only: every process is a client of the supervisor's router on
tcp/127.0.0.1:7447, with multicast scouting and gossip off, so nothing leaves the machine and two
stacks on one machine never meet unless told to (give them different ports or robot names).

Every session is opened by `open_session`, which turns zenoh's errors (multi-line Rust messages
with source locations) into one `SessionError` line naming the problem and its fix: an endpoint
already in use, a router nobody runs, an address this machine does not have. Endpoints and zenoh
config files are checked before zenoh sees them (`ConfigError`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
from pathlib import Path

from smana.common.config import ConfigError, ZenohConfig


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """The zenoh flags every smana command shares. They override the [zenoh] config section."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh session mode")
    g.add_argument(
        "--connect",
        "-e",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        "-l",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to listen on (repeatable)",
    )
    g.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="zenoh JSON5 config file (TLS, access control, ...); the flags above override it",
    )
    g.add_argument(
        "--no-multicast-scouting",
        dest="multicast_scouting",
        action="store_false",
        default=None,
        help="disable multicast scouting (the default)",
    )
    g.add_argument(
        "--multicast-scouting",
        dest="multicast_scouting",
        action="store_true",
        help="enable multicast scouting (find peers on the LAN)",
    )


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


class SessionError(ValueError):
    """A zenoh session that could not be opened for a reason the user can fix (a port in use, no
    router to connect to, ...). The message is one line: the problem, then what to do."""


# How to choose another listen endpoint, with {} standing for a suggested one.
LISTEN_HINT = "--listen {}"

# zenoh's protocols (zenoh-link); an IP one's address is <host>:<port>
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_PROTOCOLS = (*_IP_PROTOCOLS, "unixsock-stream", "unixpipe", "serial", "vsock")
_ENDPOINT = re.compile(r"(?P<proto>[A-Za-z0-9-]+)/(?P<addr>[^?#]+)(?P<rest>[?#].*)?")
_EXAMPLE = "e.g. tcp/127.0.0.1:7447"
_RUST_SOURCE = re.compile(r"\s*\bat /\S*?\.rs:\d+\.?")  # "... at /root/.cargo/.../tcp.rs:61."


def check_endpoint(endpoint: str) -> None:
    """ConfigError unless `endpoint` reads as <protocol>/<address>, with <host>:<port> for the IP
    protocols. zenoh would refuse most of these too, but only when the session opens, and a
    connect endpoint without a port would read as "nobody answers" there."""
    m = _ENDPOINT.fullmatch(endpoint)
    if not m:
        raise ConfigError(
            f"{endpoint!r} is not a zenoh endpoint: expected <protocol>/<address>, {_EXAMPLE}"
        )
    proto = m["proto"]
    if proto not in _PROTOCOLS:
        raise ConfigError(
            f"endpoint {endpoint!r}: unknown protocol {proto!r} (zenoh speaks "
            f"{', '.join(_PROTOCOLS)}), {_EXAMPLE}"
        )
    if proto in _IP_PROTOCOLS:
        host, sep, port = m["addr"].rpartition(":")
        if not (sep and host and port.isdigit() and int(port) <= 65535):
            raise ConfigError(
                f"endpoint {endpoint!r}: expected {proto}/<host>:<port> with a port "
                f"from 0 to 65535, {_EXAMPLE}"
            )


def free_loopback_port() -> int:
    """A TCP port nobody listens on now, on 127.0.0.1: for a stack of its own (a benchmark, an
    experiment's runs, a test) that must not meet one already running on 7447."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout_s: float = 15.0) -> None:
    """Return once something listens on 127.0.0.1:`port` (a router started for a stack of its
    own); TimeoutError after `timeout_s`."""
    import socket
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def make_zenoh_config(zc: ZenohConfig):
    """Build a `zenoh.Config` from the [zenoh] section (ConfigError for what cannot work)."""
    import zenoh  # imported here so that cores and config code never need zenoh

    for endpoint in [*zc.connect, *zc.listen]:
        check_endpoint(endpoint)
    conf = _read_zenoh_file(Path(zc.config_file)) if zc.config_file else zenoh.Config()
    if zc.config_file and json.loads(conf.get_json("access_control")).get("enabled"):
        # every process reads that file, clients too, and a client given the policy denies its
        # own traffic (the stack never got ready): the policy goes where links arrive
        raise ConfigError(
            f"zenoh config file {zc.config_file} enables access_control: give the policy as "
            "zenoh.acl_file (smana sets it on routers only, where links arrive)"
        )
    conf.insert_json5("mode", json.dumps(zc.mode))
    if zc.connect:
        conf.insert_json5("connect/endpoints", json.dumps(zc.connect))
    if zc.listen:
        conf.insert_json5("listen/endpoints", json.dumps(zc.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(zc.gossip))
    _apply_security(conf, zc)
    return conf


def open_session(source, listen_hint: str = LISTEN_HINT):
    """Open a zenoh session from a [zenoh] section (`ZenohConfig`) or a built `zenoh.Config`, for
    `with open_session(...) as session:`. zenoh's errors become a one-line `SessionError`;
    `listen_hint` says how this command chooses another listen endpoint, for a taken one."""
    import zenoh

    conf = make_zenoh_config(source) if isinstance(source, ZenohConfig) else source
    taken = taken_listen_endpoint(conf)
    if taken is not None:
        # said before zenoh starts: a session that fails to open on a taken port can abort
        # the process from its runtime's threads ("terminate called ...", status -6)
        raise SessionError(
            explain_open_error(f"{_address(taken)} already in use", conf, listen_hint)
        )
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise SessionError(explain_open_error(str(exc), conf, listen_hint)) from exc


def taken_listen_endpoint(conf) -> str | None:
    """The first TCP listen endpoint of `conf` whose port another socket holds on this machine
    (a bind on it fails with "address in use"), None when every one is free. Other errors of a
    bind (no such address, no permission) are left to zenoh, which names them."""
    import errno
    import socket

    for ep in _get(conf, "listen/endpoints") or []:
        if not ep.startswith("tcp/"):
            continue
        host, sep, port = _address(ep).rpartition(":")
        if not (sep and port.isdigit()) or int(port) == 0:
            continue
        host = host.strip("[]")
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            # as a listener binds (zenoh's does): a port a closed socket left in TIME_WAIT is
            # free, one another socket listens on is not
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((host, int(port)))
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    return ep
    return None


def explain_open_error(text: str, conf, listen_hint: str = LISTEN_HINT) -> str:
    """One line for a zenoh.open() error: what went wrong and what to do. The endpoints come from
    `conf` (zenoh names them in its own syntax, or not at all)."""
    listen = _get(conf, "listen/endpoints") or []
    connect = _get(conf, "connect/endpoints") or []
    text = _one_line(_RUST_SOURCE.sub("", text))

    def named(endpoints: list[str]) -> list[str]:  # those the message is about, else all
        return [e for e in endpoints if _address(e) in text] or endpoints

    if listen and ("os error 98" in text or "already in use" in text):
        ep = named(listen)[0]
        return (
            f"{ep} is already in use: another smana stack (or zenohd) is probably running; "
            f"stop it, or choose another port, e.g. {listen_hint.format(_next_port(ep))}"
        )
    if listen and ("os error 99" in text or "Cannot assign requested address" in text):
        return (
            f"cannot listen on {', '.join(named(listen))}: no network interface of this "
            "machine has that address; use 127.0.0.1, 0.0.0.0 or one of its own addresses"
        )
    if listen and ("os error 13" in text or "Permission denied" in text):
        ep = named(listen)[0]
        return (
            f"cannot listen on {ep}: permission denied (ports below 1024 need privileges); "
            f"choose another port, e.g. {listen_hint.format(_next_port(ep, 7448))}"
        )
    if listen and "failed to lookup address" in text:
        return (
            f"cannot listen on {', '.join(listen)}: unknown host name; use an IP address "
            "such as 127.0.0.1 or 0.0.0.0"
        )
    if "Unable to connect to any of" in text:
        secured = _get(conf, "transport/auth/usrpwd/user") or any(
            e.startswith(("tls/", "quic/")) for e in connect
        )
        refused = " (or it refused this host's certificate or credentials)" if secured else ""
        return (
            f"cannot connect to {', '.join(connect)}: nothing answers there{refused}; is the "
            "smana stack running? Start it with `smana up`, or point --connect at its "
            "router"
        )
    if "No peer specified" in text:
        return (
            f"nothing to connect to: give --connect ENDPOINT ({_EXAMPLE}), or "
            "--multicast-scouting to find a router on the LAN"
        )
    return f"cannot open the zenoh session: {text}"


def _get(conf, key: str):
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # a key this zenoh does not have: nothing to say about it
        return None


def _address(endpoint: str) -> str:
    """tcp/127.0.0.1:7447?iface=lo -> 127.0.0.1:7447"""
    return re.split(r"[?#]", endpoint.partition("/")[2])[0]


def _next_port(endpoint: str, default: int | None = None) -> str:
    """The same endpoint on the next port (or on `default`): a suggestion to try."""
    head, sep, port = endpoint.rpartition(":")
    if not (sep and port.isdigit()):
        return endpoint
    n = default if default is not None else (int(port) + 1 if int(port) < 65535 else 7448)
    return f"{head}:{n}"


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _read_zenoh_file(path: Path):
    """A zenoh JSON5 / YAML config file as a `zenoh.Config`; ConfigError with the line, column
    and zenoh's own words when it does not parse or has an unknown key."""
    import zenoh

    if not path.exists():
        raise ConfigError(
            f"zenoh config file not found: {path} (--zenoh-config, zenoh.config_file)"
        )
    if not path.is_file():
        raise ConfigError(f"zenoh config file {path} is not a file")
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(f"zenoh config file {path}: {_explain_parse_error(str(exc))}") from exc


def _explain_parse_error(text: str) -> str:
    """zenoh's config errors come as serde debug output (`Message { msg: "...", location: Some(
    Location { line: 1, column: 19 }) }`) or as a pest report (` --> 1:19 ... = expected ...`)."""
    text = _RUST_SOURCE.sub("", text)
    where = re.search(r"line: (\d+), column: (\d+)", text) or re.search(r"-->\s*(\d+):(\d+)", text)
    what = re.search(r'\b(?:msg|message): "((?:[^"\\]|\\.)*)"', text) or re.search(
        r"^\s*= (.+)$", text, re.MULTILINE
    )
    message = what[1] if what else text
    return _one_line((f"line {where[1]}, column {where[2]}: " if where else "") + message)


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
        ca, cert, key = (
            _require(zc.tls_ca, "tls_ca"),
            _require(zc.tls_cert, "tls_cert"),
            _require(zc.tls_key, "tls_key"),
        )
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
        import zenoh

        path = _require(zc.acl_file, "acl_file")
        try:
            conf.insert_json5("access_control", Path(path).read_text())
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh.acl_file {path}: {_explain_parse_error(str(exc))}") from exc
