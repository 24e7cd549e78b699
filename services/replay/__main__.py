"""`smana replay DATASET`: replay a recorded dataset into the stack instead of the simulator.

DATASET is a SemanticKITTI or RELLIS-3D sequence (or their root), a ROS 1 .bag, a ROS 2 bag folder,
an .mcap file, or a folder of labelled PLY/NPZ scans. Scans without labels (KITTI .bin without
.label, clouds without a label field) replay with --label-field none: their points are labelled
ground or obstacle by geometry. With --run, the mapper, navgraph and planner
are started too (no sim), and the run directory gets what `smana up` writes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import sys
import threading
import time
from pathlib import Path

from smana.common.cli import (
    config_from_args,
    make_parser,
    non_negative_int,
    output_dir,
    positive_float,
    run_command,
    setup_logging,
)
from smana.common.config import SmanaConfig
from smana.common.service import on_stop_signals

STACK = ("mapper", "navgraph", "planner")


def cli(argv: list[str] | None = None) -> int:
    from smana.services.replay.readers import READERS

    p = make_parser("smana replay", __doc__.strip().splitlines()[0])
    p.epilog = (
        "Duration measured once on a 2-core machine: --info takes seconds. --run spends about 10 "
        "s starting "
        "the stack, then goes at the mapper's pace in lockstep (30 synthetic 32 x 1024 scans: 5 "
        "s), at the recorded rate times "
        "--rate with --realtime; the report at the end takes a few seconds more. A progress bar "
        "of the scans sent, with an ETA, shows on a terminal (SMANA_PROGRESS=1 forces it, 0 "
        "hides it)."
    )
    p.add_argument("dataset", nargs="?", help="dataset path (or set replay.dataset)")
    p.add_argument("--run", action="store_true", help="also start mapper, navgraph and planner")
    p.add_argument("--info", action="store_true", help="describe the dataset and exit")
    p.add_argument(
        "--format",
        help=f"one of {', '.join(READERS)}, or a reader's package.module:Class (default: detect)",
    )
    p.add_argument("--sequence", help="sequence to replay when DATASET holds several")
    p.add_argument("--table", help="class table (default: the dataset's own)")
    pace = p.add_mutually_exclusive_group()  # (--mode is zenoh's flag)
    pace.add_argument(
        "--lockstep",
        dest="pace",
        action="store_const",
        const="lockstep",
        help="send each scan once the mapper has integrated the last (default)",
    )
    pace.add_argument(
        "--realtime",
        dest="pace",
        action="store_const",
        const="realtime",
        help="send scans at the recorded rate (times --rate)",
    )
    p.add_argument(
        "--rate", type=positive_float, metavar="X", help="realtime mode: x X the recorded rate"
    )
    p.add_argument("--start", type=non_negative_int, metavar="N", help="first scan to replay")
    p.add_argument("--count", type=non_negative_int, metavar="N", help="number of scans to replay")
    p.add_argument(
        "--label-field",
        help="bags and PLY: name of the integer label field; 'none' (any format): read no "
        "labels, label the points ground/obstacle by geometry (class table geometric)",
    )
    p.add_argument("--cloud-topic", help="bags: the sensor_msgs/PointCloud2 topic")
    p.add_argument("--odom-topic", help="bags: the nav_msgs/Odometry topic")
    p.add_argument(
        "--fixed-pose",
        type=float,
        nargs=4,
        metavar=("X", "Y", "Z", "YAW"),
        help="bags without odometry: the sensor's fixed pose",
    )
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    rc = cfg.replay
    given = {
        "dataset": args.dataset,
        "format": args.format,
        "sequence": args.sequence,
        "class_table": args.table,
        "mode": args.pace,
        "rate_factor": args.rate,
        "start": args.start,
        "count": args.count,
        "label_field": args.label_field,
        "cloud_topic": args.cloud_topic,
        "odom_topic": args.odom_topic,
        "fixed_pose": list(args.fixed_pose) if args.fixed_pose else None,
    }
    rc = dataclasses.replace(rc, **{k: v for k, v in given.items() if v is not None})
    if rc.dataset:  # services may run elsewhere (the supervisor's cwd is the run dir)
        rc = dataclasses.replace(rc, dataset=str(Path(rc.dataset).resolve()))
    cfg = dataclasses.replace(cfg, replay=rc)
    setup_logging(cfg.general.log_level, "replay")

    from smana.services.replay.readers import DatasetError
    from smana.services.replay.service import open_reader, table_name

    try:
        reader = open_reader(rc)
    except (DatasetError, ValueError, ImportError) as exc:
        print(f"smana replay: {exc}", file=sys.stderr)
        return 2
    try:
        table_name(rc, reader)  # a table that cannot hold the labels stops here
    except ValueError as exc:
        reader.close()
        print(f"smana replay: {exc}", file=sys.stderr)
        return 2
    if args.info:
        return _info(reader, rc)
    if args.run:
        return run_stack(cfg, reader)
    from smana.services.replay.service import main

    return main(cfg, reader)


def _info(reader, rc) -> int:
    from smana.services.replay.service import table_name, topic_of

    i = reader.info()
    print(f"{i.path}: {i.format}, {i.n_scans} scans at {i.rate_hz:.2f} Hz")
    print(f"class table {table_name(rc, reader)}, published on robot/{topic_of(rc, reader)}")
    reader.report_skipped(sys.stdout, limit=1000)
    reader.close()
    return 0


def run_stack(cfg: SmanaConfig, reader) -> int:
    """Supervise mapper, navgraph and planner (and the recorder) with the replay in place of the
    sim; the run ends when the replay has sent its last scan. The run directory gets what
    `smana up` writes: config, logs, map, recording, report (with a replay section). What went
    wrong (a service never ready, a scan lost in lockstep, a recorder that missed poses) heads
    the report, ends the output and makes the exit status 1."""
    from smana.common.config import ServiceDeployConfig
    from smana.deploy.supervisor import Supervisor
    from smana.services.replay.service import table_name, topic_of

    rc = cfg.replay
    table = table_name(rc, reader)
    if Path(table).suffix == ".toml":
        table = str(Path(table).resolve())
    topic = topic_of(rc, reader)
    reader.close()  # the replay process opens it again
    g = cfg.general
    run_dir = Path(g.run_dir) if g.run_dir else Path("runs") / time.strftime("replay-%Y%m%d-%H%M%S")
    output_dir(run_dir)  # a file, or a folder that cannot be made: refused before anything starts
    services = [n for n in STACK if getattr(cfg.deploy, n).enabled]
    recorder = _recorder_argv()
    cfg = dataclasses.replace(
        cfg,
        general=dataclasses.replace(g, class_table=table, run_dir=str(run_dir)),
        mapper=dataclasses.replace(cfg.mapper, inputs=[topic]),
        deploy=dataclasses.replace(cfg.deploy, finish_with="replay"),
        replay=dataclasses.replace(
            rc, class_table=table, wait_for=services + (["recorder"] if recorder else [])
        ),
    )
    sup = Supervisor(cfg, run_dir, services)
    if recorder:
        sup.add("recorder", recorder(sup.config_path, cfg.general.robot))
    argv = [sys.executable, "-m", "smana.services.replay", "--config", str(sup.config_path)]
    sup.add("replay", argv, ServiceDeployConfig(restart="never"))
    on_stop_signals(lambda _sig: sup.stop())
    print(f"smana replay: run directory {run_dir}", flush=True)
    from smana.common import progress

    with _StackProgress(sup, cfg.general.robot), progress.logs_around_bar():
        code = sup.run()
    completed = _replay_completed(run_dir)
    warnings = sup.warnings()
    if code != 0 and completed:
        # The replay finished its work (its summary is written) and was only caught exiting:
        # the supervisor kills a process whose liveliness token went before the process did.
        print("smana replay: the replay completed; its exit was cut short", file=sys.stderr)
        code = 0
        warnings = [w for w in warnings if not w.startswith("replay exited with status")]
    if not (run_dir / "replay.json").is_file():
        warnings.append("the replay did not finish (no replay.json; see logs/replay.log)")
    warnings = _write_report(run_dir, sup.service_config, warnings)
    print(f"smana replay: done, everything is in {run_dir}", flush=True)
    print(f"smana replay: {'FAILED' if warnings or code else 'ok'}", flush=True)
    for w in warnings:
        print(f"  warning: {w}", flush=True)
    return 1 if warnings or code else 0


class _StackProgress:
    """`smana replay --run`'s bar: the supervised replay writes to its log file, so this process
    draws the scans it has sent of the total, read from its status (`progress`: "done/total",
    published every `general.status_period_s`). On a terminal only (common/progress.py); the
    supervisor's 10 s line is then written above the bar."""

    def __init__(self, sup, robot: str):
        from smana.common import progress

        self.sup, self.robot, self.progress = sup, robot, progress
        self.on = progress.enabled()
        self.bar = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._follow, name="replay-progress", daemon=True)

    def __enter__(self):
        if self.on:
            plain = self.sup.print_progress

            def print_progress(elapsed_s: float) -> None:
                buf = io.StringIO()
                with contextlib.redirect_stdout(buf):
                    plain(elapsed_s)
                self.progress.say(buf.getvalue().rstrip("\n"))

            self.sup.print_progress = print_progress
            self._thread.start()
        return self

    def _follow(self) -> None:
        while not self._stop.wait(0.5):
            st = self.sup.statuses.get((self.robot, "replay"))  # one dict read: no lock needed
            if st is None:
                continue
            done, _, total = str(st.details.get("progress", "")).partition("/")
            if not (done.isdigit() and total.isdigit()):
                continue
            if self.bar is None:
                self.bar = self.progress.bar(int(total), "replay", unit="scan")
            self.bar.update(int(done) - self.bar.n)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        if self.bar is not None:
            # the replay's last status may predate its last scans: its summary has the count
            if _replay_completed(Path(self.sup.run_dir)):
                self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()


