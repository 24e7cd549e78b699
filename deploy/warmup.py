"""`smana warmup`: compile every service's numba kernels once, in this one process, into the
cache all services load them from.

Every kernel is `cache=True`: numba keeps the machine code next to the source
(`__pycache__/*.nbi, *.nbc`), keyed by the source file's modification time and size, so an edited
kernel file compiles again and nothing else does. Where the package folder is not writable (a
system install) numba falls back to a cache under the user's cache directory
(`~/.cache/numba`), and `NUMBA_CACHE_DIR` chooses another; every process of the same user finds
the same one, so the services share what this command (or whichever service came first) compiled.

Without it nothing is lost: each service compiles what is missing on a thread of its own while
it is already live (`Service.prepare_in_background`, common/service.py). But on a fresh install
every service compiles at once on the same cores, and navgraph, planner and explorer compile the
same grid kernels three times over; run once here, in order, each kernel compiles once. With
`--profile`, the import time of each service and the compile time of each kernel compiled (a
kernel loaded from the cache costs no compile: run on an empty `NUMBA_CACHE_DIR` to see them all).
"""

from __future__ import annotations

import sys
import time

from smana.common import service_table
from smana.common.cli import config_file_from_args, run_command
from smana.common.registry import load_spec

# service -> its Service class, from the table of services (common/service_table.py, `warm_up`):
# `prepare()` compiles its kernels on a throwaway input (no session, no file of the run). The sim
# is not among them: its `prepare()` builds a world, and its one kernel (camera labels) compiles in
# its camera worker on the first frame.
WARMUPS: dict[str, str] = {r.name: r.service_class for r in service_table.rows() if r.warm_up}


class CompileTimes:
    """The seconds numba spends compiling each kernel (exclusive of the kernels it calls, which
    compile inside it), from numba's `numba:compile` events: cache misses only."""

    def __init__(self):
        from numba.core import event

        self._event = event
        self.seconds: dict[str, float] = {}
        self._stack: list[list[float]] = []  # [start, seconds spent in nested compiles]
        outer = self

        class _Listener(event.Listener):
            def on_start(self, ev):
                outer._stack.append([time.perf_counter(), 0.0])

            def on_end(self, ev):
                t0, nested = outer._stack.pop()
                dt = time.perf_counter() - t0
                if outer._stack:
                    outer._stack[-1][1] += dt
                f = ev.data["dispatcher"].py_func
                name = f"{f.__module__.removeprefix('smana.')}.{f.__qualname__}"
                outer.seconds[name] = outer.seconds.get(name, 0.0) + dt - nested

        self._listener = _Listener()

    def __enter__(self):
        self._event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc):
        self._event.unregister("numba:compile", self._listener)


def warm(service: str, config, profile: bool = False) -> dict:
    """Compile (or load) `service`'s kernels here: its import seconds, its prepare seconds and,
    with `profile`, the seconds per kernel compiled."""
    t0 = time.perf_counter()
    cls = load_spec(WARMUPS[service], f"smana warmup {service}", kind="class")
    t1 = time.perf_counter()
    svc = cls(config)
    if profile:
        with CompileTimes() as ct:
            svc.prepare()
        kernels = dict(sorted(ct.seconds.items(), key=lambda kv: -kv[1]))
    else:
        svc.prepare()
        kernels = {}
    return {"import_s": t1 - t0, "prepare_s": time.perf_counter() - t1, "kernels": kernels}


def cli(argv: list[str] | None = None) -> int:
    import argparse

    from smana.common.cli import ArgumentParser, add_config_args, doc_summary

    p = ArgumentParser(
        prog="smana warmup",
        description=doc_summary(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Duration measured once on a 2-core machine: about a minute on an empty cache, 3 "
        "s on a full one.",
    )
    add_config_args(p)
    p.add_argument(
        "--services",
        default=",".join(WARMUPS),
        help=f"comma-separated (default {','.join(WARMUPS)})",
    )
    p.add_argument("--profile", action="store_true", help="compile seconds per kernel")
    args = p.parse_args(argv)
    services = args.services.split(",")
    for s in services:
        if s not in WARMUPS:
            p.error(f"no kernels to warm for {s!r} (one of {', '.join(WARMUPS)})")
    config = config_file_from_args(args)
    import logging

    logging.basicConfig(level=logging.WARNING)  # the services' "kernels ready" lines: not here
    t0 = time.perf_counter()
    for i, s in enumerate(services, 1):
        r = warm(s, config, args.profile)
        print(
            f"[{i}/{len(services)}] {s:<9} kernels ready in {r['prepare_s']:5.1f} s "
            f"(import {r['import_s']:.2f} s)",
            flush=True,
        )
        for name, sec in r["kernels"].items():
            print(f"      {sec:6.2f} s  {name}", flush=True)
    from numba.core.config import CACHE_DIR

    where = CACHE_DIR or "__pycache__ beside each kernel's source (or ~/.cache/numba)"
    print(f"smana warmup: done in {time.perf_counter() - t0:.1f} s; cache: {where}")
    return 0


def main() -> int:
    return run_command("warmup", cli)


if __name__ == "__main__":
    sys.exit(main())
