"""The `smana` command: one entry point, one subcommand per service and tool.

Subcommands are imported lazily, so `smana --help` is instant and a tool's optional dependencies
are only needed when that tool runs. Each target is `module:function` taking the remaining argv.

Exit status: 0 done, 1 the command ran and failed, 2 misuse. Misuse (a bad argument or config, a
port in use, nothing to connect to) is one line on stderr, `smana <command>: <message>`; see
`common/cli.py::run_command`.
"""

from __future__ import annotations

import importlib
import sys

# name -> (module:function, one-line help). Order is the order of `smana --help`.
COMMANDS: dict[str, tuple[str, str]] = {
    "up": ("smana.deploy.supervisor:cli", "start the whole stack (the closed-loop demo)"),
    "status": ("smana.deploy.status:cli", "list live services and their status over zenoh"),
    "sim": ("smana.services.sim.__main__:cli", "run the PyBullet simulator service"),
    "mapper": ("smana.services.mapper.__main__:cli", "run the semantic mapper service"),
    "navgraph": ("smana.services.navgraph.__main__:cli", "run the navigation graph service"),
    "planner": ("smana.services.planner.__main__:cli", "run the weighted A* planner service"),
    "explorer": ("smana.services.explorer.__main__:cli", "run the frontier explorer service"),
    "replay": ("smana.services.replay.__main__:cli", "replay a dataset into the stack"),
    "ros2": ("smana.services.ros2.__main__:cli", "smana as a ROS 2 node over rmw_zenoh"),
    "coordinator": (
        "smana.services.coordinator.__main__:cli",
        "run a fleet's coordinator (next-best views, no two robots to one frontier)",
    ),
    "plan": ("smana.services.planner.plan_cli:cli", "ask the planner for a path and print it"),
    "world": ("smana.services.sim.world_cli:cli", "export or preview a simulated world"),
    "warmup": ("smana.deploy.warmup:cli", "compile every service's numba kernels ahead, once"),
    "bench": ("smana.deploy.cli:bench", "benchmarks of each service (smana bench --help)"),
    "eval": ("smana.lab.evaluation:cli", "evaluate a run's map against ground truth"),
    "experiment": ("smana.lab.experiments:cli", "the paper's experiments: noise, exploration"),
    "view": ("smana.deploy.view:cli", "open a run's Rerun recording"),
    "router": ("smana.deploy.router:cli", "run a standalone zenoh router (Python, no zenohd)"),
    "deploy": ("smana.deploy.security:cli", "multi-host set-up: init-certs (TLS, users, ACL)"),
}

BENCHES = {
    "mapper": "smana.lab.bench.mapper:cli",
    "navgraph": "smana.lab.bench.navgraph:cli",
    "planner": "smana.lab.bench.planner:cli",
    "sim": "smana.lab.bench.sim:cli",
    "explorer": "smana.lab.bench.explorer:cli",
    "replay": "smana.lab.bench.replay:cli",
    "pipeline": "smana.lab.bench.pipeline:cli",
    "restart": "smana.lab.bench.restart:cli",
    "startup": "smana.lab.bench.startup:cli",
    "fuzz": "smana.lab.bench.fuzz:cli",
}


def _usage() -> str:
    width = max(len(n) for n in COMMANDS)
    lines = [
        "usage: smana <command> [options]",
        "",
        "smana: semantic mapping and navigation for ground robots, over Eclipse Zenoh.",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "Run `smana <command> --help` for the options of one command."]
    return "\n".join(lines)


def _call(name: str, target: str, argv: list[str]) -> int:
    from smana.common.cli import run_command

    module, func = target.split(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("smana"):
            print(f"smana: {module} is not available in this build ({exc})", file=sys.stderr)
            return 2
        raise
    return run_command(name, getattr(mod, func), argv)


def bench(argv: list[str]) -> int:
    """`smana bench <name> ...`"""
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in BENCHES:
        print("usage: smana bench {" + ",".join(BENCHES) + "} [options]", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return _call(f"bench {argv[0]}", BENCHES[argv[0]], argv[1:])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] == "--version":
        from smana.common.version import smana_version

        print(smana_version())
        return 0
    name = argv[0]
    if name not in COMMANDS:
        print(f"smana: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    return _call(name, COMMANDS[name][0], argv[1:])


if __name__ == "__main__":
    sys.exit(main())
