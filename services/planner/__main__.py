"""`smana planner`: the semantic-aware weighted A* path planner over zenoh.

Keeps a copy of the navigation graph from navgraph's patches and answers path queries on
`smana/<robot>/planner/path` (PathRequest in msgpack, or JSON from any zenoh tool).
"""

from __future__ import annotations

import sys

from smana.common.cli import ServiceCommand, doc_summary, run_command

# a class table or a config that cannot be read: one line, no traceback
COMMAND = ServiceCommand(
    "planner", doc_summary(__doc__), "smana.services.planner.service:main", (OSError, ValueError)
)


def cli(argv: list[str] | None = None) -> int:
    return COMMAND.cli(argv)


if __name__ == "__main__":
    sys.exit(run_command("planner", cli))
