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

The identities and the policy are `deploy/acl.py`'s; this module writes them into the folders.

Point the `[zenoh]` section at a host's folder (`tls_ca`, `tls_cert`, `tls_key`,
`credentials_file`, `acl_file`); the `robot`, `base`, `multi-robot`, `fleet` and `fleet-robot`
profiles do (see `docs/deployment.md`, which also has the policy as a table).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
from pathlib import Path

from smana.common.cli import ArgumentParser, UsageError
from smana.common.keys import check_robot
from smana.common.zenoh_config import read_credentials
from smana.deploy.acl import (
    acl_policy,
    base_users,
    robot_users,
)
from smana.deploy.certs import issue_host_cert, new_ca, write_cert, write_key, write_secret


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
