"""`smana coordinator`: hands out the fleet's next-best views, no two members to one frontier.

Runs under the fleet's name (`--robot fleet`, `fleet.name`) with `fleet.robots` set; answers
`smana/<fleet>/coordinator/claim/<member>` and publishes `smana/<fleet>/coordinator/claims`.
"""

from __future__ import annotations

import sys

from smana.common.cli import config_from_args, doc_summary, make_parser, run_command, setup_logging


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana coordinator", doc_summary(__doc__))
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "coordinator")
    from smana.services.coordinator.service import main

    return main(cfg)


if __name__ == "__main__":
    sys.exit(run_command("coordinator", cli))
