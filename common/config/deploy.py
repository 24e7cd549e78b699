"""[deploy] config section: how `smana up` runs the stack, and one `[deploy.<service>]` table per
service it can start, made from the table of services (common/service_table.py: each row's `deploy`
defaults), so a plug-in's service gets its table with no edit here."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from smana.common import service_table
from smana.common.config.section import ConfigError, Section, param

RestartPolicy = Literal["never", "on-failure", "always"]


@dataclass
class ServiceDeployConfig(Section):
    """How the supervisor runs one service (dora's vocabulary)."""

    enabled: bool = True  # `smana up` starts it
    restart: RestartPolicy = "on-failure"  # when an exited service is started again
    # The first restart waits restart_delay_s, each further one in restart_window_s twice as
    # long, up to restart_max_delay_s. Past max_restarts in the window the service is in a crash
    # loop: it is still restarted (every restart_max_delay_s) and the run is reported failed.
    restart_delay_s: float = param(0.1, ge=0)
    restart_max_delay_s: float = param(10.0, ge=0)
    max_restarts: int = param(5, ge=0)
    restart_window_s: float = param(60.0, gt=0)
    # A hot spare: once the service is ready, a second process imports and prepares (kernels, a
    # simulated world) and waits; a crashed service is taken over by it in a fraction of a second
    # instead of seconds of start-up. Costs that process's memory (~160-180 MB) while it waits.
    standby: bool = False
    args: list[str] = param([])  # extra command-line arguments


@dataclass
class _DeployBase(Section, section="deploy"):
    profile: str = "local"  # set by `smana up --profile NAME` (deploy/profiles/NAME.toml)
    # The supervisor's router. Local services connect to the FIRST listen endpoint; further ones
    # (e.g. tls/0.0.0.0:7448 on a base station) are for other hosts' routers.
    router_listen: list[str] = param(["tcp/127.0.0.1:7447"])
    router_connect: list[str] = param([])  # other routers (robot -> base)
    robots: list[str] = param([])  # multi-robot: one instance per robot name (in a fleet: the
    # members whose own services run on this host; [] = every member on the base, else
    # general.robot)
    fleet_base: bool = True  # a fleet: this host runs the fleet's shared services
    fleet_members: bool = True  # a fleet: this host runs members' own services
    # Health: a service shows its `starting` token within health_timeout_s of its start (or it is
    # killed and restarted), then its `alive` token within startup_timeout_s (loading a map,
    # compiling numba kernels on a cold cache: minutes on a loaded 2-core machine).
    health_timeout_s: float = param(30.0, gt=0)
    startup_timeout_s: float = param(600.0, gt=0)
    # A service with `standby` gets its hot spare once it has been ready this long: a short run
    # (a test, a quick experiment) never pays for spares, and the spares' imports never compete
    # with the stack's own start-up on a 2-core machine.
    standby_delay_s: float = param(20.0, ge=0)
    stop_timeout_s: float = param(5.0, gt=0)  # after SIGINT, a service still running is killed
    finish_with: str = "explorer"  # the run ends when this service exits with status 0

    def validate(self) -> None:
        from smana.common.keys import check_name

        for robot in self.robots:
            try:
                check_name(robot)
            except ValueError as exc:
                raise ConfigError(f"deploy.robots: {exc}") from None


def _policy(defaults: dict):
    return field(default_factory=lambda: ServiceDeployConfig(**defaults))


# [deploy] with a ServiceDeployConfig field per service `smana up` can start, in table order.
DeployConfig = dataclasses.make_dataclass(
    "DeployConfig",
    [(r.name, ServiceDeployConfig, _policy(r.deploy)) for r in service_table.supervised()],
    bases=(_DeployBase,),
    namespace={
        "__doc__": "[deploy]: the supervisor's settings and each service's policy.",
        "__module__": __name__,
    },
)
DeployConfig.section = "deploy"  # make_dataclass passes no class keywords to __init_subclass__
