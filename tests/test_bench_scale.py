"""`smana bench scale`: the quick run drives through mapper, navgraph and planner and prints every
row (no timing asserted: the machine is shared); the drop model on made-up times; bad options."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from smana.lab.bench import scale


def test_drop_model_is_latest_wins_at_10_hz():
    assert scale.dropped([0.05] * 10) == []
    # scan 0 takes 0.25 s: scan 1 arrives at 0.1 and is replaced by scan 2 at 0.2, which
    # starts at 0.25, before scan 3 arrives: only scan 1 is lost
    assert scale.dropped([0.25, 0.01, 0.01, 0.01]) == [1]
    # a 0.35 s scan: scans 1 and 2 are replaced in turn, scan 3 (arrives 0.3) waits to 0.35
    assert scale.dropped([0.35, 0.01, 0.01, 0.01, 0.01]) == [1, 2]
    # the chain slower than 10 Hz all along (0.15 s, 6.7 Hz): a third of the scans is lost
    assert abs(len(scale.dropped([0.15] * 300)) - 100) <= 2


def test_quick_run_prints_every_row(tmp_path, capsys):
    assert scale.cli(["--quick", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    print(text)
    for row in ("| map |", "| graph |", "| plan |", "| total |", "drops at 10 Hz", "RSS:"):
        assert row in text
    assert "same voxels after load: True" in text
    # --help: "the tables on stdout and in <out>/scale_bench.md, the figures in <out>/...json"
    assert "| map |" in (tmp_path / "scale_bench.md").read_text()
    raw = json.loads((tmp_path / "scale_bench.json").read_text())
    assert raw["scans_done"] == raw["scans"] == 100  # --quick: 15 m at 1.5 m/s and 10 Hz
    assert raw["points_in_scan"] == 4096
    assert raw["plan_ok"] > 0 and not raw["plan_failed"]  # the drive is free: every plan found
    assert raw["rss"] and all(r[2] > 0 for r in raw["rss"])
    assert raw["store"]["regions_written"] > 0  # the quick drive leaves blocks behind on disk
    assert not (tmp_path / "scale_map.npz").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["--km", "0"],
        ["--speed", "fast"],
        ["--backend", "nope"],
        ["--window-m", "5"],
        ["--planner-box-m", "2x20"],
    ],
)
def test_bad_options_exit_2(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        scale.cli([*argv, "--out", str(tmp_path)])
    assert e.value.code == 2
    assert "Traceback" not in capsys.readouterr().err


def test_sigint_ends_the_drive_and_still_saves_loads_and_reports(tmp_path):
    """The run stops at the next scan after SIGINT, then saves, loads and reports what it drove."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "smana.lab.bench.scale", "--km", "1", "--window-m", "0"]
        + ["--rss-every-s", "0.1", "--no-goals", "--out", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "SMANA_PROGRESS": "0"},
    )
    try:
        line = proc.stdout.readline()  # the first RSS line: the drive is under way
        assert "km, scan 0/6667" in line, line + proc.stderr.read()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped by SIGINT after" in out and "Traceback" not in err
    raw = json.loads((tmp_path / "scale_bench.json").read_text())
    assert 1 <= raw["scans_done"] < 6667
    assert raw["load_same"] and raw["save_s"] > 0
