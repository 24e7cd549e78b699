"""Finishing camera frames beside the simulation loop: on a worker thread or in a worker process.

Rendering holds PyBullet, and PyBullet holds the GIL while it renders, so a worker *thread* (the
default, `camera.worker = "thread"`) only overlaps the part of finishing that releases the GIL
(OpenCV's SLIC) and contends for the rest. A worker *process* (`"process"`) degrades the labels,
builds the cloud and encodes the messages on another core and hands back bytes ready to put, but
the ~4 MB rendered frame and ~10 MB of messages cross a pipe through the pool's feeder threads,
which want the GIL too: on this 2-core machine it measured slower than the thread (4.2 vs 4.7 Hz
at 640 x 640, `smana bench sim`), and both slower than finishing in line (`"off"`, 5.8 Hz), which
however stalls poses for a frame's finishing. More cores, or a lighter frame, may turn that round.

One worker, one frame in flight: frames are finished in the order they were captured, as the
label and confidence random streams require (the process builds its own `FrameFinisher` from the
same config and seed, so its draws are the ones the loop's finisher would have made).
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from smana.common.config import SimConfig
from smana.common.messages import encode
from smana.common.service import die_with_parent

from .simulation import CameraFrame, FrameFinisher, PendingFrame


@dataclass
class FinishedFrame:
    """A camera frame ready to publish: its cloud encoded, its images (if asked for) as payloads."""

    seq: int
    cloud: bytes
    images: dict[str, dict] = field(default_factory=dict)


def image_payloads(frame: CameraFrame) -> dict[str, dict]:
    """`robot/image/{rgb,depth,semantic}` payloads of a frame (msgpack maps)."""
    h, w = frame.semantic.shape
    common = {"stamp_s": frame.stamp_s, "seq": frame.seq, "width": w, "height": h}
    depth = np.where(np.isfinite(frame.depth_m), frame.depth_m, 0.0).astype("<f4")
    semantic = np.clip(frame.semantic, 0, None).astype("<u2")  # 0 (unknown): no point
    return {
        kind: {**common, "encoding": enc, "data": data.tobytes()}
        for kind, enc, data in (
            ("rgb", "rgb8", np.ascontiguousarray(frame.rgb)),
            ("depth", "32FC1", depth),
            ("semantic", "16UC1", semantic),
        )
    }


def finished(frame: CameraFrame, images: bool) -> FinishedFrame:
    return FinishedFrame(
        frame.seq, encode(frame.to_cloud()), image_payloads(frame) if images else {}
    )


# -- the worker process ---------------------------------------------------------------------------

_finisher: FrameFinisher | None = None
_images = False


def _process_init(config: SimConfig, colour_lut: np.ndarray, images: bool) -> None:
    global _finisher, _images
    die_with_parent()
    # the service's process group gets the stop signal; the service then shuts us down in order
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _finisher = FrameFinisher(config, colour_lut)
    _images = images


def _process_finish(pending: PendingFrame) -> FinishedFrame:
    return finished(_finisher.finish(pending), _images)


def make_worker(
    kind: str, config: SimConfig, finisher: FrameFinisher, colour_lut: np.ndarray
) -> tuple[Executor, Callable[[PendingFrame], FinishedFrame]] | None:
    """An executor and the function to submit to it, for `kind` "process" or "thread"; None for
    "off" (finish in line)."""
    images = config.camera.publish_images
    if kind == "process":
        pool = ProcessPoolExecutor(
            1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_process_init,
            initargs=(config, colour_lut, images),
        )
        return pool, _process_finish
    if kind == "thread":
        return ThreadPoolExecutor(1, "sim-camera"), lambda p: finished(finisher.finish(p), images)
    if kind == "off":
        return None
    raise ValueError(f"camera worker {kind!r}: expected process, thread or off")
