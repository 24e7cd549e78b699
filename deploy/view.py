"""`smana view`: look at a run in the Rerun viewer.

    smana view RUN_DIR               # open RUN_DIR/recording.rrd in the native viewer
    smana view RUN_DIR --web         # serve it to a browser instead (headless machines):
                                     # prints the address to open; Ctrl-C stops the server
    smana view --spawn               # watch a running stack live in a new viewer
    smana view --connect URL         # ... or stream to a viewer already running at URL

Live modes run the same recorder as `smana up` (services/recorder/), with the usual zenoh flags
to reach the stack. Without a display or a viewer binary, a one-line hint says what to do.

`--web` serves on 127.0.0.1 (Rerun's own default is every interface): `--bind 0.0.0.0` shares it
with the network, or keep loopback and tunnel both ports (`ssh -L 9090:localhost:9090 -L
9876:localhost:9876 HOST`).
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path
from urllib.parse import quote

from smana.services.recorder.recorder import RRD_NAME


def _viewer_cmd() -> list[str] | None:
    exe = shutil.which("rerun")
    if exe:
        return [exe]
    try:
        import rerun  # noqa: F401 - the SDK ships the viewer as `python -m rerun`
    except ImportError:
        return None
    return [sys.executable, "-m", "rerun"]


def find_rrd(run_dir: Path) -> Path:
    if run_dir.is_file() and run_dir.suffix == ".rrd":
        return run_dir
    rrd = run_dir / RRD_NAME
    if rrd.is_file():
        return rrd
    found = sorted(run_dir.glob("*.rrd"))
    if not found:
        raise FileNotFoundError(f"no Rerun recording (.rrd) in {run_dir}")
    return found[0]


WEB_PORT, GRPC_PORT = 9090, 9876  # Rerun's defaults
READY_TIMEOUT_S = 60.0  # a cold start of the viewer binary on a busy 2-core machine
STOP_GRACE_S = 1.0  # SIGINT, SIGTERM, then SIGKILL: Ctrl-C stops the server in a second or two


def web_url(host: str, web_port: int, grpc_port: int) -> str:
    """The address a browser opens: the web viewer, told where the recording's gRPC server is."""
    if host in ("0.0.0.0", "::", ""):  # every interface: name the host, not the wildcard
        host = socket.gethostname()
    elif ":" in host:
        host = f"[{host}]"
    proxy = quote(f"rerun+http://{host}:{grpc_port}/proxy", safe="")
    return f"http://{host}:{web_port}/?url={proxy}"


def _check_port_free(bind: str, port: int, flag: str) -> None:
    from smana.common.cli import UsageError

    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind, port))
        except OSError as exc:
            raise UsageError(
                f"cannot serve on {bind}:{port} ({exc.strerror or exc}); choose another with "
                f"{flag}" + ("" if exc.errno == errno.EADDRINUSE else " or --bind")
            ) from None


def _listening(host: str, port: int) -> bool:
    if host in ("0.0.0.0", ""):
        host = "127.0.0.1"
    elif host == "::":
        host = "::1"
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def web_cmd(viewer: list[str], rrd: Path, bind: str, web_port: int, grpc_port: int) -> list[str]:
    return [
        *viewer,
        "--web-viewer",
        "--bind",
        bind,
        "--web-viewer-port",
        str(web_port),
        "--port",
        str(grpc_port),
        str(rrd),
    ]


def serve_web(viewer: list[str], rrd: Path, bind: str, web_port: int, grpc_port: int) -> int:
    """Serve `rrd` to browsers with Rerun's web viewer, bound to `bind`; print the address once
    both servers listen; stop it on SIGINT/SIGTERM (SIGKILL after `STOP_GRACE_S`)."""
    from smana.common.service import die_with_parent, on_stop_signals

    _check_port_free(bind, web_port, "--web-port")
    _check_port_free(bind, grpc_port, "--grpc-port")
    cmd = web_cmd(viewer, rrd, bind, web_port, grpc_port)
    stop = threading.Event()
    on_stop_signals(lambda _sig: stop.set())
    # Rerun's own log (its address line names `localhost` and the wildcard) is kept for errors;
    # its own session, so a terminal's Ctrl-C reaches smana alone, which stops it
    proc = subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        errors="replace",
        start_new_session=True,
        preexec_fn=die_with_parent,
    )
    tail: deque[str] = deque(maxlen=5)
    drain = threading.Thread(target=lambda: tail.extend(proc.stderr), daemon=True)
    drain.start()
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not (_listening(bind, web_port) and _listening(bind, grpc_port)):
            if proc.poll() is not None or stop.is_set() or time.monotonic() > deadline:
                break
            stop.wait(0.1)
        else:
            print(
                f"smana view: open {web_url(bind, web_port, grpc_port)} (serving {rrd} on "
                f"{bind}; Ctrl-C stops)",
                flush=True,
            )
            while proc.poll() is None and not stop.wait(0.2):
                pass
        if stop.is_set() or proc.poll() is None:
            return 0 if stop.is_set() else _failed(proc, tail, "did not start")
        return _failed(proc, tail, f"exited with status {proc.returncode}")
    finally:
        _stop(proc)


