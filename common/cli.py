"""Command-line plumbing every smana command shares: `--config`, `--set`, `--robot`, `--run-dir`,
`--log-level` and the zenoh flags, turned into one validated `SmanaConfig`; argument types that
refuse impossible values; and `run_command`, which turns a user's mistake into one line.

Exit status of every command: 0 done, 1 it ran and failed (a planner's "no path", a run whose
explorer failed), 2 misuse (a bad argument or config, a port in use, nothing to connect to): one
line on stderr, `smana <command>: <what is wrong and what to do>`. A bug still shows its traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import math
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path

from smana.common.config import ConfigError, SmanaConfig
from smana.common.zenoh_config import SessionError, add_zenoh_args, apply_zenoh_args


class UsageError(ValueError):
    """A command-line value that cannot work (a run directory that is a file, ...)."""


# What `run_command` reports in one line: mistakes of the user's, not of the code's.
USER_ERRORS = (ConfigError, SessionError, UsageError)


def run_command(name: str, cli: Callable[[list[str] | None], int | None], argv=None) -> int:
    """Run a command's `cli(argv)` and return its exit status. A user error (`USER_ERRORS`) is
    printed as `smana <name>: <message>` on one line and gives status 2; anything else is a bug and
    propagates with its traceback. Used by `smana <command>` and by every `python -m` entry."""
    try:
        status = int(cli(argv) or 0)
        sys.stdout.flush()  # here, not at exit: a reader gone by then is the case below
        return status
    except USER_ERRORS as exc:
        print(f"smana {name}: {' '.join(str(exc).split())}", file=sys.stderr)
        if isinstance(exc, SessionError):
            # zenoh failed to open a session (a taken port, a bad endpoint): its runtime's
            # threads can abort the interpreter's exit ("terminate called without an active
            # exception", status -6 under load), so this process ends here, with the status
            # it owes; nothing of smana's is left to tear down
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(2)
        return 2
    except BrokenPipeError:
        # the reader went away (`smana deploy acl | head -1`): nothing more to tell it, and no
        # traceback; what is still buffered goes nowhere, not into a second error at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def exit_process(status: int) -> None:
    """End a service's process now, with `status`, once its `run` has returned: its state is
    flushed and its zenoh session closed by then, and the interpreter's own teardown (zenoh's
    runtime threads, worker pools) took over 5 s under load now and then, long enough for the
    supervisor to call a finished service hung and kill it. Logs and stdio are flushed first.
    Only for a process whose every file is written and closed when `run` returns."""
    import logging

    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


# A number or a comma-separated list of numbers (`-1.9,5.3`, `-2`, `-.5,1e3,-4`): a value, never
# an option. argparse (before 3.12.7) takes only `-5` and `-1.5` for negative numbers.
_UNSIGNED = r"(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
NUMBER_LIST = re.compile(rf"^-{_UNSIGNED}(?:,\s*[-+]?{_UNSIGNED})*$")


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a one-line error, `smana up: argument --duration: expected a number > 0, got
    '-5' (see smana up --help)`, and status 2: the usage block of a command with the shared flags
    is seven lines that hide the one that matters. Subcommand parsers inherit it.

    An argument that reads as a number list starting with a minus sign (`--to -1.9,5.3`) is a
    value, not an unknown option, for every option of every command (no smana flag looks like a
    number, which is what makes this safe)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse's own hook for what looks like a negative number (its `_parse_optional` treats
        # a match as positional while no option string looks like a number)
        self._negative_number_matcher = NUMBER_LIST

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def add_config_args(p: argparse.ArgumentParser) -> None:
    """`--config FILE` and `--set SECTION.KEY=VALUE`: how every command, a service or a tool
    (`smana world`), chooses its config. `config_file_from_args` reads them."""
    p.add_argument("--config", "-c", metavar="FILE", help="smana TOML config")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one config value, e.g. --set mapper.resolution_m=0.3 (repeatable)",
    )


def config_file_from_args(args: argparse.Namespace, layers=()) -> SmanaConfig:
    """The config `add_config_args`' flags choose: defaults, `layers`, the file, then --set."""
    return SmanaConfig.load(args.config, list(args.overrides or []), layers)


