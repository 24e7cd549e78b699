"""Service processes for the benchmarks: each `smana.services.<name>` in its own process group,
a client of the benchmark's router, its output in a log file; stopped with SIGINT, and SIGKILL
past a deadline. One place for what the replay, start-up and fuzz stacks all do."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path


def service_argv(name: str, endpoint: str, robot: str, *args: str) -> list[str]:
    return [
        sys.executable,
        *("-m", f"smana.services.{name}"),
        *("--mode", "client", "--connect", endpoint, "--robot", robot),
        *args,
    ]


def spawn(argv: list[str], log_path: Path, env: dict | None = None, cwd=None) -> subprocess.Popen:
    """Start `argv` in a process group of its own (a signal reaches its children too) that dies
    with this process; stdout and stderr appended to `log_path`."""
    from smana.deploy.supervisor import die_with_parent

    with open(log_path, "ab") as log:  # the child keeps its own descriptor
        return subprocess.Popen(
            argv,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            env=dict(os.environ if env is None else env, PYTHONUNBUFFERED="1"),
            cwd=cwd,
            preexec_fn=die_with_parent,
        )


def signal_group(proc: subprocess.Popen, sig: int) -> None:
    """Signal a process's group, if it still runs."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass


def kill(proc: subprocess.Popen) -> None:
    signal_group(proc, signal.SIGKILL)
    proc.wait()


def stop(procs: Iterable[subprocess.Popen], timeout_s: float) -> list[int | None]:
    """SIGINT to all, then each gets `timeout_s` to exit before SIGKILL. Exit codes, None for a
    process that had to be killed."""
    procs = list(procs)
    for proc in procs:
        signal_group(proc, signal.SIGINT)
    codes: list[int | None] = []
    for proc in procs:
        try:
            codes.append(proc.wait(timeout=timeout_s))
        except subprocess.TimeoutExpired:
            kill(proc)
            codes.append(None)
    return codes
