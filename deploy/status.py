"""`smana status`: which services are up (liveliness tokens: `starting` while they load or
compile, `alive` when ready) and what they report: their state, what they are doing while
starting, and their books (messages in and out, accepted, dropped by reason, rejected by kind)."""

from __future__ import annotations

import json
import sys

from smana.common import keys
from smana.common.cli import config_from_args, make_parser, positive_float
from smana.common.messages import ServiceStatus, to_json
from smana.common.query import QueryError, request
from smana.common.zenoh_config import open_session


def live_services(
    session, robot: str = "*", timeout_s: float = 2.0, kind: str = "alive"
) -> list[tuple[str, str]]:
    """(robot, service) for every liveliness token under smana/<robot>/<kind>/* (kind: alive,
    or starting)."""
    found = set()
    pattern = keys.alive_any(robot) if kind == "alive" else keys.starting_any(robot)
    for reply in session.liveliness().get(pattern, timeout=timeout_s):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) == 4:
                found.add((parts[1], parts[3]))
    return sorted(found)


def collect(session, robot: str = "*", timeout_s: float = 2.0) -> list[dict]:
    rows = []
    alive = live_services(session, robot, timeout_s)
    starting = [x for x in live_services(session, robot, timeout_s, "starting") if x not in alive]
    for r, service in sorted(alive + starting):
        row = {"robot": r, "service": service, "alive": (r, service) in alive}
        try:
            st = request(session, keys.status(r, service), timeout_s=timeout_s)
            if isinstance(st, ServiceStatus):
                row["status"] = json.loads(to_json(st))
        except QueryError as exc:
            row["error"] = str(exc)
        rows.append(row)
    return rows


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana status", __doc__)
    p.add_argument("--all-robots", action="store_true", help="every robot, not only --robot")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=2.0,
        metavar="S",
        help="how long to wait for answers (default 2)",
    )
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    robot = "*" if args.all_robots else cfg.general.robot
    with open_session(cfg.zenoh) as session:
        rows = collect(session, robot, args.timeout)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0 if rows else 1
    if not rows:
        print(f"no live smana services for robot {robot!r}: is it running?", file=sys.stderr)
        return 1
    print(
        f"{'robot':<8} {'service':<10} {'state':<9} {'uptime':>8} {'in':>8} {'out':>8} "
        f"{'dropped':>8}  rejected / doing"
    )
    for row in rows:
        st = row.get("status")
        if st is None:
            state = "running" if row["alive"] else "starting"
            print(f"{row['robot']:<8} {row['service']:<10} {state:<9}  {row.get('error', '')}")
            continue
        if st["state"] == "starting":
            what = (st.get("details") or {}).get("startup_step", "")
        else:
            what = ", ".join(f"{k}={v}" for k, v in sorted(st["rejected"].items())) or "-"
        print(
            f"{row['robot']:<8} {row['service']:<10} {st['state']:<9} {st['uptime_s']:>7.0f}s "
            f"{st['msgs_in']:>8} {st['msgs_out']:>8} {sum(st['dropped'].values()):>8}  {what}"
        )
    return 0