def doc_summary(doc: str | None) -> str:
    """A module docstring's first paragraph as one line: a command's --help description (its
    first line alone may stop mid-sentence)."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def make_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = ArgumentParser(prog=prog, description=description)
    add_config_args(p)
    p.add_argument("--robot", help="robot name, the <robot> segment of every key (default r1)")
    p.add_argument("--run-dir", help="directory for logs, saved state and the config used")
    p.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    add_zenoh_args(p)
    return p


def config_from_args(args: argparse.Namespace, layers=()) -> SmanaConfig:
    """Load `layers` and the config file, apply --set, then the dedicated flags. A bad config is a
    `ConfigError` naming the key (`run_command` prints it in one line)."""
    cfg = config_file_from_args(args, layers)
    general = cfg.general
    if args.robot:
        general = dataclasses.replace(general, robot=args.robot)
    if args.run_dir:
        general = dataclasses.replace(general, run_dir=args.run_dir)
    if args.log_level:
        general = dataclasses.replace(general, log_level=args.log_level)
    general.validate()
    if general.run_dir:  # before anything starts: a service would map, then fail to save
        not_a_file(general.run_dir)
    try:
        return dataclasses.replace(cfg, general=general, zenoh=apply_zenoh_args(cfg.zenoh, args))
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


class ServiceCommand:
    """A service's command line (`smana <name>`, `python -m smana.services.<name>`), the one
    sequence every `services/<name>/__main__.py` runs: the shared parser (`make_parser`), the
    config its flags choose (`config_from_args`, with the service's own flags turned into
    `--set` overrides), logging, then the service's `main(config, ...)`, imported only then (so
    that `--help` and a bad flag stay quick). An error of a `refused` kind from `main` (a file
    that cannot be read, a config that cannot work) is one line on stderr,
    `smana <name>: <error>`, and status 2. `cli` is the whole sequence for a service with no
    flag of its own; the others call `parser`, `config` and `run` around their own steps."""

    def __init__(
        self, name: str, description: str, main: str, refused: tuple[type, ...] = ()
    ) -> None:
        self.name = name
        self.description = description
        self.main = main  # "package.module:function"
        self.refused = refused

    def parser(self) -> argparse.ArgumentParser:
        return make_parser(f"smana {self.name}", self.description)

    def config(self, args: argparse.Namespace, overrides=()) -> SmanaConfig:
        """The config of the parsed `args`, `overrides` (`SECTION.KEY=VALUE`) after the user's."""
        args.overrides.extend(overrides)
        return config_from_args(args)

    def run(self, config: SmanaConfig, *extra) -> int:
        """Logging, then `main(config, *extra)`: its exit status."""
        setup_logging(config.general.log_level, self.name)
        module, function = self.main.split(":")
        main = getattr(importlib.import_module(module), function)
        try:
            return main(config, *extra)
        except self.refused as exc:
            print(f"smana {self.name}: {exc}", file=sys.stderr)
            return 2

    def cli(self, argv: list[str] | None = None) -> int:
        return self.run(self.config(self.parser().parse_args(argv)))


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format=f"%(asctime)s %(levelname)s {name}: %(message)s",
        stream=sys.stderr,
    )


# -- argument types: argparse reports a refused value in one line (ArgumentParser), status 2 ----


def _number(kind: type, low: float, inclusive: bool, high: float | None = None):
    bound = f">= {low:g}" if inclusive else f"> {low:g}"
    if high is not None:
        bound += f" and <= {high:g}"
    what = f"{'an integer' if kind is int else 'a number'} {bound}"

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        too_high = high is not None and v > high
        if not math.isfinite(v) or v < low or (v == low and not inclusive) or too_high:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v

    return parse


positive_float = _number(float, 0.0, inclusive=False)
non_negative_float = _number(float, 0.0, inclusive=True)
positive_int = _number(int, 0, inclusive=False)
non_negative_int = _number(int, 0, inclusive=True)


def int_in(low: int, high: int | None = None):
    """An argparse type: an integer from `low` (to `high`)."""
    return _number(int, low, inclusive=True, high=high)


def point(text: str) -> tuple[float, ...]:
    """An argparse type: a point `X,Y` or `X,Y,Z` in metres (`-1.9,5.3` too: `ArgumentParser`
    takes it for a value)."""
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) not in (2, 3) or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"expected X,Y in metres, got {text!r}")
    return v


def not_a_file(path: str | Path, what: str = "run directory", flag: str = "--run-dir") -> Path:
    """`path`, or a UsageError when it exists and is not a directory."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{what} {p} is a file, not a directory; choose another with {flag} DIR")
    return p


def output_dir(path: str | Path, what: str = "run directory", flag: str = "--run-dir") -> Path:
    """`path` as a directory to write into, created if missing. UsageError, before anything starts,
    when it is a file or cannot be created or written (`flag` is how to choose another)."""
    p = not_a_file(path, what, flag)
    fix = f"choose another with {flag} DIR"
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"{what} {p} cannot be created ({exc.strerror or exc}); {fix}") from None
    if not os.access(p, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {p} is not writable; {fix}")
    return p


def output_file(path: str | Path, what: str = "--out") -> Path:
    """`path` as a file to write: UsageError, before anything starts, when it is a directory or
    its folder does not exist."""
    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{what} {p} is a directory; give a file name")
    if not p.parent.is_dir():
        raise UsageError(f"{what} {p}: folder {p.parent} does not exist")
    return p
