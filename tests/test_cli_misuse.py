"""Misuse of the command line ends in one line on stderr and exit status 2, never in a traceback.

Each case runs `python -m smana.deploy ...` as the user would. No stack starts: a taken port is
a plain listening socket, "nobody there" is a free loopback port, and every command gets explicit
endpoints (never 7447, where a real stack may run) with multicast scouting off.
"""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from smana.common.cli import UsageError, run_command
from smana.common.config import ConfigError
from tests.conftest import REPO, free_port

NO_SCOUT = "--no-multicast-scouting"


def smana(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "smana.deploy", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd or REPO,
        stdin=subprocess.DEVNULL,
    )


def one_line_misuse(r: subprocess.CompletedProcess, command: str, *words: str) -> str:
    """Exit 2, no traceback, stderr one line `smana <command>: ...` holding every word."""
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert len(lines) == 1, r.stderr
    # argparse names a subcommand's parser in full (`smana world export: argument ...`)
    assert lines[0].startswith(f"smana {command}"), lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.fixture
def taken_port():
    """A loopback port something else already listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


# -- zenoh sessions --------------------------------------------------------------------------------


def test_up_on_a_taken_port_names_it_and_how_to_move(tmp_path, taken_port):
    ep = f"tcp/127.0.0.1:{taken_port}"
    r = smana(
        "up",
        "--only",
        "planner",
        "--run-dir",
        str(tmp_path / "run"),
        NO_SCOUT,
        "--set",
        f'deploy.router_listen=["{ep}"]',
    )
    line = one_line_misuse(
        r, "up", f"{ep} is already in use", "another smana stack", "--set 'deploy.router_listen=["
    )
    assert f"127.0.0.1:{taken_port + 1}" in line
    assert not (tmp_path / "run").exists()  # nothing ran: no run directory left behind


def test_service_on_a_taken_port_suggests_listen(taken_port):
    ep = f"tcp/127.0.0.1:{taken_port}"
    r = smana("planner", "--mode", "peer", "--listen", ep, NO_SCOUT, "--log-level", "WARNING")
    one_line_misuse(
        r, "planner", f"{ep} is already in use", f"--listen tcp/127.0.0.1:{taken_port + 1}"
    )


def test_router_on_a_taken_port(taken_port):
    r = smana("router", "--listen", f"tcp/127.0.0.1:{taken_port}", NO_SCOUT)
    one_line_misuse(r, "router", "already in use", "--listen")


@pytest.mark.parametrize(
    "endpoint, words",
    [
        ("nonsense", ["'nonsense' is not a zenoh endpoint", "tcp/127.0.0.1:7447"]),
        ("tcp/127.0.0.1", ["expected tcp/<host>:<port>"]),
        ("tcp/127.0.0.1:99999", ["port from 0 to 65535"]),
        ("foo/127.0.0.1:1", ["unknown protocol 'foo'"]),
    ],
)
def test_bad_endpoint(endpoint, words):
    one_line_misuse(smana("status", "--connect", endpoint, NO_SCOUT), "status", *words)


@pytest.mark.parametrize(
    "text, words",
    [
        ("{ mode: ", ["line 1, column 9", "expected"]),  # JSON5 that does not parse
        ("{ mode: 'client', nosuch: 1 }", ["line 1, column 19", "unknown field `nosuch`"]),
        ("{ mode: 'bogus' }", ["unknown variant `bogus`"]),
    ],
)
def test_broken_zenoh_config_file(tmp_path, text, words):
    f = tmp_path / "zenoh.json5"
    f.write_text(text)
    r = smana(
        "status", "--zenoh-config", str(f), "--connect", f"tcp/127.0.0.1:{free_port()}", NO_SCOUT
    )
    one_line_misuse(r, "status", f"zenoh config file {f}:", *words)


def test_missing_zenoh_config_file(tmp_path):
    r = smana("status", "--zenoh-config", str(tmp_path / "nope.json5"), NO_SCOUT)
    one_line_misuse(r, "status", "zenoh config file not found", "nope.json5")


def test_status_with_nothing_to_connect_to():
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = smana("status", "--connect", ep, NO_SCOUT)
    one_line_misuse(r, "status", f"cannot connect to {ep}", "smana up", "--connect")


def test_client_without_any_endpoint():
    r = smana("status", "--set", "zenoh.connect=[]", NO_SCOUT)
    one_line_misuse(r, "status", "nothing to connect to", "--connect")


def test_plan_with_no_stack():
    r = smana(
        "plan",
        "--from",
        "0,0",
        "--to",
        "1,1",
        "--connect",
        f"tcp/127.0.0.1:{free_port()}",
        NO_SCOUT,
    )
    one_line_misuse(r, "plan", "cannot connect to", "smana up")


def test_goto_with_no_stack():
    r = smana("goto", "1", "2", "--connect", f"tcp/127.0.0.1:{free_port()}", NO_SCOUT)
    one_line_misuse(r, "goto", "cannot connect to", "smana up")


# -- arguments, checked before anything starts ---------------------------------------------------


@pytest.mark.parametrize("value", ["-5", "0", "nan", "soon"])
def test_up_refuses_a_duration_that_is_not_positive(tmp_path, value):
    r = smana("up", "--duration", value, "--run-dir", str(tmp_path / "run"))
    one_line_misuse(r, "up", "argument --duration: expected a number > 0", repr(value))
    assert not (tmp_path / "run").exists()


def test_up_refuses_a_run_dir_that_is_a_file(tmp_path):
    f = tmp_path / "afile"
    f.write_text("")
    # the router's port is free: the run directory is refused before it opens
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = smana(
        "up",
        "--only",
        "planner",
        "--run-dir",
        str(f),
        "--duration",
        "1",
        NO_SCOUT,
        "--set",
        f'deploy.router_listen=["{ep}"]',
    )
    one_line_misuse(r, "up", f"run directory {f} is a file", "--run-dir")
    r = smana(
        "up",
        "--only",
        "planner",
        "--run-dir",
        str(f / "sub"),
        "--duration",
        "1",
        NO_SCOUT,
        "--set",
        f'deploy.router_listen=["{ep}"]',
    )
    one_line_misuse(r, "up", "cannot be created", "--run-dir")


def test_mapper_run_dir_is_a_file(tmp_path):
    """A service alone refuses a run directory that is a file before it maps anything (it used
    to map, then lose the map in a FileExistsError on SIGTERM and exit 0)."""
    f = tmp_path / "afile"
    f.write_text("")
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = smana("mapper", "--run-dir", str(f), "--connect", ep, NO_SCOUT)
    one_line_misuse(r, "mapper", f"run directory {f} is a file")
    assert f.read_text() == ""


def test_missing_extra_fails_the_stack_at_once(tmp_path):
    """`smana up` with a service whose optional package is missing stops before anything starts,
    in one line naming the extra (it used to restart the service 8 times). `rosbags` is hidden the
    way Python hides a module: `sys.modules["rosbags"] = None`."""
    code = (
        "import sys; sys.modules['rosbags'] = None\n"
        "from smana.common.cli import run_command\n"
        "from smana.deploy.supervisor import cli\n"
        "sys.exit(run_command('up', cli))"
    )
    ep = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "run"
    args = ["--set", "deploy.ros2.enabled=true", "--run-dir", str(run_dir), NO_SCOUT]
    args += ["--set", f'deploy.router_listen=["{ep}"]', "--duration", "60"]
    r = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    one_line_misuse(r, "up", "rosbags", "pip install 'smana[ros2]'")
    assert not run_dir.exists()


def test_bad_config_value_is_one_line(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[mapper]\nresolution_m = -1\n")
    r = smana("status", "--config", str(cfg))
    one_line_misuse(r, "status", "mapper.resolution_m: expected a number > 0")


@pytest.mark.parametrize(
    "command, args, words",
    [
        ("status", ["--timeout", "0"], ["--timeout", "> 0"]),
        (
            "status",
            [
                "--set",
                "zenoh.tls_ca=ca.pem",
                "--set",
                "zenoh.tls_cert=c.pem",
                "--set",
                "zenoh.tls_key=k.pem",
            ],
            ["zenoh.tls_ca: file not found"],
        ),
        ("sim", ["--pose-noise", "abc"], ["--pose-noise"]),
        ("explorer", ["--budget", "0"], ["--budget", "> 0"]),
        ("plan", ["--from", "0,0", "--to", "1,1", "--max-step", "-1"], ["--max-step"]),
        ("plan", ["--from", "0,0", "--to", "1,1", "--timeout", "-2"], ["--timeout"]),
        ("plan", ["--from", "0,0", "--to", "1,1", "--cost", "grass=-1"], ["--cost", ">= 0"]),
        ("goto", ["1", "nan"], ["argument y", "finite"]),
        ("goto", ["1", "2", "--tolerance", "0"], ["--tolerance", "> 0"]),
        ("goto", ["1", "2", "--yaw", "inf"], ["--yaw", "finite"]),
        ("goto", ["1"], ["required", "y"]),
        ("goto", ["1", "2", "--id", "x" * 65], ["--id", "64 printable"]),
        ("replay", ["--rate", "0", "x"], ["--rate", "> 0"]),
        ("replay", ["--count", "-1", "x"], ["--count", ">= 0"]),
        ("bench planner", ["--queries", "9"], ["--queries", "<= 4"]),
        ("bench sim", ["--runs", "0"], ["--runs", "> 0"]),
        ("bench replay", ["--res", "0.1/0"], ["--res", "MAP/GRAPH"]),
        ("experiment exploration", ["--budget", "-1"], ["--budget", "> 0"]),
        ("experiment exploration", ["--set", "explorer.nope=1"], ["explorer.nope"]),
        ("eval map", [".", "--spacing", "0"], ["--spacing"]),
        ("world export", ["--out", "w.ply", "--size", "-1"], ["--size", "> 0"]),
        ("world export", ["--out", "no/such/dir/w.ply"], ["--out", "does not exist"]),
    ],
)
def test_impossible_values_are_refused_up_front(tmp_path, command, args, words):
    if command in ("status", "plan", "goto"):  # were a value let through, nobody would answer
        args = [*args, "--connect", f"tcp/127.0.0.1:{free_port()}", NO_SCOUT]
    r = smana(*command.split(), *args, cwd=tmp_path)
    one_line_misuse(r, command.split()[0], *words)
    assert not list(tmp_path.iterdir())  # nothing was written


def test_experiment_out_that_is_a_file(tmp_path):
    f = tmp_path / "afile"
    f.write_text("")
    r = smana("experiment", "exploration", "--quick", "--out", str(f))
    one_line_misuse(r, "experiment", "is a file", "--out")


# -- names and numbers that escaped: one line, exit 2 within 10 s, nothing left running ---------


def smana_alone(tmp_path, *args: str, timeout_s: float = 10.0):
    """Run `smana ...` in its own process group with a marker in its environment (inherited by
    anything it starts, in whatever group); returns (completed, seconds, processes left)."""
    import os
    import signal
    import time
    import uuid

    import psutil

    mark = uuid.uuid4().hex
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "smana.deploy", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        cwd=tmp_path,
        start_new_session=True,
        env=dict(os.environ, SMANA_MISUSE_MARK=mark),
    )

    def left() -> list:
        out = []
        for p in psutil.process_iter():
            try:
                if p.pid != os.getpid() and (
                    os.getpgid(p.pid) == proc.pid or p.environ().get("SMANA_MISUSE_MARK") == mark
                ):
                    out.append(p)
            except (psutil.Error, ProcessLookupError, PermissionError):
                continue
        return out

    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        for p in left():
            p.kill()
        out, err = proc.communicate()
        pytest.fail(f"smana {' '.join(args)} still running after {timeout_s} s:\n{err}")
    took = time.monotonic() - t0
    remaining = left()
    for p in remaining:  # leave the machine clean even when the test fails
        with __import__("contextlib").suppress(psutil.Error):
            p.send_signal(signal.SIGKILL)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done, took, remaining


def _no_router_args() -> list[str]:
    # were anything to start, it would listen on a free port, never on a real stack's 7447
    return [NO_SCOUT, "--set", f'deploy.router_listen=["tcp/127.0.0.1:{free_port()}"]']


@pytest.mark.parametrize(
    "args, words",
    [
        (["up", "--set", 'fleet.robots=["a/b"]'], ["fleet.robots", "'a/b'", "[A-Za-z0-9_-]"]),
        (["up", "--set", 'fleet.name="f*"'], ["fleet.name", "'f*'"]),
        (["up", "--robot", "a/b"], ["general.robot", "'a/b'"]),
        (["up", "--set", 'general.robot="r$1"'], ["general.robot", "'r$1'"]),
        (["up", "--set", 'deploy.robots=["r1", "r#2"]'], ["deploy.robots", "'r#2'"]),
        (["up", "--robot", "r" * 33], ["general.robot", "{1,32}"]),
        (["up", "--robot", "mapper@r1"], ["'mapper@r1'"]),
        (["replay", "--robot", "a?b", "data"], ["general.robot", "'a?b'"]),
        (["ros2", "--robot", "a/b"], ["general.robot", "'a/b'"]),
        (["up", "--set", "mapper.resolution_m=1e400"], ["mapper.resolution_m", "finite", "inf"]),
        (["up", "--set", "navgraph.resolution_m=-1e400"], ["navgraph.resolution_m", "finite"]),
        (["up", "--set", "mapper.resolution_m=1e-9"], ["mapper.resolution_m", "at least 0.01 m"]),
        (["up", "--set", "mapper.resolution_m=1e300"], ["mapper.resolution_m", "<= 10,"]),
        (["up", "--set", "explorer.time_budget_s=inf"], ["explorer.time_budget_s", "finite"]),
        (["up", "--set", "navgraph.bounds_max_xy=[1e300, 1e300]"], ["navgraph.bounds", "nodes"]),
        (["up", "--set", "navgraph.resolution_m=1e-5"], ["navgraph.", "at most 1048576"]),
        (["deploy", "init-certs", "--robots", "r1,../base"], ["robot name", "'../base'"]),
        (["deploy", "acl", "--robots", "r1/**"], ["robot name", "'r1/**'"]),
    ],
)
def test_a_bad_name_or_number_is_one_line_and_exit_2_with_nothing_left(tmp_path, args, words):
    if args[0] in ("up", "replay", "ros2"):
        args = [*args, "--run-dir", str(tmp_path / "run"), *_no_router_args()]
    if args[0] == "deploy" and args[1] == "init-certs":
        args = [*args, "--out", str(tmp_path / "certs")]
    r, took, left = smana_alone(tmp_path, *args)
    one_line_misuse(r, args[0], *words)
    assert took < 10.0, took
    assert not left, left
    assert not (tmp_path / "run").exists() and not (tmp_path / "certs").exists()


def test_check_name_is_the_one_rule():
    from smana.common.keys import check_name, check_robot

    for good in ("r1", "robot_2", "a-b", "X" * 32, "_", "0"):
        assert check_name(good) == good == check_robot(good)
    for bad in ("", "a/b", "a*", "$x", "a?", "#", "a@b", "a.b", "a b", "x" * 33, "é", None, 7):
        with pytest.raises(ValueError, match="must match"):
            check_name(bad)


def test_eval_of_a_run_without_a_simulator_needs_gt(tmp_path):
    """A run with the simulator off has no world to score against: `smana eval map` says so in
    one line instead of scoring the map against the default simulated garden."""
    import numpy as np

    from smana.common.config import SmanaConfig
    from smana.services.mapper.voxel_ply import write_ply

    run = tmp_path / "run"
    SmanaConfig.load(None, ["deploy.sim.enabled=false"]).write(run / "config.toml")
    pts = np.zeros((4, 3), np.float32)
    write_ply(
        run / "map.ply",
        pts,
        np.zeros((4, 3), np.uint8),
        np.ones(4, np.uint16),
        np.ones(4, np.float32),
    )
    r, took, left = smana_alone(tmp_path, "eval", "map", str(run))
    one_line_misuse(r, "eval", "no ground truth", "simulator was off", "--gt FILE")
    assert not (run / "gt.ply").exists() and not left


def test_a_start_that_fails_halfway_leaves_nothing_running(tmp_path):
    """The supervisor's start fails after it started a service (here the navgraph's log cannot
    be opened): it stops what it started and exits, instead of hanging with an orphan."""
    run = tmp_path / "run"
    (run / "logs" / "navgraph.log").mkdir(parents=True)
    args = ["up", "--only", "planner,navgraph", "--run-dir", str(run), *_no_router_args()]
    r, took, left = smana_alone(tmp_path, *args, timeout_s=20.0)
    assert r.returncode != 0 and "navgraph.log" in r.stderr, r.stderr
    assert not left, left
    print(f"a failed start ended in {took:.1f} s")


# -- the catching itself -------------------------------------------------------------------------


def test_run_command_one_line_for_user_errors_and_tracebacks_for_bugs(capsys):
    def bad_config(argv):
        raise ConfigError("mapper.x: expected\na number")

    def bad_usage(argv):
        raise UsageError("--run-dir x is a file")

    assert run_command("mapper", bad_config) == 2
    assert capsys.readouterr().err == "smana mapper: mapper.x: expected a number\n"
    assert run_command("up", bad_usage) == 2
    assert capsys.readouterr().err == "smana up: --run-dir x is a file\n"

    def bug(argv):
        return {}["missing"]

    with pytest.raises(KeyError):  # a bug is not misuse: its traceback stays
        run_command("mapper", bug)


def test_explain_open_error_for_messages_not_easily_provoked():
    import zenoh

    from smana.common.zenoh_config import explain_open_error

    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", '["tcp/10.255.255.1:7447", "tls/127.0.0.1:7448"]')
    conf.insert_json5("connect/endpoints", '["tls/127.0.0.1:7449"]')
    src = " at /root/.cargo/git/checkouts/zenoh/io/zenoh-link-commons/src/tcp.rs:61."
    msg = explain_open_error(
        "Can not create a new TCP listener bound to tcp/10.255.255.1:7447: "
        f"[10.255.255.1:7447: Cannot assign requested address (os error 99)"
        f"{src}]{src}",
        conf,
    )
    assert msg.startswith("cannot listen on tcp/10.255.255.1:7447: no network interface")
    msg = explain_open_error(
        f"Unable to connect to any of [Single(tls/127.0.0.1:7449)]! {src}", conf
    )
    assert "tls/127.0.0.1:7449" in msg and "certificate or credentials" in msg
    msg = explain_open_error(
        "Cannot create a new TLS listener on 127.0.0.1:7448. Invalid TLS "
        f"private key file: No such file or directory (os error 2){src}"
        f"{src}",
        conf,
    )
    assert msg == (
        "cannot open the zenoh session: Cannot create a new TLS listener on "
        "127.0.0.1:7448. Invalid TLS private key file: No such file or directory "
        "(os error 2)"
    )


def test_a_taken_listen_port_is_found_before_zenoh_opens(taken_port):
    """The taken port is found by a bind of our own, before zenoh starts a runtime whose threads
    can abort the process; a free port and other protocols pass to zenoh."""
    import json

    import zenoh

    from smana.common.zenoh_config import taken_listen_endpoint

    def conf(*endpoints):
        c = zenoh.Config()
        c.insert_json5("listen/endpoints", json.dumps(list(endpoints)))
        return c

    taken = f"tcp/127.0.0.1:{taken_port}"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    assert taken_listen_endpoint(conf(free, taken)) == taken
    assert taken_listen_endpoint(conf(free)) is None
    assert taken_listen_endpoint(conf(f"udp/127.0.0.1:{taken_port}", "tcp/127.0.0.1:0")) is None
