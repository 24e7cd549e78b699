"""`smana planner`: the semantic-aware weighted A* path planner over zenoh.

Keeps a copy of the navigation graph from navgraph's patches and answers path queries on
`smana/<robot>/planner/path` (PathRequest in msgpack, or JSON from any zenoh tool).
"""

from __future__ import annotations

import sys

from smana.common.cli import config_from_args, doc_summary, make_parser, run_command, setup_logging


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana planner", doc_summary(__doc__))
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "planner")
    from smana.services.planner.service import main

    try:
        return main(cfg)
    except (OSError, ValueError) as exc:
        print(f"smana planner: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(run_command("planner", cli))
