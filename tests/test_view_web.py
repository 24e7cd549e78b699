"""`smana view RUN --web`: serves the recording to a browser on loopback (unless told otherwise),
prints the one address to open, and stops on Ctrl-C within a second or two."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import pytest

from smana.deploy import view
from tests.conftest import REPO, free_port
from tests.test_cli_misuse import one_line_misuse, smana

pytestmark = pytest.mark.multiprocess
pytest.importorskip("rerun")


@pytest.fixture
def run_dir(tmp_path):
    """A run directory with a small recording in it."""
    code = (
        "import rerun as rr, sys\n"
        "rec = rr.RecordingStream('smana-test')\n"
        "rec.save(sys.argv[1])\n"
        "rec.log('points', rr.Points3D([[0, 0, 0], [1, 1, 1]]))\n"
        "rec.flush()\n"
    )
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "recording.rrd")], check=True)
    assert (tmp_path / "recording.rrd").stat().st_size > 0
    return tmp_path


def _listen_addresses(port: int) -> set[str]:
    """The local addresses sockets listening on `port` are bound to (from /proc/net/tcp)."""
    found = set()
    for path, width in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        try:
            lines = open(path).read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            addr, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:
                raw = bytes.fromhex(addr)
                if width == 8:
                    found.add(socket.inet_ntop(socket.AF_INET, raw[::-1]))
                else:
                    words = b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4))
                    found.add(socket.inet_ntop(socket.AF_INET6, words))
    return found


def _lines(stream, out: queue.Queue) -> None:
    for line in stream:
        out.put(line)
    out.put(None)


def test_web_serves_on_loopback_prints_the_address_and_stops_on_ctrl_c(run_dir):
    web, grpc = free_port(), free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "smana.deploy", "view", str(run_dir), "--web"]
        + ["--web-port", str(web), "--grpc-port", str(grpc)],
        cwd=REPO,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    out: queue.Queue = queue.Queue()
    threading.Thread(target=_lines, args=(proc.stdout, out), daemon=True).start()
    try:
        first = out.get(timeout=120)  # the viewer binary's cold start on a busy machine
        if first is None:
            err = proc.communicate(timeout=10)[1]
            if "Rerun web viewer" in err:  # this rerun cannot serve the web viewer here
                pytest.skip(err.strip())
            pytest.fail(f"smana view exited {proc.returncode}: {err}")
        url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
        assert first.startswith(f"smana view: open {url} "), first
        assert "Ctrl-C" in first
        # what it printed is true: both servers listen, on loopback only
        assert _listen_addresses(web) == {"127.0.0.1"}, _listen_addresses(web)
        assert _listen_addresses(grpc) == {"127.0.0.1"}, _listen_addresses(grpc)
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as page:
            assert page.status == 200
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the terminal signals smana's group
        proc.wait(timeout=10)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, proc.stderr.read()
    assert took < 2.5, took
    # nothing left behind: the viewer's servers went with it
    assert not _listen_addresses(web) and not _listen_addresses(grpc)
    # one line of ours, none of Rerun's log
    assert out.get(timeout=5) is None


def test_web_on_a_port_in_use_is_one_line(run_dir):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = smana("view", str(run_dir), "--web", "--web-port", str(port))
    one_line_misuse(r, "view", f"127.0.0.1:{port}", "--web-port")


def test_the_address_names_the_host_when_serving_every_interface():
    assert view.web_url("0.0.0.0", 9090, 9876) == (
        f"http://{socket.gethostname()}:9090/?url=rerun%2Bhttp%3A%2F%2F"
        f"{socket.gethostname()}%3A9876%2Fproxy"
    )
    assert view.web_url("::1", 1, 2).startswith("http://[::1]:1/?url=rerun%2Bhttp%3A%2F%2F%5B")


def test_print_only_shows_the_bind_address(run_dir, capsys):
    assert view.cli([str(run_dir), "--web", "--bind", "10.0.0.5", "--print-only"]) == 0
    out = capsys.readouterr().out
    assert "--web-viewer --bind 10.0.0.5" in out and str(run_dir / "recording.rrd") in out
