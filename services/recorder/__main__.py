"""`smana recorder`: record a running smana stack into a Rerun .rrd file (`smana up` starts it)."""

from __future__ import annotations

import sys
from pathlib import Path

from smana.common.cli import ServiceCommand, run_command
from smana.services.recorder.recorder import RRD_NAME

COMMAND = ServiceCommand(
    "recorder",
    "Record a running smana stack into a Rerun .rrd file.",
    "smana.services.recorder.service:main",
)


def cli(argv: list[str] | None = None) -> int:
    p = COMMAND.parser()
    p.add_argument("--rrd", type=Path, help=f"output file (default RUN_DIR/{RRD_NAME})")
    p.add_argument("--spawn", action="store_true", help="also stream to a newly spawned viewer")
    p.add_argument("--viewer-url", metavar="URL", help="also stream to a running viewer (gRPC)")
    args = p.parse_args(argv)
    return COMMAND.run(COMMAND.config(args), args.rrd, args.spawn, args.viewer_url)


if __name__ == "__main__":
    sys.exit(run_command("recorder", cli))
