"""`smana bench <name>`: one benchmark per module, each running smana beside the peer a user
would pick instead, on the same input in the same process."""

from __future__ import annotations

import sys

BENCHES = {
    "mapper": "smana.lab.bench.mapper:cli",
    "tsdf": "smana.lab.bench.tsdf:cli",
    "navgraph": "smana.lab.bench.navgraph:cli",
    "planner": "smana.lab.bench.planner:cli",
    "sim": "smana.lab.bench.sim:cli",
    "explorer": "smana.lab.bench.explorer:cli",
    "replay": "smana.lab.bench.replay:cli",
    "pipeline": "smana.lab.bench.pipeline:cli",
    "scale": "smana.lab.bench.scale:cli",
    "restart": "smana.lab.bench.restart:cli",
    "startup": "smana.lab.bench.startup:cli",
    "fuzz": "smana.lab.bench.fuzz:cli",
    "ros2-throughput": "smana.lab.bench.ros2_throughput:cli",
}


def cli(argv: list[str]) -> int:
    """`smana bench <name> ...`"""
    from smana.deploy.cli import call

    if not argv or argv[0] in ("-h", "--help") or argv[0] not in BENCHES:
        print("usage: smana bench {" + ",".join(BENCHES) + "} [options]", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return call(f"bench {argv[0]}", BENCHES[argv[0]], argv[1:])
