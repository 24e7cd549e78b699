"""The research harness: what measures smana rather than runs it.

    evaluation.py    a map and a trajectory against the simulator's ground truth
    report.py        a run's report.md / metrics.json (written by `smana up` and `smana replay`)
    experiments.py   the paper's experiments (`smana experiment noise|exploration`)
    plots.py         every figure smana writes (matplotlib, Agg; refuses one without a legend)
    fuzz.py          the message fuzzer (`smana bench fuzz`, tests/test_fuzz_*.py)
    bench/           `smana bench <name>`: one module per benchmark, each beside its peer
    commands.py      its `smana` commands (bench, eval, experiment), declared to deploy/cli.py
                     through the entry-point group `smana.commands` (pyproject.toml)
    data/            deterministic synthetic scans and datasets for benchmarks and tests

It imports the cores (services/*) and common/; the product never imports it, except `smana up`
and `smana replay`, which write their run's report with `lab.report` when they finish, and
`smana world preview`, which draws with `lab.plots`.
"""
