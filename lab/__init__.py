"""The research harness: what measures smana rather than runs it.

    evaluation.py    `smana eval map` (its measures are deploy/report/ground_truth.py's)
    experiments.py   the paper's experiments (`smana experiment noise|exploration`)
    paper_figures.py the paper's figures, beside the product's (common/plotting.py, re-exported)
    fuzz_messages.py the message fuzzer (`smana bench fuzz`, tests/test_fuzz_*.py)
    bench/           `smana bench <name>`: one module per benchmark, each beside its peer
    commands.py      its `smana` commands (bench, eval, experiment), declared to deploy/cli.py
                     through the entry-point group `smana.commands` (pyproject.toml)
    data/            deterministic synthetic scans and datasets for benchmarks and tests

It imports the product (services/*, common/, deploy/); the product never imports it: a run's
report is the product's (deploy/report/), and so are the figures a run or `smana world preview`
draws (common/plotting.py).
"""
