"""Command-line plumbing every smana command shares: `--config`, `--set`, `--robot`, `--run-dir`,
`--log-level` and the zenoh flags, turned into one validated `SmanaConfig`."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys

from smana.common.config import ConfigError, SmanaConfig
from smana.common.zenoh_config import add_zenoh_args, apply_zenoh_args


def make_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--config", "-c", metavar="FILE", help="smana TOML config")
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override one config value, e.g. --set mapper.resolution_m=0.3 (repeatable)",
    )  # fmt: skip
    p.add_argument("--robot", help="robot name, the <robot> segment of every key (default r1)")
    p.add_argument("--run-dir", help="directory for logs, saved state and the config used")
    p.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    add_zenoh_args(p)
    return p


def config_from_args(args: argparse.Namespace, layers=()) -> SmanaConfig:
    """Load `layers` and the config file, apply --set, then the dedicated flags. Exits with a clear
    message on a bad config instead of a traceback."""
    overrides = list(args.overrides or [])
    try:
        cfg = SmanaConfig.load(args.config, overrides, layers)
    except ConfigError as exc:
        sys.exit(f"config error: {exc}")
    general = cfg.general
    if args.robot:
        general = dataclasses.replace(general, robot=args.robot)
    if args.run_dir:
        general = dataclasses.replace(general, run_dir=args.run_dir)
    if args.log_level:
        general = dataclasses.replace(general, log_level=args.log_level)
    try:
        general.validate()
        return dataclasses.replace(cfg, general=general, zenoh=apply_zenoh_args(cfg.zenoh, args))
    except (ConfigError, ValueError) as exc:
        sys.exit(f"config error: {exc}")


def setup_logging(level: str, name: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format=f"%(asctime)s %(levelname)s {name}: %(message)s",
        stream=sys.stderr,
    )
