"""Small inputs that were accepted, or crashed as `internal`, and are now refused in one line or
handled: JSON integers past 1e308 in a goal or a claim, an absurd yaw or tolerance, a broken pipe
under `| head`, empty name lists, and counters bumped by worker threads."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from smana.common import keys
from smana.common.service import Reject
from smana.services.explorer.navigation import GoalRefused, parse_goal
from tests.conftest import REPO

HUGE = 10**400  # what json.loads makes of a 401-digit integer


def _goal(**body):
    return parse_goal({"x": 1.0, "y": 1.0, **body}, (-10.0, -10.0), (10.0, 10.0), 0.2, 5.0)


@pytest.mark.parametrize(
    "body",
    [
        {"x": HUGE},
        {"y": -HUGE},
        {"yaw": HUGE},
        {"tolerance_m": HUGE},
        {"yaw": 1e308},
        {"yaw": -101.0},
        {"tolerance_m": 5e-324},
        {"tolerance_m": 0.0009},
    ],
)
def test_a_goal_with_a_huge_or_absurd_number_is_refused_as_a_value(body):
    with pytest.raises(GoalRefused) as err:
        _goal(**body)
    assert err.value.kind in ("value", "out_of_bounds"), err.value
    assert len(str(err.value)) < 200


def test_a_sane_goal_still_passes():
    g = _goal(yaw=6.5, tolerance_m=0.001)
    assert g.tolerance_m == 0.001 and abs(g.yaw) <= 3.15
    assert _goal(yaw=None).yaw is None


def test_a_claim_with_a_huge_integer_is_a_value_refusal_not_internal():
    from tests.test_fuzz_coordinator import _Req, coordinator

    s = coordinator()
    member = s.book.members[0]
    for goal in ([HUGE, 1.0], [1.0, -HUGE]):
        with pytest.raises(Reject) as err:
            s.on_claim(member, _Req({"goal": goal}, keys.claim(s.robot, member)))
        assert err.value.kind == "value"


@pytest.mark.parametrize(
    "argv",
    [["deploy", "acl", "--robots", "r1,r2"], ["world", "info"], ["deploy", "acl"]],
    ids=["deploy-acl", "world-info", "deploy-acl-default"],
)
def test_a_reader_gone_under_a_pipe_is_no_traceback_and_no_error(argv):
    r, w = os.pipe()
    os.close(r)  # `| head -1` that already left: the first write meets a broken pipe
    try:
        done = subprocess.run(
            [sys.executable, "-m", "smana.deploy.cli", *argv],
            stdout=w,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
            timeout=120,
        )
    finally:
        os.close(w)
    assert done.stderr == "" and done.returncode == 1, done.stderr


@pytest.mark.parametrize("robots", ["", " , "])
def test_deploy_acl_and_init_certs_refuse_an_empty_robot_list(robots, tmp_path):
    from smana.deploy.security import cli

    for cmd in (["acl"], ["init-certs", "--out", str(tmp_path / "c")]):
        with pytest.raises(SystemExit) as exc:
            cli([*cmd, "--robots", robots])
        assert exc.value.code == 2
    assert not (tmp_path / "c").exists()


def test_counters_that_workers_bump_are_bumped_under_the_lock():
    from smana.common.config import SmanaConfig
    from tests.support.echo_service import EchoService

    class Spy:
        held = 0

        def __enter__(self):
            Spy.held += 1

        def __exit__(self, *exc):
            return False

    class Query:
        def reply(self, *a, **k):
            pass

    svc = EchoService(SmanaConfig(), 0.0)
    svc._counter_lock = Spy()
    svc.note("x", "a note")
    svc._send_reply(Query(), "k", b"", None)
    assert Spy.held == 2 and svc.events["x"] == 1 and svc.msgs_out == 1


def test_sigterm_to_smana_goto_cancels_its_goal(monkeypatch, capsys):
    # the robot kept driving after `kill <goto>`: only Ctrl-C canceled
    import contextlib
    import signal

    from smana.services.explorer import goto_cli

    asked = []

    class Session:
        def declare_subscriber(self, *a, **k):
            return type("Sub", (), {"undeclare": lambda self: None})()

    def request(session, key, body, timeout_s):
        asked.append(key)
        if key.endswith("goal/cancel"):
            return {"canceled": True}
        return {"accepted": True, "id": "g1"}

    def follow(feedback, gid, timeout_s):
        os.kill(os.getpid(), signal.SIGTERM)  # `kill` while it follows
        raise AssertionError("SIGTERM did not interrupt the goto")

    monkeypatch.setattr(goto_cli, "open_session", lambda z: contextlib.nullcontext(Session()))
    monkeypatch.setattr(goto_cli, "request", request)
    monkeypatch.setattr(goto_cli, "follow", follow)
    before = signal.getsignal(signal.SIGTERM)
    assert goto_cli.cli(["1", "2"]) == 1
    assert asked[-1] == keys.explorer_goal_cancel("r1"), asked
    assert "goal g1: canceled" in capsys.readouterr().out
    assert signal.getsignal(signal.SIGTERM) is before  # the caller's handler is back


@pytest.mark.parametrize("name", ["exploration", "navnoise", "risk"])
def test_an_empty_arms_list_is_refused_not_the_full_default(name, tmp_path, capsys):
    from smana.common.cli import run_command
    from smana.lab.experiments import cli as experiment

    argv = [name, "--quick", "--out", str(tmp_path / "no"), "--arms", ""]
    assert run_command("experiment", experiment, argv) == 2
    assert not (tmp_path / "no").exists()
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--arms" in err, err


def test_bench_scale_refuses_a_planner_box_beyond_memory_in_one_line(capsys):
    from smana.common.cli import run_command
    from smana.lab.bench.scale import cli

    assert run_command("bench scale", cli, ["--planner-box-m", "100000x100000"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "GiB" in err and "Traceback" not in err, err


def test_a_policy_in_the_zenoh_config_file_is_refused_in_one_line(tmp_path):
    # it was applied to every process, clients too: each denied its own traffic, never ready
    from smana.common.config import ConfigError, ZenohConfig
    from smana.common.zenoh_config import make_zenoh_config
    from smana.deploy.acl import acl_policy

    f = tmp_path / "zenoh.json5"
    f.write_text('{"access_control": ' + __import__("json").dumps(acl_policy()) + "}")
    with pytest.raises(ConfigError) as err:
        make_zenoh_config(ZenohConfig(mode="client", config_file=str(f)))
    assert "zenoh.acl_file" in str(err.value) and "\n" not in str(err.value)
    f.write_text('{"access_control": {"enabled": false}}')  # a disabled block is harmless
    make_zenoh_config(ZenohConfig(mode="client", config_file=str(f)))
