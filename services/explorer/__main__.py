"""`smana explorer`: next-best-view frontier exploration over the navigation graph.

Drives the robot (robot/cmd_vel) toward the view that sees most unknown ground for the least path
cost, until no view is worth it or `explorer.time_budget_s` is spent; then exits with status 0.

It also drives to the poses it is sent (query explorer/goal, or `smana goto X Y`): exploration
pauses meanwhile and resumes after (`explorer.resume_after_goal`). With
`--set explorer.mode=navigate` it never explores and only drives to the goals it is sent.
"""

from __future__ import annotations

from smana.common.cli import (
    ServiceCommand,
    doc_summary,
    exit_process,
    positive_float,
    run_command,
)

COMMAND = ServiceCommand("explorer", doc_summary(__doc__), "smana.services.explorer.service:main")


def cli(argv: list[str] | None = None) -> int:
    p = COMMAND.parser()
    p.add_argument("--budget", type=positive_float, metavar="S", help="time budget, seconds")
    args = p.parse_args(argv)
    budget = [] if args.budget is None else [f"explorer.time_budget_s={args.budget}"]
    return COMMAND.run(COMMAND.config(args, budget))


if __name__ == "__main__":
    # its state, trajectory and graph are written and closed when the service stops
    exit_process(run_command("explorer", cli))
