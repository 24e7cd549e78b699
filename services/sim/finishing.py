"""Finishing camera frames beside the simulation loop: on a worker thread or in a worker process.

Rendering holds PyBullet, and PyBullet holds the GIL while it renders, so a worker *thread*
(`camera.worker = "thread"`) only overlaps the part of finishing that releases the GIL (OpenCV's
SLIC) and contends for the rest. A worker *process* (`"process"`) degrades the labels, builds the
cloud and encodes the messages on another core. Its frames come and go through shared memory
(`ShmWorker`: a ring of frame slots and result slots, only a slot index and two poses on a
pipe): an earlier process pool pickled the ~4 MB rendered frame and ~10 MB of messages through
a pipe and its feeder threads, which wanted the GIL the renderer holds, and measured slower than
the thread (4.2 vs 4.7 Hz at 640 x 640, `smana bench sim`, 2 cores). `"off"` finishes in line,
which stalls poses for a frame's finishing.

One worker, frames finished in the order they were captured, as the label and confidence random
streams require (the process builds its own `FrameFinisher` from the same config and seed, so
its draws are the ones the loop's finisher would have made: the bytes are the same, tested).
"""

from __future__ import annotations

import collections
import multiprocessing
import signal
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

import numpy as np

from smana.common.config import SimConfig
from smana.common.messages import encode
from smana.common.service import die_with_parent

from .camera import CameraCapture
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


# -- the worker process, fed through shared memory -------------------------------------------------

# Bytes per pixel of a frame slot (rgb u1 x 3, depth f4, labels i4) and of a result slot (the
# encoded cloud: points f4 x 3, labels u2, confidences f4; the images rgb, depth f4, semantic u2).
_IN_PX = 3 + 4 + 4
_OUT_PX = 12 + 2 + 4 + 3 + 4 + 2
_OUT_HEAD = 1 << 16  # the cloud message's header and the image maps' fields, with room to spare
SLOTS = 2  # a frame rendering while the one before is finished


def _frame_views(buf, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rgb, depth, labels as arrays over a frame slot."""
    n = h * w
    rgb = np.ndarray((h, w, 3), np.uint8, buf, 0)
    depth = np.ndarray((h, w), np.float32, buf, 3 * n)
    labels = np.ndarray((h, w), np.int32, buf, 7 * n)
    return rgb, depth, labels


def _attach(name: str):
    from multiprocessing import shared_memory

    # A spawned child shares its parent's resource tracker, which keeps one entry per name: the
    # parent's unlink at shutdown settles it (unregistering here too would make that a KeyError).
    return shared_memory.SharedMemory(name=name)


def _shm_main(conn, config: SimConfig, colour_lut, images: bool, names, out_names) -> None:
    """The worker process: finish the frame in a slot, write its messages into the result slot
    of the same index, answer with their lengths (a result too big for its slot goes through
    the pipe instead)."""
    die_with_parent()
    # the service's process group gets the stop signal; the service then shuts us down in order
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    finishers: dict[int, FrameFinisher] = {}  # per fleet member: its own random streams
    h, w = config.camera.height, config.camera.width
    ins = [_attach(n) for n in names]
    outs = [_attach(n) for n in out_names]
    try:
        while True:
            try:
                msg = conn.recv()
            except EOFError:  # the service is gone
                break
            if msg is None:
                break
            slot, stamp_s, seq, world_from_sensor, true_pose, focal_px, member = msg
            if member not in finishers:
                finishers[member] = FrameFinisher(config, colour_lut, member)
            finisher = finishers[member]
            try:
                rgb, depth, labels = _frame_views(ins[slot].buf, h, w)
                cap = CameraCapture(rgb, depth, labels, true_pose, focal_px)
                frame = finished(
                    finisher.finish(PendingFrame(stamp_s, seq, cap, world_from_sensor, member)),
                    images,
                )
                del rgb, depth, labels, cap
                conn.send(_write_result(outs[slot].buf, frame))
            except Exception as exc:  # noqa: BLE001 - the service counts it; the worker goes on
                conn.send(("error", seq, f"{type(exc).__name__}: {exc}"))
    finally:
        for shm in ins + outs:
            shm.close()


def _write_result(buf, frame: FinishedFrame) -> tuple:
    """The frame's messages into a result slot: ("slot", seq, cloud length, image fields with
    (offset, length) in place of their data); ("inline", frame) when they do not fit."""
    need = len(frame.cloud) + sum(len(m["data"]) for m in frame.images.values())
    if need > len(buf):
        return ("inline", frame)
    n = len(frame.cloud)
    buf[:n] = frame.cloud
    fields = {}
    for kind, m in frame.images.items():
        data = m["data"]
        buf[n : n + len(data)] = data
        fields[kind] = {**m, "data": (n, len(data))}
        n += len(data)
    return ("slot", frame.seq, len(frame.cloud), fields)


class _SlotFuture:
    """A frame in the worker. `done()` and `result()` read the worker's answers, in order."""

    def __init__(self, worker: ShmWorker, slot: int):
        self._worker, self.slot = worker, slot
        self._result: FinishedFrame | None = None
        self._error: BaseException | None = None
        self._settled = False

    def _settle(self, answer) -> None:
        self._settled = True
        kind = answer[0]
        if kind == "inline":
            self._result = answer[1]
        elif kind == "broken":
            self._error = BrokenProcessPool("the camera worker process died")
        elif kind == "error":
            self._error = RuntimeError(f"camera worker, frame {answer[1]}: {answer[2]}")
        else:
            _, seq, n, fields = answer
            buf = self._worker.outs[self.slot].buf
            images = {
                k: {**m, "data": bytes(buf[m["data"][0] : sum(m["data"])])}
                for k, m in fields.items()
            }
            self._result = FinishedFrame(seq, bytes(buf[:n]), images)

    def done(self) -> bool:
        try:
            while not self._settled and self._worker.answer_ready():
                self._worker.read_answer()
        except BrokenProcessPool:
            pass  # settled us too: result() raises it
        return self._settled

    def result(self, timeout: float | None = None) -> FinishedFrame:
        while not self._settled:
            try:
                self._worker.read_answer(timeout)
            except BrokenProcessPool:
                break  # settled us too
        if self._error is not None:
            raise self._error
        return self._result


