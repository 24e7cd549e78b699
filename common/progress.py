"""Progress bars with an ETA for smana's long commands (experiments, replay, benchmarks).

One choice for all of smana: tqdm (one pure-Python package, no dependencies of its own; rich would
bring pygments and markdown-it-py for a bar). Shared by the replay service and the research harness
(`lab/`), so it lives here.

The bar goes to stderr and only when stderr is a terminal, so logs, pipes and tests see nothing
of it; `SMANA_PROGRESS=1` forces it on (e.g. under `script` or a CI that renders `\\r`) and
`SMANA_PROGRESS=0` off. The line-by-line output scripts parse stays on stdout: print it with
`say()`, which lifts the bar out of the way while the line is written.

    with progress.bar(len(configs), "noise sweep", unit="config") as bar:
        for c in configs:
            ...
            progress.say(f"{c}: done")
            bar.update()
"""

from __future__ import annotations

import contextlib
import os
import sys

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

ENV = "SMANA_PROGRESS"
_ON = {"1", "yes", "on", "true", "always"}
_OFF = {"0", "no", "off", "false", "never"}


def enabled(stream=None) -> bool:
    """Whether a bar would be drawn on `stream` (stderr by default): `SMANA_PROGRESS` if set,
    else whether the stream is a terminal."""
    value = os.environ.get(ENV, "").strip().lower()
    if value in _ON:
        return True
    if value in _OFF:
        return False
    if value:
        raise ValueError(f"{ENV}={value!r}: use 1 (always draw progress bars) or 0 (never)")
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


def bar(total: int | None, desc: str, unit: str = "it", *, enable: bool | None = None) -> tqdm:
    """A tqdm bar with an ETA on stderr; a disabled one (every call a no-op) when `enable` is
    False, or when it is None and `enabled()` says no."""
    if total is not None and total < 0:
        raise ValueError(f"progress total must be >= 0, got {total}")
    on = enabled() if enable is None else enable
    try:
        width, height = os.get_terminal_size(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):  # not a terminal (a file, a pipe, a test)
        width = height = None
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        file=sys.stderr,
        disable=not on,
        # follow the terminal's size; a pseudo-terminal that reports 0 x 0 (`script`, some CI
        # runners) gets 80 x 24: tqdm draws nothing in zero columns or rows
        dynamic_ncols=bool(width),
        ncols=80 if width == 0 else None,
        nrows=24 if height == 0 else None,
        leave=True,
        # a 2-core machine: the bar must not cost what it measures
        mininterval=0.5,
    )


def logs_around_bar():
    """A context in which `logging`'s console lines are written above the bars rather than
    through them (a no-op when no bar is drawn)."""
    return logging_redirect_tqdm() if enabled() else contextlib.nullcontext()


def say(line: str, file=None) -> None:
    """Print one line of the command's own output (stdout by default) without tearing a bar."""
    tqdm.write(line, file=sys.stdout if file is None else file)
