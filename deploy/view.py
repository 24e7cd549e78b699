"""`smana view`: look at a run in the Rerun viewer.

    smana view RUN_DIR               # open RUN_DIR/recording.rrd in the native viewer
    smana view RUN_DIR --web         # serve it to a browser instead (headless machines)
    smana view --spawn               # watch a running stack live in a new viewer
    smana view --connect URL         # ... or stream to a viewer already running at URL

Live modes run the same recorder as `smana up` (deploy/recording.py), with the usual zenoh flags
to reach the stack. Without a display or a viewer binary, a one-line hint says what to do.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from smana.deploy.recording import RRD_NAME


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


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import config_from_args, make_parser, output_dir, setup_logging

    p = make_parser("smana view", __doc__.strip().splitlines()[0])
    p.add_argument("run_dir", nargs="?", type=Path, help="a run directory or an .rrd file")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead")
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
        from smana.deploy.recording import main as record

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
    cmd = [*viewer, *(["--web-viewer"] if args.web else []), str(rrd)]
    if args.print_only:
        print(" ".join(cmd))
        return 0
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
