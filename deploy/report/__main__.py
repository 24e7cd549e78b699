"""`python -m smana.deploy.report RUN_DIR`: re-write the report of a finished run (metrics.json,
report.md, plots/) and print report.md."""

from __future__ import annotations

import sys
from pathlib import Path

from smana.common.cli import ArgumentParser, run_command


def cli(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="smana report", description="(Re)write a run's report.")
    p.add_argument("run_dir", type=Path)
    args = p.parse_args(argv)
    if not args.run_dir.is_dir():
        print(f"smana report: {args.run_dir} is not a run directory", file=sys.stderr)
        return 2
    from smana.deploy.report.ground_truth import load_run_config
    from smana.deploy.report.write import write_report

    path = write_report(args.run_dir, load_run_config(args.run_dir))
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(run_command("report", cli))
