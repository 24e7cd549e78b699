"""`smana navgraph`: the 2.5D semantic navigation graph builder over zenoh.

Integrates the mapper's deltas (highest voxel per node, recomputed when the map clears a voxel,
obstacles and safety zone from the class table), publishes graph patches, and answers graph, node
and stats queries.
"""

from __future__ import annotations

import sys

from smana.common.cli import config_from_args, doc_summary, make_parser, run_command, setup_logging


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana navgraph", doc_summary(__doc__))
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "navgraph")
    from smana.services.navgraph.service import main

    try:
        return main(cfg)
    except (OSError, ValueError) as exc:  # e.g. a class table that cannot be read: no traceback
        print(f"smana navgraph: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(run_command("navgraph", cli))
