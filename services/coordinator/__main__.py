"""`smana coordinator`: hands out the fleet's next-best views, no two members to one frontier.

Runs under the fleet's name (`--robot fleet`, `fleet.name`) with `fleet.robots` set; answers
`smana/<fleet>/coordinator/claim/<member>` and publishes `smana/<fleet>/coordinator/claims`.
"""

from __future__ import annotations

import sys

from smana.common.cli import ServiceCommand, doc_summary, run_command

COMMAND = ServiceCommand(
    "coordinator", doc_summary(__doc__), "smana.services.coordinator.service:main"
)


def cli(argv: list[str] | None = None) -> int:
    return COMMAND.cli(argv)


if __name__ == "__main__":
    sys.exit(run_command("coordinator", cli))
