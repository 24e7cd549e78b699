"""The paper's experiments (sections 4.2 and 4.3), reproduced in smana's simulated garden.

    smana experiment noise [--quick] [--out DIR]
    smana experiment exploration [--quick] [--seeds 3] [--out DIR]
    smana experiment fleet [--quick] [--robots 1,2,3] [--out DIR]
    smana experiment resources [--quick] [--repeats 5] [--out DIR]
    smana experiment navnoise [--quick] [--seeds 5] [--out DIR]   # beyond the paper
    smana experiment risk [--quick] [--seeds 10] [--out DIR]      # issue 29, closed loop
    smana experiment robustness [--quick] [--seeds 10] [--out DIR]  # under perception noise
    smana experiment report [--check]     # docs/experiments.md's tables from the committed data

One module per experiment (`noise.py`, `exploration.py`), each with its `add_parser(sub)` and
`main(args, parser, out)`; this module only dispatches. Every experiment writes raw results (CSV
and JSON), PNG plots and a markdown summary into `--out`; `--quick` runs a small version that the
test suite runs. Each also writes its compact raw rows into `--out`/data/<name>.json
(`report.write_data`), the file docs/experiments/data/ holds once committed. A module whose
`needs_output(args)` is false for a call gets no `--out` (`risk --synthetic --figure PNG` draws
one file).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from .exploration import (
    PAPER_TERRAIN_SHARE,
    ExplorationExperimentConfig,
    exploration_run,
    run_exploration,
)
from .exploration_report import summarise_exploration, write_exploration_outputs
from .noise import (
    BACKENDS,
    LEVELS,
    PAPER_LABEL_LOSS,
    POSE_NOISE,
    NoiseExperimentConfig,
    fixed_trajectory,
    run_noise,
)
from .noise_report import label_losses, write_noise_outputs

__all__ = [
    "BACKENDS",
    "LEVELS",
    "PAPER_LABEL_LOSS",
    "PAPER_TERRAIN_SHARE",
    "POSE_NOISE",
    "ExplorationExperimentConfig",
    "NoiseExperimentConfig",
    "cli",
    "exploration_run",
    "fixed_trajectory",
    "label_losses",
    "run_exploration",
    "run_noise",
    "summarise_exploration",
    "write_exploration_outputs",
    "write_noise_outputs",
]

# subcommand -> module; each module has add_parser(sub) and main(args, parser, out)
EXPERIMENTS = {
    "noise": "noise",
    "exploration": "exploration",
    "ablation": "ablation",
    "routes": "routes",
    "fleet": "fleet",
    "resources": "resources",
    "navnoise": "navnoise",
    "risk": "risk",
    "robustness": "robustness",
    "report": "report",  # not an experiment: the docs' tables from the committed data
}


# flags whose values are paths of this machine: the data file records them as placeholders
PATH_FLAGS = ("--out", "--python")


def recorded(words: list[str]) -> str:
    """A command as a data file records it, quoted for a shell: a path given to --out or
    --python (a folder of this machine) becomes <out> or <python>, left unquoted."""
    import shlex

    out, it = [], iter(words)
    for w in it:
        flag, eq, _ = w.partition("=")
        if flag in PATH_FLAGS and eq:
            out.append(f"{flag}=<{flag[2:]}>")
        elif w in PATH_FLAGS:
            out.append(w)
            if next(it, None) is not None:
                out.append(f"<{w[2:]}>")
        else:
            out.append(shlex.quote(w))
    return " ".join(out)


def cli(argv: list[str] | None = None) -> int:
    import importlib

    from smana.common.cli import ArgumentParser, doc_summary, output_dir

    from .report import COMMAND

    p = ArgumentParser(prog="smana experiment", description=doc_summary(__doc__))
    sub = p.add_subparsers(dest="which", required=True)
    modules = {k: importlib.import_module(f"{__name__}.{m}") for k, m in EXPERIMENTS.items()}
    for mod in modules.values():
        mod.add_parser(sub)
    words = sys.argv[1:] if argv is None else list(argv)
    args = p.parse_args(words)
    mod = modules[args.which]
    parser = sub.choices[args.which]  # errors point at `smana experiment <which> --help`
    if getattr(mod, "NO_OUTPUT", False):  # writes into the repo's docs, no run directory
        return mod.main(args, parser, None)
    if hasattr(mod, "check_args"):
        mod.check_args(args, parser)  # a misuse is refused before the output directory exists
    if not getattr(mod, "needs_output", lambda args: True)(args):  # e.g. risk --figure: a file
        return mod.main(args, parser, None)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = args.out or Path("runs") / f"experiment-{args.which}-{stamp}"
    output_dir(out, "output directory", "--out")
    # the data file records the command that made it (report.write_data)
    token = COMMAND.set(recorded(["smana", "experiment", *words]))
    try:
        return mod.main(args, parser, out)
    finally:
        COMMAND.reset(token)


if __name__ == "__main__":
    from smana.common.cli import run_command

    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(run_command("experiment", cli))
