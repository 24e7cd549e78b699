"""The one table of services: every part that lists services derives its list from `TABLE`.

A row says what a service is to the rest of smana: the `smana <name>` command and its entry module,
its `Service` class, whether and when `smana up` starts it (the table's order is the start order:
producers first), where it runs in a fleet, its default `[deploy.<name>]` policy, whether
`smana warmup` compiles its kernels, its roles in the access-control policy and the queries of it
that only read. Derived from it: the `smana` command's service commands (deploy/cli.py), the
`[deploy.<name>]` sections (common/config/deploy.py), `smana warmup`'s list (deploy/warmup.py),
the supervisor's start order, fleet layout and checks (deploy/supervisor.py, deploy/fleet.py,
deploy/outcome.py), the ACL's roles (deploy/acl.py) and `keys.SERVICES`.

A service outside smana is one row too, with no edit here: a distribution declares it under the
entry-point group `smana.services` (`echo = "my_package:ROW"`, ROW a `ServiceRow`); `rows()`
appends it after smana's own. tests/test_service_table.py adds a toy service that way.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Literal

ENTRY_POINT_GROUP = "smana.services"
FLEET_PLACES = ("shared", "member")
ACL_ROLES = ("robot", "sensor", "drive", "base", "fleet")


@dataclass(frozen=True)
class ServiceRow:
    """One service. Only `name` and `help` are required: a row with no more is a service that
    `smana up` starts, under each robot's name, and that owns `smana/<robot>/<name>/**`."""

    name: str
    help: str  # the one line of `smana --help`
    module: str = ""  # run as `python -m <module>` (default smana.services.<name>)
    # `smana <name>`'s "module:function" (default <module>.__main__:cli for smana's own services,
    # <module>:cli for another's); None: no such command
    command: str | None = ""
    service_class: str = ""  # "module:Class", its `Service` (for `smana warmup`)
    # "start": `smana up` starts it, in table order; "last": after the others and stopped once
    # they have exited (the recorder: it records everything they sent); None: `smana up` never
    # does and it has no [deploy.<name>] section.
    up: Literal["start", "last"] | None = "start"
    # In a fleet: "shared", one under the fleet's name on the base; "member", one per member on
    # its host. A service in neither does not run in a fleet.
    fleet: tuple[str, ...] = ()
    fleet_only: bool = False  # runs only in a fleet (the coordinator)
    deploy: dict[str, Any] = field(default_factory=dict)  # [deploy.<name>] defaults
    warm_up: bool = False  # `smana warmup` compiles its kernels (its class's prepare())
    # The ACL (deploy/acl.py): "robot", an identity `<robot>.<name>` that owns
    # `smana/<robot>/<name>/**`; "sensor", it also publishes the robot's sensor streams; "drive",
    # it also publishes the robot's velocity commands and, in a fleet, asks the coordinator for
    # the robot's claims; "base", a base may run it for a robot; "fleet", an identity
    # `<fleet>.<name>` on the base.
    acl: tuple[str, ...] = ("robot",)
    reads: tuple[str, ...] = ()  # its queries that only read: every identity may ask them
    needs: tuple[str, ...] = ()  # what it needs to do its job (a run's warning when one is missing)
    requires: tuple[tuple[str, str], ...] = ()  # (module, extra): checked before `smana up` starts

    def __post_init__(self):
        bad = [p for p in self.fleet if p not in FLEET_PLACES]
        bad += [r for r in self.acl if r not in ACL_ROLES]
        if not self.name.isidentifier() or bad or self.up not in ("start", "last", None):
            raise ValueError(f"service row {self.name!r}: bad name, up, fleet or acl value {bad}")
        if not self.module:
            object.__setattr__(self, "module", f"smana.services.{self.name}")
            main = f"{self.module}.__main__:cli"
        else:
            main = f"{self.module}:cli"
        if self.command == "":
            object.__setattr__(self, "command", main)

    @property
    def shared_only(self) -> bool:
        """In a fleet, only the fleet's own instance runs (under the fleet's name)."""
        return "shared" in self.fleet and "member" not in self.fleet


