"""`smana plan --from X,Y --to X,Y`: ask the running planner for a path and print it.

Exit status: 0 with a path, 1 when the planner answered with an error (unreachable, blocked, ...),
2 when nobody answered (no stack to connect to, or no planner in it) or the arguments are wrong.
"""

from __future__ import annotations

import json
import sys
import uuid

import numpy as np

from smana.common import keys
from smana.common.cli import (
    config_from_args,
    doc_summary,
    make_parser,
    non_negative_float,
    point,
    positive_float,
    run_command,
)
from smana.common.messages import PathReply, PathRequest, to_json
from smana.common.query import QueryError, request
from smana.common.zenoh_config import open_session


def format_reply(reply: PathReply, show_path: bool) -> str:
    if not reply.ok:
        lines = [f"no path: {reply.error}: {reply.message}"]
        if len(reply.nearest_free):
            lines.append(
                f"nearest free node: ({reply.nearest_free[0]:.2f}, {reply.nearest_free[1]:.2f})"
            )
        return "\n".join(lines)
    p = reply.path
    shares = ", ".join(f"{k} {v:.0%}" for k, v in sorted(reply.label_share.items()))
    lines = [
        f"path: {len(p)} nodes, {reply.cost_distance:.2f} m, from ({p[0, 0]:.2f}, {p[0, 1]:.2f}) "
        f"to ({p[-1, 0]:.2f}, {p[-1, 1]:.2f})",
        f"cost {reply.cost_total:.3f} = distance {reply.cost_distance:.3f} + height "
        f"{reply.cost_height:.3f} + traversability {reply.cost_traversability:.3f}",
        f"labels: {shares}",
        f"{reply.nodes_expanded} nodes expanded in {reply.time_ms:.1f} ms",
    ]
    if show_path:
        lines += [f"  {x:8.2f} {y:8.2f} {z:7.2f}" for x, y, z in p.tolist()]
    return "\n".join(lines)


def parser():
    """`smana plan`'s arguments (the coordinates accept negative values: `--to -1.9,5.3`)."""
    p = make_parser("smana plan", doc_summary(__doc__))
    p.add_argument(
        "--from", dest="start", type=point, required=True, metavar="X,Y", help="start (m)"
    )
    p.add_argument(
        "--to",
        dest="goal",
        type=point,
        required=True,
        metavar="X,Y",
        help="goal (m), e.g. -1.9,5.3",
    )
    p.add_argument("--h-f", type=non_negative_float, help="height weight (default: [planner] h_f)")
    p.add_argument(
        "--t-f", type=non_negative_float, help="traversability weight (default: [planner] t_f)"
    )
    p.add_argument("--max-step", type=positive_float, metavar="M", help="maximum step height (m)")
    p.add_argument(
        "--cost",
        action="append",
        default=[],
        metavar="CLASS=COST",
        help="override a class cost, e.g. --cost grass=4 (repeatable)",
    )
    p.add_argument("--allow-unknown", action="store_true", help="cross unknown nodes")
    p.add_argument("--unknown-cost", type=non_negative_float, help="cost T of an unknown node")
    p.add_argument("--path", action="store_true", help="print every path point")
    p.add_argument("--json", action="store_true", help="print the reply as JSON")
    p.add_argument(
        "--timeout",
        type=positive_float,
        default=10.0,
        metavar="S",
        help="how long to wait for the planner's answer (default 10)",
    )
    return p


def cli(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    cfg = config_from_args(args)
    start, goal = np.array(args.start), np.array(args.goal)
    from smana.common.classes import ClassTable

    table = ClassTable.load(cfg.general.class_table)
    try:
        class_costs = table.cost_overrides(args.cost)  # refused here, not by the planner
    except ValueError as exc:
        print(f"smana plan: --cost: {exc}", file=sys.stderr)
        return 2
    req = PathRequest(
        request_id=uuid.uuid4().hex[:12],
        start=start,
        goal=goal,
        h_f=args.h_f,
        t_f=args.t_f,
        class_costs=class_costs,
        allow_unknown=args.allow_unknown,
        unknown_cost=cfg.planner.unknown_cost if args.unknown_cost is None else args.unknown_cost,
        max_step_m=args.max_step,
    )
    with open_session(cfg.zenoh) as session:
        try:
            reply = request(session, keys.path_query(cfg.general.robot), req, args.timeout)
        except QueryError as exc:
            print(f"smana plan: {exc}", file=sys.stderr)
            return 2
    if not isinstance(reply, PathReply):
        print(f"smana plan: unexpected reply {reply!r}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(json.loads(to_json(reply)), indent=2))
    else:
        print(format_reply(reply, args.path))
    return 0 if reply.ok else 1


if __name__ == "__main__":
    sys.exit(run_command("plan", cli))
