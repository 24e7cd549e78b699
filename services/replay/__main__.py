"""`smana replay DATASET`: replay a recorded dataset into the stack instead of the simulator.

DATASET is a SemanticKITTI or RELLIS-3D sequence (or their root), a ROS 1 .bag, a ROS 2 bag folder,
an .mcap file, or a folder of labelled PLY/NPZ scans. Scans without labels (KITTI .bin without
.label, clouds without a label field) replay with --label-field none: their points are labelled
ground or obstacle by geometry. With --run, the mapper, navgraph and planner
are started too (no sim), and the run directory gets what `smana up` writes.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
import time
from pathlib import Path

from smana.common.cli import (
    ServiceCommand,
    doc_summary,
    non_negative_int,
    positive_float,
    run_command,
    setup_logging,
)
from smana.common.config import SmanaConfig

STACK = ("mapper", "navgraph", "planner")
COMMAND = ServiceCommand("replay", doc_summary(__doc__), "smana.services.replay.service:main")


def cli(argv: list[str] | None = None) -> int:
    from smana.services.replay.readers import READERS

    p = COMMAND.parser()
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
    cfg = COMMAND.config(args)
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
    setup_logging(cfg.general.log_level, "replay")  # the reader may warn as it opens

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
    return COMMAND.run(cfg, reader)


def _info(reader, rc) -> int:
    from smana.services.replay.service import table_name, topic_of

    i = reader.info()
    print(f"{i.path}: {i.format}, {i.n_scans} scans at {i.rate_hz:.2f} Hz")
    print(f"class table {table_name(rc, reader)}, published on robot/{topic_of(rc, reader)}")
    reader.report_skipped(sys.stdout, limit=1000)
    reader.close()
    return 0


def run_stack(cfg: SmanaConfig, reader) -> int:
    """`smana up`'s path (deploy/supervisor.py `main`) with the replay in place of the sim:
    mapper, navgraph and planner (and the recorder) are supervised, the run ends when the replay
    has sent its last scan, and the run directory gets what `smana up` writes, its report in its
    replay form (deploy/report/finish.py)."""
    from smana.deploy.supervisor import main
    from smana.services.replay.service import table_name, topic_of

    rc = cfg.replay
    table = table_name(rc, reader)
    if Path(table).suffix == ".toml":
        table = str(Path(table).resolve())
    topic = topic_of(rc, reader)
    reader.close()  # the replay process opens it again
    g = cfg.general
    run_dir = Path(g.run_dir) if g.run_dir else Path("runs") / time.strftime("replay-%Y%m%d-%H%M%S")
    services = [n for n in STACK if getattr(cfg.deploy, n).enabled]
    if importlib.util.find_spec("rerun") is not None:  # a build without rerun-sdk: no recording
        services.append("recorder")
    cfg = dataclasses.replace(
        cfg,
        general=dataclasses.replace(g, class_table=table, run_dir=str(run_dir)),
        mapper=dataclasses.replace(cfg.mapper, inputs=[topic]),
        deploy=dataclasses.replace(cfg.deploy, finish_with="replay"),
        replay=dataclasses.replace(rc, class_table=table, wait_for=services),
    )
    return main(cfg, services=[*services, "replay"], prog="smana replay")


if __name__ == "__main__":
    sys.exit(run_command("replay", cli))