TABLE: tuple[ServiceRow, ...] = (
    ServiceRow(
        "sim",
        "run the PyBullet simulator service",
        service_class="smana.services.sim.service:SimService",
        fleet=("shared",),
        deploy={"standby": True},
        acl=("robot", "sensor"),
    ),
    ServiceRow(
        "replay",
        "replay a dataset into the stack",
        service_class="smana.services.replay.service:ReplayService",
        # `smana replay --run` starts it through `smana up`'s path, in the sim's place; sent
        # once, never restarted, and off in a plain `smana up`
        deploy={"enabled": False, "restart": "never"},
        acl=("robot", "sensor"),
    ),
    ServiceRow(
        "mapper",
        "run the semantic mapper service",
        service_class="smana.services.mapper.service:MapperService",
        fleet=("shared", "member"),
        deploy={"standby": True},
        warm_up=True,
        acl=("robot", "fleet"),
        reads=("stats", "snapshot", "point"),
    ),
    ServiceRow(
        "navgraph",
        "run the navigation graph service",
        service_class="smana.services.navgraph.service:NavgraphService",
        fleet=("shared",),
        deploy={"standby": True},
        warm_up=True,
        acl=("robot", "base", "fleet"),
        reads=("graph", "node", "stats"),
    ),
    ServiceRow(
        "planner",
        "run the weighted A* planner service",
        service_class="smana.services.planner.service:PlannerService",
        fleet=("member",),
        deploy={"standby": True},
        warm_up=True,
        acl=("robot", "base", "fleet"),
        reads=("path", "stats"),
    ),
    ServiceRow(
        "explorer",
        "run the frontier explorer service",
        service_class="smana.services.explorer.service:ExplorerService",
        fleet=("member",),
        deploy={"standby": True},
        warm_up=True,
        acl=("robot", "drive", "base"),
        reads=("state",),
        needs=("mapper", "navgraph", "planner", "coordinator"),
    ),
    ServiceRow(
        "coordinator",
        "run a fleet's coordinator (next-best views, no two robots to one frontier)",
        service_class="smana.services.coordinator.service:CoordinatorService",
        fleet=("shared",),
        fleet_only=True,
        acl=("fleet",),
        reads=("claims", "stats"),
    ),
    ServiceRow(
        "recorder",
        "record a run into a Rerun .rrd file",
        module="smana.services.recorder",
        service_class="smana.services.recorder.service:RecorderService",
        command=None,  # started by `smana up` only
        up="last",
        fleet=("shared",),
        acl=("robot", "base", "fleet"),
    ),
    ServiceRow(
        "ros2",
        "smana as a ROS 2 node over rmw_zenoh",
        service_class="smana.services.ros2.service:Ros2Service",
        deploy={"enabled": False},  # off unless asked: --set deploy.ros2.enabled=true
        requires=(("rosbags", "ros2"),),
        # With a real robot's topics it publishes the robot's clouds and pose (robot/scan,
        # robot/pose) as a driver does: the secured profile lets it.
        acl=("robot", "sensor"),
    ),
)


@functools.cache
def rows() -> tuple[ServiceRow, ...]:
    """`TABLE`, then every row declared under the entry-point group `smana.services`. A plug-in
    that does not load, is not a `ServiceRow` or reuses a name is left out with one warning."""
    import logging
    from importlib.metadata import entry_points

    log = logging.getLogger("smana.services")
    out = list(TABLE)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            row = ep.load()
        except Exception as exc:  # noqa: BLE001 - a broken plug-in must not stop smana
            log.warning("service plug-in %s = %s does not load: %s", ep.name, ep.value, exc)
            continue
        if not isinstance(row, ServiceRow):
            log.warning("service plug-in %s = %s is not a ServiceRow", ep.name, ep.value)
        elif any(r.name == row.name for r in out):
            log.warning("service plug-in %s: a service %r exists already", ep.value, row.name)
        else:
            out.append(row)
    return tuple(out)


def names() -> tuple[str, ...]:
    return tuple(r.name for r in rows())


def row(name: str) -> ServiceRow | None:
    return next((r for r in rows() if r.name == name), None)


def supervised() -> tuple[ServiceRow, ...]:
    """The rows `smana up` can start (those with a `[deploy.<name>]` section)."""
    return tuple(r for r in rows() if r.up is not None)


def start_order() -> tuple[str, ...]:
    """What `smana up` starts first, in order (the last wave, the recorder, aside)."""
    return tuple(r.name for r in rows() if r.up == "start")


def fleet(place: str) -> tuple[str, ...]:
    """The services a fleet runs at `place`: "shared" (the base's) or "member" (each member's)."""
    return tuple(r.name for r in rows() if r.up == "start" and place in r.fleet)


def with_acl(role: str) -> tuple[str, ...]:
    return tuple(r.name for r in rows() if role in r.acl)


def stops_last(name: str) -> bool:
    r = row(name)
    return r is not None and r.up == "last"
