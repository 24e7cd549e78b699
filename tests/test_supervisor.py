"""The supervisor: restart after kill -9 within 3 s, restart caps, health, clean stop; the CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from smana.common.config import ServiceDeployConfig, SmanaConfig
from smana.deploy.supervisor import Supervisor
from tests.conftest import wait_for

pytestmark = pytest.mark.multiprocess

ECHO = str(Path(__file__).parent / "support" / "echo_service.py")


def make_supervisor(tmp_path, port, **policy):
    cfg = SmanaConfig.load(
        None,
        [
            f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
            "general.robot=sv",
            "general.status_period_s=0.5",
        ],
    )
    sup = Supervisor(cfg, tmp_path / "run", services=[])
    argv = [sys.executable, ECHO, "--config", str(sup.config_path)]
    sup.add("echo", argv, ServiceDeployConfig(**policy))
    return sup


def run_in_thread(sup):
    t = threading.Thread(target=sup.run, kwargs={"progress_period_s": 3600}, daemon=True)
    t.start()
    return t


def test_kill9_is_restarted_within_3s(tmp_path):
    from tests.conftest import free_port

    sup = make_supervisor(tmp_path, free_port(), restart="on-failure", restart_delay_s=0.2)
    t = run_in_thread(sup)
    try:
        echo = sup.procs["echo"]
        assert wait_for(lambda: echo.alive, 30), (tmp_path / "run/logs/echo.log").read_text()
        pid = echo.proc.pid
        os.kill(pid, signal.SIGKILL)
        t0 = time.monotonic()
        assert wait_for(lambda: echo.proc is not None and echo.proc.pid != pid and echo.alive, 10)
        assert time.monotonic() - t0 < 3.0, "restart took too long"
        assert echo.exit_codes == [-signal.SIGKILL]
        assert (tmp_path / "run" / "config.toml").exists()
    finally:
        sup.stop()
        t.join(15)
    assert not t.is_alive()
    assert echo.proc is None and echo.exit_codes[-1] == 0  # stopped cleanly by SIGINT
    # back within 3 s, and still a warning of the run: one line, the status and the time back
    crashes = [w for w in sup.warnings() if w.startswith("echo crashed")]
    assert len(crashes) == 1, sup.warnings()
    assert "exit status -9; restarted, ready" in crashes[0], crashes


def test_a_service_that_refuses_its_config_stops_the_stack(tmp_path):
    """Exit status 2 is a service's "this configuration cannot work" (one line on stderr): it is
    not restarted, the stack stops at once and the run returns 2 with that line."""
    from tests.conftest import free_port

    sup = make_supervisor(tmp_path, free_port(), restart="on-failure", restart_delay_s=0.2)
    refuse = "import sys; print('smana echo: needs X: pip install smana[x]', file=sys.stderr); "
    argv = [sys.executable, "-c", refuse + "sys.exit(2)"]
    sup.add("refuser", argv, ServiceDeployConfig(restart="on-failure", restart_delay_s=0.2))
    t0 = time.monotonic()
    code = sup.run(progress_period_s=3600)
    assert code == 2
    assert time.monotonic() - t0 < 30
    refuser = sup.procs["refuser"]
    assert refuser.exit_codes == [2] and refuser.n_restarts == 0
    assert (
        sup.config_error
        == "refuser refused its configuration: smana echo: needs X: pip install smana[x]"
    )
    assert all(m.proc is None for m in sup.procs.values())  # the echo service was stopped too


def test_crash_loop_goes_on_and_never_policy_says_so(tmp_path):
    from tests.conftest import free_port

    sup = make_supervisor(tmp_path, free_port(), restart="never")
    t = run_in_thread(sup)
    try:
        echo = sup.procs["echo"]
        assert wait_for(lambda: echo.alive, 30)
        os.kill(echo.proc.pid, signal.SIGKILL)
        assert wait_for(lambda: echo.finished, 5)
        assert echo.proc is None and len(echo.exit_codes) == 1
    finally:
        sup.stop()
        t.join(15)
    assert any("echo exited with status -9 and was not restarted" in w for w in sup.warnings())

    # Past max_restarts in the window the service is in a crash loop: still restarted (never
    # given up), and the run says so.
    sup = make_supervisor(
        tmp_path,
        free_port(),
        restart="always",
        restart_delay_s=0.05,
        restart_max_delay_s=0.5,
        max_restarts=2,
        restart_window_s=60,
    )
    t = run_in_thread(sup)
    try:
        echo = sup.procs["echo"]
        for _ in range(4):
            assert wait_for(lambda: echo.proc is not None and echo.alive, 30)
            os.kill(echo.proc.pid, signal.SIGKILL)
            assert wait_for(lambda: echo.proc is None or not echo.alive, 5)
        assert wait_for(lambda: echo.crash_looped and echo.alive, 30)  # back, once more
        assert len(echo.exit_codes) == 4 and echo.n_restarts == 4
    finally:
        sup.stop()
        t.join(15)
    assert any("echo kept crashing" in w for w in sup.warnings()), sup.warnings()


def test_cli_help_lists_every_command():
    out = subprocess.run(
        [sys.executable, "-m", "smana.deploy", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for cmd in ("up", "status", "sim", "mapper", "navgraph", "planner", "explorer", "bench"):
        assert f"\n  {cmd} " in out
    bad = subprocess.run(
        [sys.executable, "-m", "smana.deploy", "nonsense"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "unknown command" in bad.stderr


def test_bad_config_is_a_clear_error(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[mapper]\nresolution_m = -1\n")
    r = subprocess.run(
        [sys.executable, "-m", "smana.deploy", "status", "--config", str(cfg)],
        capture_output=True,
        text=True,
    )
    assert r.returncode != 0
    assert "mapper.resolution_m: expected a number > 0" in r.stderr


def test_smana_up_restarts_a_killed_service_and_dies_cleanly(tmp_path):
    import zenoh

    from smana.common import keys
    from smana.common.config import ZenohConfig
    from smana.common.messages import ServiceStatus
    from smana.common.query import QueryError, request
    from smana.common.zenoh_config import make_zenoh_config
    from tests.conftest import free_port

    port = free_port()
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "smana.deploy",
            "up",
            "--only",
            "navgraph,planner",
            "--robot",
            "up",
            "--run-dir",
            str(tmp_path / "run"),
            "--set",
            f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
            "--set",
            "deploy.planner.restart_delay_s=0.2",
        ],
        stdout=open(tmp_path / "up.log", "wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )

    def planner_pid(session):
        try:
            st = request(session, keys.status("up", "planner"), timeout_s=1)
        except QueryError:
            return None
        return st.pid if isinstance(st, ServiceStatus) else None

    def planner_processes() -> set[int]:
        pids = set()
        for d in os.listdir("/proc"):
            try:
                cmd = open(f"/proc/{d}/cmdline", "rb").read().split(b"\0")
            except (OSError, ValueError):
                continue
            if b"smana.services.planner" in cmd and str(tmp_path).encode() in b" ".join(cmd):
                pids.add(int(d))
        return pids

    def gone(pid: int) -> bool:
        """Exited: no process, or a zombie (an orphan's exit status waits for init to reap)."""
        try:
            return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] in "ZX"
        except OSError:
            return True

    # the router is up when smana up says so (never a fixed wait: at load 10 a second was short)
    assert wait_for(lambda: "zenoh router listening" in (tmp_path / "up.log").read_text(), 60), (
        tmp_path / "up.log"
    ).read_text()
    conf = make_zenoh_config(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        with zenoh.open(conf) as session:
            assert wait_for(lambda: planner_pid(session), 60), (tmp_path / "up.log").read_text()
            first = planner_pid(session)
            os.kill(first, signal.SIGKILL)
            # Restarted: a new planner process exists within 3 s...
            assert wait_for(lambda: planner_processes() - {first}, 3.0), "no restart within 3 s"
            # ...and is healthy again soon after (imports and kernels take their time).
            assert wait_for(lambda: planner_pid(session) not in (None, first), 20)
            second = planner_pid(session)
            # The supervisor itself killed with -9: its services (and their standby processes)
            # must not outlive it.
            os.kill(up.pid, signal.SIGKILL)
            up.wait()
            assert wait_for(lambda: gone(second), 10), (
                tmp_path / "run" / "logs" / "planner.log"
            ).read_text()[-3000:]
            assert wait_for(lambda: all(gone(p) for p in planner_processes()), 10)
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
    log = (tmp_path / "up.log").read_text()
    assert "planner exited with status -9; restarting" in log


def test_one_instance_per_robot(tmp_path):
    """deploy.robots: the multi-robot base runs each service once per robot namespace."""
    from tests.conftest import free_port

    cfg = SmanaConfig.load(
        None,
        [
            f'deploy.router_listen=["tcp/127.0.0.1:{free_port()}"]',
            'deploy.robots=["ra", "rb"]',
        ],
    )
    sup = Supervisor(cfg, tmp_path / "run", services=["planner"])
    assert set(sup.procs) == {"planner@ra", "planner@rb"}
    t = run_in_thread(sup)
    try:
        assert wait_for(lambda: all(m.alive for m in sup.procs.values()), 60), [
            (tmp_path / "run" / "logs" / f"{n}.log").read_text() for n in sup.procs
        ]
        assert {(m.robot, m.service) for m in sup.procs.values()} == {
            ("ra", "planner"),
            ("rb", "planner"),
        }
    finally:
        sup.stop()
        t.join(15)


def test_a_process_the_supervisor_kills_is_a_warning_that_says_why(tmp_path):
    from tests.conftest import free_port

    sup = make_supervisor(tmp_path, free_port(), restart="on-failure")
    sup.config.deploy.health_timeout_s = 1.0  # a process with no token at all: killed soon
    mute = [sys.executable, "-c", "import time; time.sleep(60)"]
    sup.add("mute", mute, ServiceDeployConfig(restart="on-failure", restart_delay_s=30))
    t = run_in_thread(sup)
    try:
        assert wait_for(lambda: sup.procs["mute"].crashes, 30)
    finally:
        sup.stop()
        t.join(15)
    lines = [w for w in sup.warnings() if w.startswith("mute was")]
    assert len(lines) == 1 and lines[0].startswith(
        "mute was killed by the supervisor (no sign of life after its start) "
    ), lines
    assert "exit status -9; not ready again before the run ended" in lines[0], lines
