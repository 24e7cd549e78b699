"""The research harness's `smana` commands. The product names no module of `lab/`: these pairs
(`module:function`, one-line help) reach `smana --help` through the entry-point group
`smana.commands` (pyproject.toml), the way a plug-in's commands would."""

BENCH = ("smana.lab.bench:cli", "benchmarks of each service (smana bench --help)")
EVAL = ("smana.lab.evaluation:cli", "evaluate a run's map against ground truth")
EXPERIMENT = ("smana.lab.experiments:cli", "the paper's experiments: noise, exploration")