def _replay_completed(run_dir: Path) -> bool:
    import json

    path = run_dir / "replay.json"
    if not path.is_file():
        return False
    s = json.loads(path.read_text())
    handled = s["published"] + s["empty"] + len(s["read_errors"])
    return handled == s["scans"] and not (s["mode"] == "lockstep" and s["lost"])


def _recorder_argv():
    try:
        from smana.deploy.recording import recorder_argv
    except ImportError:  # a build without the recorder (rerun-sdk missing)
        return None
    return recorder_argv


def _write_report(run_dir: Path, cfg: SmanaConfig, warnings: list[str]) -> list[str]:
    """`smana up`'s report (map export, files, metrics, plots), in its replay form: the dataset,
    the replay's figures and the map's content instead of measures against a simulated world.
    Returns every warning: `warnings` and what the report found in the figures."""
    import json

    summary_path = run_dir / "replay.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
    if summary is None:
        print(
            f"smana replay: no {summary_path} (the replay did not finish); the report has no "
            "replay section",
            file=sys.stderr,
        )
    try:
        from smana.lab import report

        path = report.write_report(run_dir, cfg, replay=summary or {}, warnings=warnings)
        metrics = json.loads((run_dir / "metrics.json").read_text())
    except Exception as exc:  # noqa: BLE001 - the run's own outcome matters more
        print(f"smana replay: the run report failed: {exc}", file=sys.stderr)
        return [*warnings, f"the report could not be written: {exc}"]
    print(f"smana replay: report written to {path}", flush=True)
    return metrics.get("warnings", warnings)


if __name__ == "__main__":
    sys.exit(run_command("replay", cli))