def _failed(proc: subprocess.Popen, tail: deque[str], what: str) -> int:
    _stop(proc)
    last = " ".join(tail[-1].split()) if tail else "no output"
    print(f"smana view: the Rerun web viewer {what}: {last}", file=sys.stderr)
    return 1


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    # SIGTERM too: a viewer started from a background job inherits SIGINT ignored
    grace = STOP_GRACE_S / 2
    for sig, wait_s in ((signal.SIGINT, grace), (signal.SIGTERM, grace), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import (
        config_from_args,
        doc_summary,
        int_in,
        make_parser,
        output_dir,
        setup_logging,
    )

    p = make_parser("smana view", doc_summary(__doc__))
    p.add_argument("run_dir", nargs="?", type=Path, help="a run directory or an .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead")
    p.add_argument(
        "--bind",
        default="127.0.0.1",
        metavar="ADDR",
        help="--web: the address to serve on (default 127.0.0.1; 0.0.0.0 for every interface)",
    )
    p.add_argument(
        "--web-port", type=int_in(1, 65535), default=WEB_PORT, help="--web: HTTP port (9090)"
    )
    p.add_argument(
        "--grpc-port",
        type=int_in(1, 65535),
        default=GRPC_PORT,
        help="--web: port of the recording's gRPC server (9876)",
    )
    p.add_argument("--spawn", action="store_true", help="live: record the stack into a new viewer")
    p.add_argument(
        "--connect-viewer",
        "--viewer",
        dest="viewer_url",
        metavar="URL",
        help="live: stream to a viewer (rerun+http://HOST:9876/proxy)",
    )
    p.add_argument(
        "--print-only", action="store_true", help="print the viewer command, run nothing"
    )
    args = p.parse_args(argv)

    headless = not (
        os.environ.get("DISPLAY")
        or os.environ.get("WAYLAND_DISPLAY")
        or sys.platform in ("darwin", "win32")
    )
    if args.spawn and headless:
        print(
            "smana view: no display to spawn a viewer on; start `rerun` on a machine with one "
            "and stream to it with `smana view --viewer rerun+http://HOST:9876/proxy`",
            file=sys.stderr,
        )
        return 2
    if args.spawn or args.viewer_url:
        cfg = config_from_args(args)
        setup_logging(cfg.general.log_level, "view")
        from smana.services.recorder.service import main as record

        rrd = args.run_dir / RRD_NAME if args.run_dir else None
        if rrd is not None:  # the live recording goes there: a file is refused before it starts
            output_dir(args.run_dir, "run directory", "smana view")
        return record(cfg, rrd, spawn=args.spawn, connect=args.viewer_url)

    if args.run_dir is None:
        p.error("give a run directory, or --spawn / --viewer URL for a live stack")
    try:
        rrd = find_rrd(args.run_dir)
    except FileNotFoundError as exc:
        print(f"smana view: {exc}", file=sys.stderr)
        return 2
    viewer = _viewer_cmd()
    if viewer is None:
        print(
            f"smana view: no Rerun viewer here (pip install rerun-sdk); the recording is {rrd}",
            file=sys.stderr,
        )
        return 2
    cmd = [*viewer, str(rrd)]
    if args.print_only:
        web = web_cmd(viewer, rrd, args.bind, args.web_port, args.grpc_port)
        print(" ".join(web if args.web else cmd))
        return 0
    if args.web:
        return serve_web(viewer, rrd, args.bind, args.web_port, args.grpc_port)
    if headless and not args.web:
        print(
            f"smana view: no display; use `smana view {args.run_dir} --web` or copy {rrd} to a "
            "machine with a viewer (`rerun FILE.rrd`)",
            file=sys.stderr,
        )
        return 2
    return subprocess.call(cmd)


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("view", cli))
