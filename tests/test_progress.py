"""Progress bars (common/progress.py): on stderr, only on a terminal unless SMANA_PROGRESS says
otherwise, with an ETA; the command's own lines stay on stdout, and a replay without a terminal
keeps its plain progress line."""

from __future__ import annotations

import io
import logging
import re
import subprocess

import pytest

from smana.common import progress
from smana.lab.data import synthetic as syn
from smana.services.replay.service import Progress

N_SCANS = 6
ETA = re.compile(r"\d+/\d+ \[\d\d:\d\d<\d\d:\d\d")  # tqdm: done/total [elapsed<remaining


class Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize(
    "env,stream,expected",
    [
        (None, io.StringIO(), False),
        (None, Terminal(), True),
        ("1", io.StringIO(), True),
        ("always", io.StringIO(), True),
        ("0", Terminal(), False),
        ("never", Terminal(), False),
    ],
)
def test_enabled_follows_the_terminal_unless_told(monkeypatch, env, stream, expected):
    if env is None:
        monkeypatch.delenv(progress.ENV, raising=False)
    else:
        monkeypatch.setenv(progress.ENV, env)
    assert progress.enabled(stream) is expected


def test_a_bad_setting_is_a_one_line_error(monkeypatch):
    monkeypatch.setenv(progress.ENV, "maybe")
    with pytest.raises(ValueError, match=r"SMANA_PROGRESS='maybe': use 1 .* or 0") as err:
        progress.enabled()
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="total must be >= 0"):
        progress.bar(-1, "x", enable=False)


def test_bar_draws_an_eta_on_stderr_and_lines_stay_on_stdout(monkeypatch, capsys):
    monkeypatch.setenv(progress.ENV, "1")
    with progress.bar(4, "noise: mapping", unit="map") as bar:
        for i in range(4):
            progress.say(f"line {i}")
            bar.update()
    out, err = capsys.readouterr()
    assert out.splitlines() == ["line 0", "line 1", "line 2", "line 3"]
    assert "noise: mapping" in err and "4/4" in err and ETA.search(err) and "map/s" in err


def test_no_bar_without_a_terminal(monkeypatch, capsys):
    monkeypatch.delenv(progress.ENV, raising=False)  # pytest's stderr is captured: no terminal
    with progress.bar(3, "exploration", unit="run") as bar:
        progress.say("seed 3 grass x1: exit 0, 54 s")
        bar.update(3)
    out, err = capsys.readouterr()
    assert out == "seed 3 grass x1: exit 0, 54 s\n" and err == ""


def test_logs_go_above_the_bar(monkeypatch, capsys):
    monkeypatch.setenv(progress.ENV, "1")
    log = logging.getLogger("smana.test_progress")
    handler = logging.StreamHandler()  # stderr, as common/cli.py::setup_logging sets it up
    log.addHandler(handler)
    try:
        with progress.bar(2, "replay", unit="scan") as bar, progress.logs_around_bar():
            bar.update()
            log.warning("no MapDelta for scan seq 1")
            bar.update()
    finally:
        log.removeHandler(handler)
    err = capsys.readouterr().err
    # the log line is whole, on its own line, not glued to a bar's redraw
    assert "\nno MapDelta for scan seq 1\n" in err.replace("\r", "\n")


def test_replay_progress_without_a_terminal_keeps_its_line(monkeypatch):
    monkeypatch.delenv(progress.ENV, raising=False)
    stream = io.StringIO()
    p = Progress(12, stream)
    p.update(5, "lat 3 ms")
    p.update(12, "lat 3 ms", force=True)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("replay: 5/12 scans  41.7%") and lines[0].endswith("lat 3 ms")
    assert lines[-1].startswith("replay: 12/12 scans 100.0%")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    syn.write_rellis_sequence(
        root, syn.SyntheticConfig(n_scans=N_SCANS, beams=16, columns=256, noise_m=0.0)
    )
    return root


@pytest.mark.multiprocess
@pytest.mark.parametrize("setting", ["1", "0"])
def test_replay_shows_scans_sent_of_total(zenoh_stack, dataset, setting):
    stack = zenoh_stack
    argv = ["-m", "smana.services.replay", *stack.zenoh_args(), "--robot", stack.robot]
    proc = stack.start(
        "replay",
        *argv,
        str(dataset),
        "--set",
        "replay.wait_for=[]",  # no mapper: nothing waits for a MapDelta
        "--realtime",
        "--rate",
        "20",
        env={progress.ENV: setting},
    )
    try:
        code = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        stack.stop(proc)
        raise AssertionError("replay did not finish:\n" + stack.log(proc)) from None
    out = stack.log(proc)
    assert code == 0, out
    if setting == "1":
        assert "replay: 100%" in out and ETA.search(out) and f"{N_SCANS}/{N_SCANS}" in out
        assert f"replay: {N_SCANS}/{N_SCANS} scans" not in out
    else:
        assert f"replay: {N_SCANS}/{N_SCANS} scans 100.0%" in out and "%|" not in out
