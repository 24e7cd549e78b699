"""Blocking work off the ros2 service's loop: a few daemon threads and a bounded queue.

The ros2 service forwards a robot's odometry and smana's velocity commands on its main loop; a
zenoh query there (GetPlan to a planner that does not answer, a snapshot from a busy mapper)
would hold every forward for its whole timeout. Such calls run here instead, each with its own
deadline; the loop only hands them over and, later, takes their results. No zenoh here: a job
is any callable, so the queue is tested in-process.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

log = logging.getLogger("smana.ros2")


class Jobs:
    """`threads` daemon threads running submitted jobs in order; at most `max_waiting` wait.
    `submit` never blocks: a full queue is refused (False), and the caller counts it. `close`
    drops what still waits, calling each dropped job's `on_drop` so that it can be counted."""

    def __init__(self, name: str, threads: int = 1, max_waiting: int = 8):
        self._queue: queue.Queue = queue.Queue(maxsize=max_waiting)
        self._closed = threading.Event()
        self._threads = [
            threading.Thread(target=self._work, name=f"{name}-{i}", daemon=True)
            for i in range(threads)
        ]
        for t in self._threads:
            t.start()

    def submit(self, job: Callable[[], None], on_drop: Callable[[], None] | None = None) -> bool:
        if self._closed.is_set():
            return False
        try:
            self._queue.put_nowait((job, on_drop))
        except queue.Full:
            return False
        return True

    def waiting(self) -> int:
        return self._queue.qsize()

    def _work(self) -> None:
        while True:
            job, _ = self._queue.get()
            if job is None or self._closed.is_set():
                return
            try:
                job()
            except Exception:  # noqa: BLE001 - a job's bug: logged, the thread goes on
                log.exception("a background job failed")
            # Let go of the job before waiting for the next: what it holds (a zenoh query,
            # whose asker waits until it is dropped) must not live on until then.
            job = _ = None

    def close(self) -> None:
        """Drop what waits (each `on_drop` called) and end the threads; a job already running
        ends by its own deadline (its threads are daemons: they never hold the process)."""
        self._closed.set()
        while True:
            try:
                job, on_drop = self._queue.get_nowait()
            except queue.Empty:
                break
            if job is not None and on_drop is not None:
                on_drop()
        for _ in self._threads:
            try:
                self._queue.put_nowait((None, None))
            except queue.Full:
                break
