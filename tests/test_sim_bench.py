"""`smana bench sim --quick`: runs and prints every row, the in-service rates included (no timing
asserted: the machine is shared)."""

from __future__ import annotations

import pytest

from smana.lab.bench import sim as bench


@pytest.mark.multiprocess
@pytest.mark.slow
def test_quick_bench_prints_every_row(capsys):
    # the in-service rows for one worker kind: each kind starts the sim service once more
    argv = ["--quick", "--width", "64", "--service-s", "2", "--workers", "process"]
    argv += ["--runs", "1", "--frames", "2", "--scans", "1"]  # the suite's time: the rows only
    assert bench.cli(argv) == 0
    out = capsys.readouterr().out
    for row in (
        "camera, finished on a worker thread, Hz",
        "camera, finished in a worker process, Hz",
        "CPU per frame, process (the loop's side), ms",
        "LiDAR 64 x 2048",
        "in the service (sim as its own process",
        "\nprocess ",
        "target >= 10 Hz in the service: not judged at 64 x 64",
    ):
        assert row in out, row
