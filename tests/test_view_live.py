"""`smana view --viewer URL`: a running stack streamed live to a Rerun viewer over gRPC.

No display here, so the "viewer" is Rerun's own headless receiver (`rerun --port P --save F`), which
takes the same gRPC stream a viewer takes and writes what arrived to an .rrd file."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import MapDelta, Pose, encode
from smana.common.service import die_with_parent
from tests.conftest import free_port, wait_for, wait_port

pytestmark = [
    pytest.mark.multiprocess,
    pytest.mark.filterwarnings("ignore:RRD file has no footer"),  # a streamed file has none
]
pytest.importorskip("rerun")


def _entities(path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    out: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        out[str(chunk.entity_path)] = out.get(str(chunk.entity_path), 0) + chunk.num_rows
    return out


def test_live_stream_reaches_a_viewer(zenoh_stack, tmp_path):
    port = free_port()
    received = tmp_path / "received.rrd"
    viewer = subprocess.Popen(
        [sys.executable, "-m", "rerun", "--port", str(port), "--save", str(received)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=die_with_parent,
    )
    try:
        wait_port(port)
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        view = zenoh_stack.start(
            "view",
            "-m",
            "smana.deploy.cli",
            "view",
            "--viewer",
            url,
            *zenoh_stack.zenoh_args(),
            "--robot",
            "test",
        )
        zenoh_stack.wait_alive("recorder")
        r = zenoh_stack.robot
        delta = MapDelta(
            stamp_s=1.0,
            seq=1,
            cloud_seq=1,
            backend="octree-max",
            resolution_m=0.1,
            centres=np.array([[1.05, 1.05, 0.05], [1.15, 1.05, 0.05]], np.float32),
            labels=np.array([1, 4], np.uint16),
            confidences=np.ones(2, np.float32),
            occupied=np.ones(2, np.uint8),
            values=np.ones(2, np.float32),
        )
        zenoh_stack.publisher(keys.map_delta(r)).put(encode(delta))
        poses = zenoh_stack.publisher(keys.pose(r))
        for i in range(20):
            poses.put(encode(Pose.from_xyz_yaw(0.1 * i, 0, 0, 0, stamp_s=0.2 * i)))
            time.sleep(0.05)
        status = zenoh_stack.session.get(keys.status(r, "recorder") + "?format=json", timeout=3)
        assert any(rep.ok for rep in status)
        assert zenoh_stack.stop(view, timeout_s=10) == 0, zenoh_stack.log(view)
        # the receiver flushes as data arrives
        assert wait_for(lambda: received.is_file() and "/world/robot" in _entities(received), 10)
    finally:
        # `python -m rerun` runs the viewer binary as its child: end the whole group
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(timeout=10)
    ents = _entities(received)
    for e in ("/world/robot", "/world/trajectory", "/world/map/b0_0"):
        assert e in ents, (e, sorted(ents))
    assert not (tmp_path / "recording.rrd").exists()  # live only: no file unless asked


def test_view_without_a_display_says_what_to_do(tmp_path, monkeypatch, capsys):
    from smana.deploy import view

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert view.cli([str(tmp_path)]) == 2
    assert "no Rerun recording" in capsys.readouterr().err
    (tmp_path / "recording.rrd").write_bytes(b"")
    if sys.platform.startswith("linux"):
        assert view.cli([str(tmp_path)]) == 2
        assert "--web" in capsys.readouterr().err
        assert view.cli(["--spawn"]) == 2
        assert "--viewer rerun+http://HOST:9876/proxy" in capsys.readouterr().err
    assert view.cli([str(tmp_path), "--web", "--print-only"]) == 0
    out = capsys.readouterr().out
    assert "--web-viewer" in out and str(tmp_path / "recording.rrd") in out
