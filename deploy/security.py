"""`smana deploy init-certs`: the files that secure a multi-host deployment (zenoh features).

It writes into one folder:

- `ca.pem` / `ca.key`: a local certificate authority (keep `ca.key` off every host);
- `<host>.pem` / `<host>.key` per host (robot, base, ...): certificates signed by the CA, good for
  both ends of a link, so TLS between routers is mutual (each side checks the other's certificate);
- `dictionary.txt`: every role's `user:password` line, random passwords (zenoh's usrpwd dictionary
  format). Only hosts that run a router get it: a router checks every login against it, and logs in
  to other routers with the `router` line;
- `credentials/<role>.txt`: that role's line alone, for a host that only runs clients (an operator's
  laptop, a viewer, a sensor driver on its own computer). `router` has none;
- `acl.json5`: the access-control policy the routers enforce (see `acl_policy`).

Point the `[zenoh]` section at them (`tls_ca`, `tls_cert`, `tls_key`, `credentials_file`,
`acl_file`); the `robot`, `base` and `multi-robot` profiles do (see `docs/deployment.md`, which also
has the policy as a table).
"""

from __future__ import annotations

import argparse
import copy
import datetime
import ipaddress
import json
import os
import secrets
import sys
from pathlib import Path

from smana.common.keys import SERVICES

# Who may do what. Roles are zenoh user names; `router` is the user routers log in as when they
# link up (robot -> base), `operator` a human with a joystick, `tool` any external zenoh tool.
SENSOR_ROLES = ("sim", "replay", "driver")
COMMAND_ROLES = ("explorer", "operator")
SAVE_ROLES = ("operator",)  # may make the mapper write its map to disk (a query, but a write)
OWNERS = (*SERVICES, "driver")  # each owns smana/<r>/<owner>/** and smana/<r>/alive/<owner>
ROLES = (*SERVICES, "driver", "operator", "tool", "router")
READERS = tuple(role for role in ROLES if role != "router")
SENSOR_TOPICS = ("cloud", "scan", "pose", "pose_truth", "clock", "image/**")

READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
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


