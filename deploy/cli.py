"""The `smana` command: one entry point, one subcommand per service and tool.

Subcommands are imported lazily, so `smana --help` is instant and a tool's optional dependencies
are only needed when that tool runs. Each target is `module:function` taking the remaining argv.
The services' commands come from the table of services (common/service_table.py); the research
harness's (`bench`, `eval`, `experiment`) and any plug-in's from the entry-point group
`smana.commands` (pyproject.toml), each a `(module:function, one-line help)` pair, so this file
names no module of `lab/`.

Exit status: 0 done, 1 the command ran and failed, 2 misuse. Misuse (a bad argument or config, a
port in use, nothing to connect to) is one line on stderr, `smana <command>: <message>`; see
`common/cli.py::run_command`.
"""

from __future__ import annotations

import functools
import sys

from smana.common import service_table

COMMAND_GROUP = "smana.commands"

_TOOLS = {
    "plan": ("smana.services.planner.plan_cli:cli", "ask the planner for a path and print it"),
    "goto": ("smana.services.explorer.goto_cli:cli", "send the robot to a pose (Ctrl-C cancels)"),
    "world": ("smana.services.sim.world_cli:cli", "export or preview a simulated world"),
    "warmup": ("smana.deploy.warmup:cli", "compile every service's numba kernels ahead, once"),
    "view": ("smana.deploy.view:cli", "open a run's Rerun recording"),
    "router": ("smana.deploy.router:cli", "run a standalone zenoh router (Python, no zenohd)"),
    "deploy": ("smana.deploy.security:cli", "multi-host set-up: init-certs (TLS, users, ACL)"),
}


def _table(rows) -> dict[str, tuple[str, str]]:
    out = {
        "up": ("smana.deploy.supervisor:cli", "start the whole stack (the closed-loop demo)"),
        "status": ("smana.deploy.status:cli", "list live services and their status over zenoh"),
    }
    return out | {r.name: (r.command, r.help) for r in rows if r.command} | _TOOLS


@functools.cache
def commands() -> dict[str, tuple[str, str]]:
    """name -> (module:function, one-line help), in the order of `smana --help`: smana's own,
    then plug-ins' (reading the installed entry points, which costs a few hundred ms on a loaded
    machine: only `--help` and a name smana does not know pay it)."""
    from importlib.metadata import entry_points

    out = _table(service_table.rows())
    for ep in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        if ep.name in out:
            continue  # smana's own command wins over a plug-in's of the same name
        try:
            target, text = ep.load()
        except Exception as exc:  # noqa: BLE001 - a broken plug-in must not stop smana
            target, text = "", f"(a plug-in, {ep.value}, that does not load: {exc})"
        out[ep.name] = (target, text)
    return out


def __getattr__(name: str):
    if name == "COMMANDS":  # every command, plug-ins' included (read when first asked for)
        return commands()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _usage() -> str:
    known = commands()
    width = max(len(n) for n in known)
    lines = [
        "usage: smana <command> [options]",
        "",
        "smana: semantic mapping and navigation for ground robots, over Eclipse Zenoh.",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in known.items()]
    lines += ["", "Run `smana <command> --help` for the options of one command."]
    return "\n".join(lines)


def call(name: str, target: str, argv: list[str]) -> int:
    """Run `target` ("module:function") as `smana <name>` with `argv`."""
    from smana.common.cli import run_command
    from smana.common.registry import RegistryError, load_spec

    try:
        func = load_spec(target, f"smana {name}", kind="command")
    except RegistryError as exc:  # not in this build, or a dependency missing: one line
        print(exc, file=sys.stderr)
        return 2
    return run_command(name, func, argv)


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
    known = _table(service_table.TABLE)  # smana's own: no need to read the installed entry points
    if name not in known:
        known = commands()
    if name not in known:
        print(f"smana: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    target, text = known[name]
    if not target:
        print(f"smana {name}: {text}", file=sys.stderr)
        return 2
    return call(name, target, argv[1:])


if __name__ == "__main__":
    sys.exit(main())