class ShmWorker:
    """A process that finishes frames handed to it through a ring of shared-memory slots.

    Only a slot index, the stamp, seq and two poses cross the pipe; the rendered frame (11 bytes
    a pixel) is copied once into a slot and the messages come back through a result slot, so
    nothing of size is pickled and no feeder thread competes for the GIL. The submitted function
    is ignored (the worker always finishes frames); it is there for the `Executor` protocol."""

    def __init__(self, config: SimConfig, colour_lut: np.ndarray, images: bool):
        self._args = (config, colour_lut, images)
        self._shape = (config.camera.height, config.camera.width)
        self.ins: list = []
        self.outs: list = []
        self._proc = None  # started with the first frame, as a process pool starts its workers
        self._pending: collections.deque[_SlotFuture] = collections.deque()
        self._next_slot = 0
        self._closed = self._broken = False

    def _start(self) -> None:
        from multiprocessing import shared_memory

        ctx = multiprocessing.get_context("spawn")
        h, w = self._shape
        self.ins = [
            shared_memory.SharedMemory(create=True, size=_IN_PX * h * w) for _ in range(SLOTS)
        ]
        self.outs = [
            shared_memory.SharedMemory(create=True, size=_OUT_PX * h * w + _OUT_HEAD)
            for _ in range(SLOTS)
        ]
        self._conn, child = ctx.Pipe()
        names = ([s.name for s in self.ins], [s.name for s in self.outs])
        self._proc = ctx.Process(
            target=_shm_main, args=(child, *self._args, *names), name="sim-camera", daemon=True
        )
        self._proc.start()
        child.close()

    def submit(self, _fn, pending: PendingFrame) -> _SlotFuture:
        if self._broken:
            raise BrokenProcessPool("the camera worker process died")
        if self._closed:
            raise RuntimeError("the camera worker is shut down")
        if self._proc is None:
            self._start()
        while len(self._pending) >= SLOTS:  # every slot in use: wait for the oldest
            self.read_answer()
        slot = self._next_slot
        self._next_slot = (slot + 1) % SLOTS
        cap = pending.capture
        if cap.labels.shape != self._shape:
            raise ValueError(f"frame {cap.labels.shape} does not fit the slots {self._shape}")
        rgb, depth, labels = _frame_views(self.ins[slot].buf, *self._shape)
        rgb[...], depth[...], labels[...] = cap.rgb, cap.depth_m, cap.labels
        del rgb, depth, labels
        future = _SlotFuture(self, slot)
        self._pending.append(future)
        self._send(
            (
                slot,
                pending.stamp_s,
                pending.seq,
                pending.world_from_sensor,
                cap.world_from_sensor,
                cap.focal_px,
                pending.member,
            )
        )
        return future

    def _send(self, msg) -> None:
        try:
            self._conn.send(msg)
        except (BrokenPipeError, OSError):
            raise BrokenProcessPool("the camera worker process died") from None

    def answer_ready(self) -> bool:
        """An answer (or the worker's end) is waiting to be read."""
        return bool(self._pending) and self._conn.poll(0)

    def read_answer(self, timeout: float | None = None) -> None:
        """The oldest frame's answer (blocking); BrokenProcessPool if the worker died."""
        if not self._pending:
            raise RuntimeError("no frame in the camera worker")
        try:
            if timeout is not None and not self._conn.poll(timeout):
                raise TimeoutError("camera worker: no answer in time")
            answer = self._conn.recv()
        except (EOFError, OSError):
            # every frame in the worker is lost with it
            self._broken = True
            for f in self._pending:
                f._settle(("broken",))
            self._pending.clear()
            raise BrokenProcessPool("the camera worker process died") from None
        self._pending.popleft()._settle(answer)

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        if self._closed:
            return
        self._closed = True
        if self._proc is None:
            return  # never started
        if wait and not cancel_futures:
            try:
                while self._pending:
                    self.read_answer()
            except BrokenProcessPool:
                pass
        for f in self._pending:
            f._settle(("error", -1, "cancelled at shutdown"))
        self._pending.clear()
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._proc.join(timeout=5 if wait else 0.5)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=2)
        self._conn.close()
        for shm in self.ins + self.outs:
            shm.close()
            shm.unlink()

    def __enter__(self) -> ShmWorker:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown(wait=True)


def make_worker(
    kind: str, config: SimConfig, finisher: FrameFinisher, colour_lut: np.ndarray
) -> tuple[Executor | ShmWorker, Callable[[PendingFrame], FinishedFrame] | None] | None:
    """An executor and the function to submit to it, for `kind` "process" or "thread"; None for
    "off" (finish in line). `finisher`: a `FrameFinisher`, or anything with its `finish` (a
    simulation's `frame_finisher`, which hands each fleet member's frames to that member's)."""
    images = config.camera.publish_images
    if kind == "process":
        return ShmWorker(config, colour_lut, images), None
    if kind == "thread":
        return ThreadPoolExecutor(1, "sim-camera"), lambda p: finished(finisher.finish(p), images)
    if kind == "off":
        return None
    raise ValueError(f"camera worker {kind!r}: expected process, thread or off")