def acl_policy(robot: str = "*", hosts: list[str] = ()) -> dict:
    """The access-control policy (the table in docs/deployment.md): default deny; every role may
    subscribe and query, except that only an operator may ask the mapper to save; only the sensor
    roles publish the robot's sensor streams and pose; only the explorer and an operator publish
    velocity commands; each service (and a driver) publishes, serves queries and shows liveliness
    under its own name only; `tool` reads and never writes; routers relay everything.

    A subject that lists several attributes matches a session only when all of them match (zenoh
    expands it into every combination of one value per attribute). So a router is user `router`
    presenting a host certificate (`hosts`, common names) on a TLS link, or user `router` on a tcp
    link; a certificate alone grants nothing, since every TLS client must present one. A router
    that opened a TLS link cannot see a user name on it (user/password only authenticates the side
    that connects): `uplink_policy` trusts the far router by its certificate there."""
    r = robot
    sensor_keys = [f"smana/{r}/robot/{t}" for t in SENSOR_TOPICS]
    rules = [
        _rule("read", ["ingress"], READ, ["smana/**"]),
        # What routers send out to their clients: samples, replies, queries to queryables.
        _rule("deliver", ["egress"], ALL_MESSAGES, ["smana/**"]),
        _rule("relay", ["ingress", "egress"], ALL_MESSAGES, ["smana/**"]),
        # Saving writes a file on the mapper's host: a deny beside `read`, on the same subjects,
        # wins over it (for every robot, whatever `robot` is).
        _rule("no-save", ["ingress"], ["query"], ["smana/*/mapper/save"], "deny"),
        _rule("publish-sensors", ["ingress"], ["put"], sensor_keys),
        _rule("publish-cmd_vel", ["ingress"], ["put"], [f"smana/{r}/robot/cmd_vel"]),
    ]
    subjects = [{"id": role, "usernames": [role]} for role in READERS]
    subjects.append({"id": "routers-tcp", "usernames": ["router"], "link_protocols": ["tcp"]})
    if hosts:
        subjects.append(
            {"id": "routers-tls", "usernames": ["router"], "cert_common_names": list(hosts)}
        )
    policies = [
        {"id": "read", "rules": ["read", "deliver"], "subjects": list(READERS)},
        {
            "id": "no-save",
            "rules": ["no-save"],
            "subjects": [role for role in READERS if role not in SAVE_ROLES],
        },
        {"id": "sensors", "rules": ["publish-sensors"], "subjects": list(SENSOR_ROLES)},
        {"id": "commanders", "rules": ["publish-cmd_vel"], "subjects": list(COMMAND_ROLES)},
        {
            "id": "routers",
            "rules": ["relay"],
            "subjects": ["routers-tcp", *(["routers-tls"] if hosts else [])],
        },
    ]
    # Each owner's key space: its topics, status and queryables; its liveliness token alone (the
    # supervisor's health check trusts it). Whatever drives the robot also shows `alive/robot`.
    for owner in OWNERS:
        alive = [f"smana/{r}/alive/{owner}"]
        if owner in SENSOR_ROLES:
            alive.append(f"smana/{r}/alive/robot")
        rules += [
            _rule(f"own-{owner}", ["ingress"], OWN, [f"smana/{r}/{owner}/**"]),
            _rule(f"alive-{owner}", ["ingress"], ["liveliness_token"], alive),
        ]
        policies.append(
            {"id": f"own-{owner}", "rules": [f"own-{owner}", f"alive-{owner}"], "subjects": [owner]}
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


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


def _key():
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _write_key(key, path: Path) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    _write_secret(path, data)


def _write_secret(path: Path, data: bytes | str) -> None:
    """Write a file only its owner can read, from the first byte on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    os.chmod(path, 0o600)  # a file that existed keeps its old mode through O_CREAT


def _write_cert(cert, path: Path) -> None:
    from cryptography.hazmat.primitives import serialization

    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def init_certs(out: Path, hosts: list[str], days: int = 825, force: bool = False) -> list[Path]:
    """Create the CA, one certificate per host, the routers' dictionary, one credentials file per
    role and the ACL policy in `out`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    out.mkdir(parents=True, exist_ok=True)
    if (out / "ca.pem").exists() and not force:
        raise FileExistsError(f"{out}/ca.pem exists (use --force to replace the whole set)")
    now = datetime.datetime.now(datetime.UTC)
    ca_key = _key()
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "smana local CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(hours=1))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_key(ca_key, out / "ca.key")
    _write_cert(ca, out / "ca.pem")
    written = [out / "ca.pem", out / "ca.key"]
    for host in hosts:
        key = _key()
        # The common name identifies the host; the names and loopback address let the
        # certificate also pass a name check where a user turns that on.
        alt = [
            x509.DNSName(host),
            x509.DNSName("localhost"),
            x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
        ]
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, host)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(hours=1))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
            )
            .sign(ca_key, hashes.SHA256())
        )
        _write_key(key, out / f"{host}.key")
        _write_cert(cert, out / f"{host}.pem")
        written += [out / f"{host}.pem", out / f"{host}.key"]
    # Routers must know every password to check logins; a client needs only its own. A file of
    # every password on every host would hand the `router` login (the relay rule) to any tool.
    passwords = {role: secrets.token_urlsafe(18) for role in ROLES}
    dictionary = out / "dictionary.txt"
    _write_secret(dictionary, "".join(f"{u}:{pw}\n" for u, pw in passwords.items()))
    folder = out / "credentials"
    folder.mkdir(exist_ok=True)
    os.chmod(folder, 0o700)
    per_role = []
    for role in READERS:
        per_role.append(folder / f"{role}.txt")
        _write_secret(per_role[-1], f"{role}:{passwords[role]}\n")
    # The single file of every password that earlier versions wrote: its passwords are void now.
    (out / "credentials.txt").unlink(missing_ok=True)
    acl = out / "acl.json5"
    acl.write_text(json.dumps(acl_policy(hosts=hosts), indent=2) + "\n")
    return [*written, dictionary, *per_role, acl]


def _check_names(hosts: list[str], robots: list[str]) -> None:
    """Host names become file names and certificate names, robot names key chunks: the one
    check of both (common/keys.py), a one-line UsageError before anything is written."""
    from smana.common.cli import UsageError
    from smana.common.keys import check_name

    try:
        for h in hosts:
            check_name(h, "--hosts: host name")
        for r in robots:
            check_name(r, "--robot: robot name")
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="smana deploy",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    ic = sub.add_parser("init-certs", help="create a CA, host certificates, credentials and ACL")
    ic.add_argument("--out", default="certs", help="folder to write into (default ./certs)")
    ic.add_argument("--hosts", default="robot,base", help="comma-separated host names")
    ic.add_argument("--days", type=int, default=825, help="validity of the certificates")
    ic.add_argument("--force", action="store_true", help="replace an existing set")
    acl = sub.add_parser("acl", help="print the access-control policy (JSON5)")
    acl.add_argument("--robot", default="*", help="restrict the policy to one robot name")
    acl.add_argument("--hosts", default="robot,base", help="host certificates' common names")
    args = p.parse_args(argv)
    hosts = [h.strip() for h in args.hosts.split(",") if h.strip()]
    _check_names(hosts, [] if args.cmd != "acl" or args.robot == "*" else [args.robot])
    if args.cmd == "acl":
        print(json.dumps(acl_policy(args.robot, hosts), indent=2))
        return 0
    if not hosts:
        p.error("--hosts needs at least one name")
    try:
        files = init_certs(Path(args.out), hosts, args.days, args.force)
    except FileExistsError as exc:
        print(f"smana deploy init-certs: {exc}", file=sys.stderr)
        return 1
    for f in files:
        print(f)
    print(
        "To every host: ca.pem and its own <host>.pem/.key. Where a router runs (smana up, smana "
        "router): also dictionary.txt and acl.json5. Where only clients run: the one "
        "credentials/<role>.txt it logs in as. ca.key goes nowhere."
    )
    return 0
