"""`smana navgraph`: the 2.5D semantic navigation graph builder over zenoh.

Integrates the mapper's deltas (highest voxel per node, recomputed when the map clears a voxel,
obstacles and safety zone from the class table), publishes graph patches, and answers graph, node
and stats queries.
"""

from __future__ import annotations

import sys

from smana.common.cli import ServiceCommand, doc_summary, run_command

# a class table or a config that cannot be read: one line, no traceback
COMMAND = ServiceCommand(
    "navgraph", doc_summary(__doc__), "smana.services.navgraph.service:main", (OSError, ValueError)
)


def cli(argv: list[str] | None = None) -> int:
    return COMMAND.cli(argv)


if __name__ == "__main__":
    sys.exit(run_command("navgraph", cli))
