"""`smana explorer`: next-best-view frontier exploration over the navigation graph.

Drives the robot (robot/cmd_vel) toward the view that sees most unknown ground for the least path
cost, until no view is worth it or `explorer.time_budget_s` is spent; then exits with status 0.

It also drives to the poses it is sent (query explorer/goal, or `smana goto X Y`): exploration
pauses meanwhile and resumes after (`explorer.resume_after_goal`). With
`--set explorer.mode=navigate` it never explores and only drives to the goals it is sent.
"""

from __future__ import annotations

from smana.common.cli import (
    config_from_args,
    doc_summary,
    exit_process,
    make_parser,
    positive_float,
    run_command,
    setup_logging,
)


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana explorer", doc_summary(__doc__))
    p.add_argument("--budget", type=positive_float, metavar="S", help="time budget, seconds")
    args = p.parse_args(argv)
    if args.budget is not None:
        args.overrides.append(f"explorer.time_budget_s={args.budget}")
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "explorer")
    from smana.services.explorer.service import main

    return main(cfg)


if __name__ == "__main__":
    # its state, trajectory and graph are written and closed when the service stops
    exit_process(run_command("explorer", cli))
