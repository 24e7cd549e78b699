"""`smana deploy init-certs`: the files that secure a multi-host deployment (zenoh features).

It writes into one folder:

- `ca.pem` / `ca.key`: a local certificate authority (keep `ca.key` off the robots);
- `<host>.pem` / `<host>.key` per host (robot, base, ...): certificates signed by the CA, good for
  both ends of a link, so TLS between routers is mutual (each side checks the other's certificate);
- `credentials.txt`: one `user:password` line per role, random passwords (zenoh's usrpwd
  dictionary format). Each smana service logs in as its own user, so the routers know which
  process sent what;
- `acl.json5`: the access-control policy the routers enforce (see `acl_policy`).

Point the `[zenoh]` section at them (`tls_ca`, `tls_cert`, `tls_key`, `credentials_file`,
`acl_file`); the `robot` and `base` profiles do (see `docs/deployment.md`).
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import os
import secrets
import sys
from pathlib import Path

from smana.common.keys import SERVICES

# Who may do what. Roles are zenoh user names; `router` is the user routers log in as when they
# link up (robot <-> base), `operator` a human with a joystick, `tool` any external zenoh tool.
SENSOR_ROLES = ("sim", "replay", "driver")
COMMAND_ROLES = ("explorer", "operator")
ROLES = (*SERVICES, "driver", "operator", "tool", "router")

READ = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
ALL_MESSAGES = [
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]  # fmt: skip


def acl_policy(robot: str = "*", hosts: list[str] = ()) -> dict:
    """The access-control policy: default deny; everyone may subscribe and query; only the sensor
    roles publish the robot's sensor streams and pose; only the explorer and an operator publish
    velocity commands; each service publishes, serves queries and shows liveliness under its own
    name only; routers relay everything. `tool` (any external zenoh tool) may read, never write.

    Routers are known by their user name `router` where they log in, and by their certificate
    (common name in `hosts`) on the TLS link: user/password only authenticates the side that
    connects, while mutual TLS authenticates both."""
    r = robot
    sensor_keys = [f"smana/{r}/robot/{t}" for t in ("cloud", "scan", "pose", "pose_truth", "clock")]
    sensor_keys.append(f"smana/{r}/robot/image/**")
    rules = [
        {"id": "read", "permission": "allow", "flows": ["ingress"], "messages": READ,
         "key_exprs": ["smana/**"]},
        # What routers send out to their clients: samples, replies, queries to queryables.
        {"id": "deliver", "permission": "allow", "flows": ["egress"], "messages": ALL_MESSAGES,
         "key_exprs": ["smana/**"]},
        {"id": "relay", "permission": "allow", "flows": ["ingress", "egress"],
         "messages": ALL_MESSAGES, "key_exprs": ["smana/**"]},
        {"id": "publish-sensors", "permission": "allow", "flows": ["ingress"],
         "messages": ["put"], "key_exprs": sensor_keys},
        {"id": "publish-cmd_vel", "permission": "allow", "flows": ["ingress"],
         "messages": ["put"], "key_exprs": [f"smana/{r}/robot/cmd_vel"]},
    ]  # fmt: skip
    subjects = [
        {"id": "routers", "usernames": ["router"]},
        *([{"id": "hosts", "cert_common_names": list(hosts)}] if hosts else []),
        {"id": "everyone", "usernames": list(ROLES)},
        {"id": "sensors", "usernames": list(SENSOR_ROLES)},
        {"id": "commanders", "usernames": list(COMMAND_ROLES)},
    ]
    policies = [
        {"rules": ["relay"], "subjects": ["routers", *(["hosts"] if hosts else [])]},
        {"rules": ["read", "deliver"], "subjects": ["everyone"]},
        {"rules": ["publish-sensors"], "subjects": ["sensors"]},
        {"rules": ["publish-cmd_vel"], "subjects": ["commanders"]},
    ]
    # Each service owns its key space: its topics, its status, its queryables, its liveliness.
    owners = {s: [s] for s in SERVICES}
    owners["sim"] = ["sim", "robot"]
    owners["replay"] = ["replay", "robot"]
    owners["driver"] = ["robot"]
    for role, segments in owners.items():
        keys = [f"smana/{r}/{seg}/**" for seg in segments if seg != "robot"]
        keys += [f"smana/{r}/alive/{seg}" for seg in segments]
        rules.append({
            "id": f"own-{role}", "permission": "allow", "flows": ["ingress"],
            "messages": ["put", "delete", "declare_queryable", "reply", "liveliness_token"],
            "key_exprs": keys,
        })  # fmt: skip
        subjects.append({"id": f"user-{role}", "usernames": [role]})
        policies.append({"rules": [f"own-{role}"], "subjects": [f"user-{role}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


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
    path.write_bytes(data)
    os.chmod(path, 0o600)


def _write_cert(cert, path: Path) -> None:
    from cryptography.hazmat.primitives import serialization

    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def init_certs(out: Path, hosts: list[str], days: int = 825, force: bool = False) -> list[Path]:
    """Create the CA, one certificate per host, credentials and the ACL policy in `out`."""
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
        )  # fmt: skip
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
        alt = [x509.DNSName(host), x509.DNSName("localhost"),
               x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]  # fmt: skip
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
    creds = out / "credentials.txt"
    creds.write_text("".join(f"{role}:{secrets.token_urlsafe(18)}\n" for role in ROLES))
    os.chmod(creds, 0o600)
    acl = out / "acl.json5"
    acl.write_text(json.dumps(acl_policy(hosts=hosts), indent=2) + "\n")
    return [*written, creds, acl]


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="smana deploy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
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
    if args.cmd == "acl":
        hosts = [h.strip() for h in args.hosts.split(",") if h.strip()]
        print(json.dumps(acl_policy(args.robot, hosts), indent=2))
        return 0
    hosts = [h.strip() for h in args.hosts.split(",") if h.strip()]
    if not hosts:
        p.error("--hosts needs at least one name")
    try:
        files = init_certs(Path(args.out), hosts, args.days, args.force)
    except FileExistsError as exc:
        print(f"smana deploy init-certs: {exc}", file=sys.stderr)
        return 1
    for f in files:
        print(f)
    print("Copy ca.pem, the host's .pem/.key and credentials.txt to each host; keep ca.key safe.")
    return 0
