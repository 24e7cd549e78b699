"""[general] config section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from smana.common.config.section import ConfigError, Section, param


@dataclass
class GeneralConfig(Section, section="general"):
    robot: str = "r1"  # the <robot> segment of every key (smana/<robot>/...)
    class_table: str = "garden3drms"  # bundled name or path to a TOML class table
    run_dir: str = ""  # empty: runs/<timestamp> for `smana up`; no files for a lone service
    status_period_s: float = param(1.0, gt=0)  # how often each service publishes its status
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"  # of every service's log
    # Plausibility of inputs (common/plausibility.py): a stamp more than stamp_window_s behind
    # its stream's clock, or ahead of where that clock can be (max_time_rate seconds of stream
    # time per wall second: a simulator's real-time factor, a lockstep replay), is refused; so is
    # a pose further from the last one than max_speed_mps allows, plus pose_slack_m of noise.
    stamp_window_s: float = param(5.0, gt=0)
    max_time_rate: float = param(100.0, gt=0)
    max_speed_mps: float = param(3.0, gt=0)
    pose_slack_m: float = param(1.0, ge=0)

    def validate(self) -> None:
        from smana.common.keys import check_name

        try:
            check_name(self.robot)
        except ValueError as exc:
            raise ConfigError(f"general.robot: {exc}") from None


@dataclass
class ZenohConfig(Section, section="zenoh"):
    # The embedded default: every process is a client of the supervisor's router on loopback.
    mode: Literal["peer", "client", "router"] = "client"
    connect: list[str] = param(["tcp/127.0.0.1:7447"])  # endpoints this session connects to
    listen: list[str] = param([])  # endpoints this session listens on
    multicast_scouting: bool = False  # find peers by multicast (off: only `connect`)
    gossip: bool = False  # learn peers from other peers
    config_file: str = ""  # a zenoh JSON5 config applied first; the keys above override it
    # Security, all from zenoh's own features (`smana deploy init-certs` makes the files):
    tls_ca: str = ""  # CA certificate that every tls/ link is checked against
    tls_cert: str = ""  # this host's certificate and key, for listening and connecting (mTLS)
    tls_key: str = ""  # the private key of tls_cert
    mtls: bool = True  # a listener also demands a certificate signed by the CA
    user: str = ""  # user/password authentication: this session's user name...
    credentials_file: str = ""  # ...whose password is its `user:password` line in this file
    # (a file of one line also names the user); a router accepts every user of the file
    acl_file: str = ""  # a router's access-control policy (JSON5 `access_control` block)
