"""`python -m smana.deploy.report RUN_DIR`: re-write the report of a finished run (metrics.json,
report.md, plots/) and print report.md."""

from __future__ import annotations

import sys
from pathlib import Path

from smana.deploy.report import ground_truth as ev
from smana.deploy.report.write import write_report


def cli(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="smana report", description="(Re)write a run's report.")
    p.add_argument("run_dir", type=Path)
    args = p.parse_args(argv)
    config = ev.load_run_config(args.run_dir)
    path = write_report(args.run_dir, config)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(cli())
