"""`smana recorder`: record a running smana stack into a Rerun .rrd file (`smana up` starts it)."""

from __future__ import annotations

import sys
from pathlib import Path

from smana.common.cli import run_command
from smana.services.recorder.recorder import RRD_NAME


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import config_from_args, make_parser, setup_logging
    from smana.services.recorder.service import main

    p = make_parser("smana recorder", "Record a running smana stack into a Rerun .rrd file.")
    p.add_argument("--rrd", type=Path, help=f"output file (default RUN_DIR/{RRD_NAME})")
    p.add_argument("--spawn", action="store_true", help="also stream to a newly spawned viewer")
    p.add_argument("--viewer-url", metavar="URL", help="also stream to a running viewer (gRPC)")
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "recorder")
    return main(cfg, args.rrd, args.spawn, args.viewer_url)


if __name__ == "__main__":
    sys.exit(run_command("recorder", cli))
