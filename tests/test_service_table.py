"""The table of services (common/service_table.py): every list of services derives from it, and a
service is a folder plus one row. The toy is tests/support/echo_service.py, declared by a row in a
plug-in made here (a module and an entry point of group `smana.services`, on PYTHONPATH): with no
edit to any file of smana, `smana up` starts it and it answers its status query over zenoh, it
is in the access-control policy, `smana --help` lists it and `[deploy.echo]` configures it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from smana.common import keys, service_table
from smana.common.config import SmanaConfig
from smana.common.registry import load_spec
from smana.deploy import acl, supervisor, warmup
from tests.conftest import REPO, free_port, stop_group, wait_for

ROW = """
from smana.common.service_table import ServiceRow

ROW = ServiceRow(
    "echo",
    "a toy service (tests/test_service_table.py)",
    module="tests.support.echo_service",
    service_class="tests.support.echo_service:EchoService",
    reads=("count",),
)
NOT_A_ROW = ("echo2", "a plug-in's mistake")
"""


def plugin(tmp_path: Path, *entries: str) -> dict:
    """An installed plug-in, as pip would leave it: its module and its dist-info (METADATA, its
    entry points) in a folder on PYTHONPATH. Returns the environment that sees it."""
    where = tmp_path / "plugin"
    info = where / "echo_toy-0.1.dist-info"
    info.mkdir(parents=True)
    (where / "echo_toy.py").write_text(ROW)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: echo-toy\nVersion: 0.1\n")
    lines = "\n".join(entries or ["echo = echo_toy:ROW"])
    (info / "entry_points.txt").write_text(f"[smana.services]\n{lines}\n")
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(where), str(REPO)]))


def smana(*argv: str, env: dict, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "smana.deploy.cli", *argv],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
    )


def test_the_lists_that_name_services_are_the_table_s():
    """What used to be hand-kept in seven places, derived: the same values as before the table."""
    assert supervisor.SERVICE_ORDER == (
        "sim",
        "replay",
        "mapper",
        "navgraph",
        "planner",
        "explorer",
        "coordinator",
        "ros2",
    )
    assert supervisor.FLEET_SHARED == ("sim", "mapper", "navgraph", "coordinator")
    assert supervisor.FLEET_MEMBER == ("mapper", "planner", "explorer")
    assert supervisor.OPTIONAL_NEEDS == {"ros2": (("rosbags", "ros2"),)}
    assert list(warmup.WARMUPS) == ["mapper", "navgraph", "planner", "explorer"]
    for name, spec in warmup.WARMUPS.items():
        assert load_spec(spec).name == name  # the class the row names is that service's
    assert set(keys.SERVICES) == {
        *("sim", "mapper", "navgraph", "planner", "explorer"),
        *("replay", "recorder", "ros2", "coordinator"),
    }
    # the ros2 service publishes a ROS 2 robot's sensor streams as a driver does (issue 28)
    assert acl.OWNERS == (
        *("sim", "replay", "ros2", "driver", "mapper", "navgraph"),
        *("planner", "explorer", "recorder"),
    )
    assert acl.BASE_RUNS == ("navgraph", "planner", "explorer", "recorder")
    assert acl.FLEET_ROLES == ("mapper", "navgraph", "planner", "coordinator", "recorder")
    assert acl.SENSOR_ROLES == ("sim", "replay", "ros2", "driver")
    assert acl.GOAL_SENDERS == ("explorer", "ros2")
    assert acl.DRIVERS == ("explorer",)
    assert acl.READ_QUERIES == (
        *("mapper/stats", "mapper/snapshot", "mapper/point"),
        *("navgraph/graph", "navgraph/node", "navgraph/stats", "planner/path", "planner/stats"),
        *("explorer/state", "coordinator/claims", "coordinator/stats", "*/status"),
    )
    d = SmanaConfig.load().deploy
    supervised = [r.name for r in service_table.supervised()]
    assert sorted(supervised) == sorted([*supervisor.SERVICE_ORDER, "recorder"])
    standby = ["sim", "mapper", "navgraph", "planner", "explorer"]
    assert [n for n in supervised if getattr(d, n).standby] == standby
    # `smana up` starts the replay only for `smana replay --run`, in the sim's place, once
    assert [n for n in supervised if not getattr(d, n).enabled] == ["replay", "ros2"]
    assert d.replay.restart == "never"


def test_a_row_with_a_value_outside_its_column_is_refused():
    with pytest.raises(ValueError, match="bad name, up, fleet or acl"):
        service_table.ServiceRow("echo", "x", fleet=("everywhere",))
    with pytest.raises(ValueError, match="bad name, up, fleet or acl"):
        service_table.ServiceRow("no/slash", "x")


def test_a_plugin_row_is_in_the_acl_the_help_and_the_config(tmp_path):
    env = plugin(tmp_path)
    acl = smana("deploy", "acl", "--robots", "r1,r2", env=env)
    assert acl.returncode == 0, acl.stderr
    policy = json.loads(acl.stdout)
    rules = {r["id"]: r for r in policy["rules"]}
    for robot in ("r1", "r2"):
        assert any(s["usernames"] == [f"{robot}.echo"] for s in policy["subjects"])
        assert rules[f"own-{robot}.echo"]["key_exprs"] == [f"smana/{robot}/echo/**"]
        assert rules[f"alive-{robot}.echo"]["key_exprs"] == [f"smana/{robot}/alive/echo"]
    assert "smana/*/echo/count" in rules["read-queries"]["key_exprs"]
    # without the plug-in, none of it
    plain = smana("deploy", "acl", "--robots", "r1", env=dict(os.environ))
    assert "echo" not in plain.stdout
    helps = smana("--help", env=env)
    assert "\n  echo " in helps.stdout, helps.stdout
    echo_help = smana("echo", "--help", env=env)
    assert echo_help.returncode == 0 and "--cloud-delay" in echo_help.stdout, echo_help.stderr
    code = "from smana.common import keys; from smana.common.config import SmanaConfig; "
    code += "print(keys.SERVICES[-1], SmanaConfig.load(None, ['deploy.echo.max_restarts=2'])"
    code += ".deploy.echo.max_restarts)"
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert got.stdout.split() == ["echo", "2"], got.stderr


def test_a_plugin_that_does_not_load_or_is_not_a_row_is_one_warning_and_left_out(tmp_path):
    env = plugin(tmp_path, "echo2 = echo_toy:NOT_A_ROW", "echo3 = no_such_module:ROW")
    helps = smana("--help", env=env)
    assert helps.returncode == 0
    assert "echo2" not in helps.stdout and "echo3" not in helps.stdout
    lines = sorted(ln for ln in helps.stderr.splitlines() if ln.strip())
    assert lines == [
        "service plug-in echo2 = echo_toy:NOT_A_ROW is not a ServiceRow",
        "service plug-in echo3 = no_such_module:ROW does not load: No module named "
        "'no_such_module'",
    ], lines


def test_the_product_names_no_lab_module_and_lab_commands_register_themselves():
    """deploy/cli.py names no module of lab/: `smana bench`, `eval` and `experiment` come from the
    entry-point group `smana.commands` (pyproject.toml) and are in `smana --help`."""
    from smana.deploy.cli import COMMANDS, _usage

    source = (REPO / "deploy" / "cli.py").read_text()
    assert "smana.lab" not in source
    for name in ("bench", "eval", "experiment"):
        assert COMMANDS[name][0].startswith("smana.lab."), COMMANDS[name]
        assert f"\n  {name} " in _usage()


@pytest.mark.multiprocess
def test_smana_up_starts_a_plugin_service_that_answers_its_status(tmp_path):
    """A service is a folder plus one row: `smana up --only echo` starts the toy under its
    `[deploy.echo]` policy, and it answers `smana/<robot>/echo/status` over zenoh."""
    import zenoh

    from smana.common.config import ZenohConfig
    from smana.common.messages import ServiceStatus
    from smana.common.query import QueryError, request
    from smana.common.zenoh_config import make_zenoh_config

    env = plugin(tmp_path)
    port = free_port()
    log = tmp_path / "up.log"
    argv = ["up", "--only", "echo", "--robot", "tbl", "--run-dir", str(tmp_path / "run")]
    argv += ["--set", f'deploy.router_listen=["tcp/127.0.0.1:{port}"]']
    argv += ["--set", "deploy.echo.restart=never", "--set", "general.status_period_s=0.5"]
    up = subprocess.Popen(
        [sys.executable, "-m", "smana.deploy.cli", *argv],
        stdout=open(log, "wb"),  # noqa: SIM115 - the child owns it
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env=env,
        cwd=REPO,
    )

    def status():
        try:
            st = request(session, keys.status("tbl", "echo"), timeout_s=1)
        except QueryError:
            return None
        return st if isinstance(st, ServiceStatus) else None

    try:
        assert wait_for(lambda: "zenoh router listening" in log.read_text(), 60), log.read_text()
        conf = make_zenoh_config(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
        with zenoh.open(conf) as session:
            assert wait_for(status, 60), log.read_text()
            st = status()
            assert (st.robot, st.service) == ("tbl", "echo")
            assert st.pid != up.pid  # its own process, started by the supervisor
    finally:
        stop_group(up, signal.SIGINT, timeout_s=60)
    written = (tmp_path / "run" / "config.toml").read_text()
    assert "[deploy.echo]" in written and 'restart = "never"' in written
    assert "started echo" in log.read_text()
    assert (tmp_path / "run" / "logs" / "echo.log").is_file()


def test_a_service_the_explorer_needs_that_never_came_up_is_a_warning(tmp_path):
    """The explorer's `needs` row: each of mapper, navgraph and planner that was never ready is a
    warning, on the robot's own name alone and on the fleet's name for the fleet's shared ones;
    the coordinator only in a fleet. Nothing is started: the supervisor is only built."""

    def needs_lines(overrides, services_=None):
        cfg = SmanaConfig.load(None, overrides)
        sup = supervisor.Supervisor(cfg, tmp_path / str(len(list(tmp_path.iterdir()))), services_)
        sup.seen_ready = {("r1", "mapper"), ("r2", "mapper")}
        return sorted(w for w in sup.warnings() if "needs never came up" in w)

    assert needs_lines(["deploy.navgraph.enabled=false"], None) == [
        "the navgraph the explorer of robot r1 needs never came up (disabled in this run "
        "(deploy.navgraph.enabled = false) and none ran elsewhere)",
        "the planner the explorer of robot r1 needs never came up (see above)",
    ]
    fleet = needs_lines(['fleet.robots=["r1", "r2"]'], ["mapper", "navgraph", "explorer"])
    assert fleet == [
        f"the {need} the explorer of robot {r} needs never came up ({why})"
        for need, why in (
            (
                "coordinator",
                "disabled in this run (deploy.coordinator.enabled = false) and none ran elsewhere",
            ),
            ("navgraph", "see above"),
            (
                "planner",
                "disabled in this run (deploy.planner.enabled = false) and none ran elsewhere",
            ),
        )
        for r in ("r1", "r2")
    ]
    assert needs_lines(['deploy.finish_with="replay"']) == []  # the replay's row needs nothing
