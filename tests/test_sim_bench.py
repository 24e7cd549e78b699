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
        "bound Hz",
        "target >= 10 Hz in the service: not judged at 64 x 64",
    ):
        assert row in out, row


def test_the_cpu_bound_of_the_service_rate():
    # the loop alone: one core's worth of its CPU per frame
    assert bench.cpu_bound_hz(100.0, 0.0, 2) == pytest.approx(10.0)
    # loop and worker share the cores: the cores' worth of both
    assert bench.cpu_bound_hz(100.0, 150.0, 2) == pytest.approx(2e3 / 250)
    assert bench.cpu_bound_hz(158.0, 102.0, 1) == pytest.approx(1e3 / 260)
    # with a core to spare, the loop's own CPU bounds it
    assert bench.cpu_bound_hz(158.0, 102.0, 2) == pytest.approx(1e3 / 158)
