"""A fleet under `smana up` (`fleet.robots`, `smana up --robots N`): the fleet's shared services
run under `fleet.name` on the base (`deploy.fleet_base`), each member's own under its name, on its
host (`deploy.robots`, default every member). One simulator simulates every member. Which service
is which is the table of services' `fleet` column (common/service_table.py).
"""

from __future__ import annotations

import json

from smana.common import service_table
from smana.common.config import ConfigError


def add_fleet(sup, names: list[str]) -> None:
    """Add the fleet's services among `names` (those enabled) to `sup`: the shared ones
    (`service_table.fleet("shared")`) under the fleet's name, each member's own
    (`service_table.fleet("member")`) under its name. Members' files go to
    `<run_dir>/robots/<member>/` (their own map, the explorer's state), the fleet's to the
    run directory itself (the merged map, the simulator's record)."""
    fc, dc = sup.config.fleet, sup.config.deploy
    if not dc.fleet_members:
        members = []
    elif dc.robots:
        members = list(dc.robots)
    else:  # a base runs every member; a member's own host runs itself
        members = list(fc.robots) if dc.fleet_base else [sup.config.general.robot]
    strangers = [r for r in members if r not in fc.robots]
    if strangers:
        raise ConfigError(f"deploy.robots {strangers} are not in fleet.robots {fc.robots}")
    sup.robots = members or [sup.fleet]
    enabled = names
    if dc.fleet_base:
        for n in service_table.fleet("shared"):
            if n in enabled:
                extra = ["--set", 'mapper.source="fleet"'] if n == "mapper" else []
                sup._add_service(f"{n}@{sup.fleet}", n, sup.fleet, extra)
    for robot in members:
        run_dir = sup.run_dir / "robots" / robot
        run_dir.mkdir(parents=True, exist_ok=True)
        for n in service_table.fleet("member"):
            if n in enabled:
                extra = ["--set", f"general.run_dir={json.dumps(str(run_dir))}"]
                sup._add_service(f"{n}@{robot}", n, robot, extra)
