"""The camera's worker process fed through shared memory (`finishing.ShmWorker`): a result too big
for its slot comes through the pipe, a dead worker is a BrokenProcessPool the service handles,
the segments go away at shutdown, and the sim service runs with it and stops cleanly. (Its bytes
equal the sequential path's: tests/test_sim_sensors.py.)"""

from __future__ import annotations

import os
import signal
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

from smana.common import keys
from smana.common.config.sim import CameraConfig, SimConfig
from smana.services.sim.finishing import FinishedFrame, ShmWorker, _write_result, finished
from smana.services.sim.simulation import Simulation
from smana.services.sim.worlds.garden import GardenConfig
from tests.conftest import wait_for

CFG = SimConfig(
    garden=GardenConfig(size_m=6.0),
    seed=4,
    noise="medium",
    camera=CameraConfig(width=48, height=48, publish_images=True),
)


def test_a_result_too_big_for_its_slot_goes_inline():
    frame = FinishedFrame(3, b"c" * 10, {"rgb": {"seq": 3, "data": b"x" * 10}})
    assert _write_result(bytearray(15), frame) == ("inline", frame)
    buf = bytearray(32)
    answer = _write_result(buf, frame)
    assert answer == ("slot", 3, 10, {"rgb": {"seq": 3, "data": (10, 10)}})
    assert bytes(buf[:20]) == b"c" * 10 + b"x" * 10


def test_worker_in_order_dead_worker_and_cleanup():
    with Simulation(CFG) as a, Simulation(CFG) as b:
        worker = ShmWorker(CFG, b.world.classes.colour_lut, images=True)
        assert worker._proc is None  # nothing runs before the first frame (a standby sim)
        # more frames in flight than slots: submit waits for the oldest, order is kept
        futures = [worker.submit(None, b.capture_camera()) for _ in range(3)]
        names = [s.name for s in worker.ins + worker.outs]
        want = [finished(a.camera_frame(), images=True) for _ in range(3)]
        assert [f.result(timeout=60).cloud for f in futures] == [w.cloud for w in want]
        os.kill(worker._proc.pid, signal.SIGKILL)
        worker._proc.join(10)
        with pytest.raises(BrokenProcessPool):
            worker.submit(None, b.capture_camera()).result(timeout=10)
        worker.shutdown(wait=False, cancel_futures=True)
    for name in names:
        assert not Path("/dev/shm", name.lstrip("/")).exists()


@pytest.mark.multiprocess
def test_sim_service_with_the_worker_process(zenoh_stack):
    stack, r = zenoh_stack, zenoh_stack.robot
    proc = stack.service(
        "sim",
        "--size",
        "6",
        "--camera",
        "48x48",
        "--camera-rate",
        "10",
        "--set",
        "sim.camera.worker=process",
    )
    stack.wait_alive("sim")
    clouds = []
    sub = stack.session.declare_subscriber(keys.cloud(r), lambda s: clouds.append(s))
    try:
        assert wait_for(lambda: len(clouds) >= 3, 60)
    finally:
        sub.undeclare()
    assert stack.stop(proc, signal.SIGINT) == 0
