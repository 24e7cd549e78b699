"""`smana up` off the happy path, each stack a real one on an isolated loopback router:

- a first start on a fresh install (an empty numba cache) with both cores busy: no service is
  killed for warming up, every one becomes ready, and the robot moves;
- `kill -9` of each service in turn, the robot exploring: each is back, the map resumed with
  every cloud the dead mapper had integrated, and the run completes; each crash is a warning line
  of report.md and of the summary, and `smana up` exits 1;
- a run whose planner is disabled says so: a Warnings section heads report.md and `smana up`
  exits non-zero.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from smana.deploy.supervisor import die_with_parent
from tests.conftest import free_port, wait_for
from tests.test_e2e_explore import small_run_overrides

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

SERVICES = ("sim", "mapper", "navgraph", "planner", "explorer")


class Up:
    """`smana up` as a subprocess, and a zenoh client of its router."""

    def __init__(self, tmp: Path, overrides: list[str], env: dict | None = None, args=()):
        self.port = free_port()
        self.run_dir = tmp / "run"
        self.robot = f"res{os.getpid()}"
        sets = [*small_run_overrides(self.port), f'general.robot="{self.robot}"', *overrides]
        argv = [sys.executable, "-m", "smana.deploy", "up", "--run-dir", str(self.run_dir)]
        argv += list(args)
        for s in sets:
            argv += ["--set", s]
        self.log_path = tmp / "up.log"
        self.proc = subprocess.Popen(
            argv,
            stdout=open(self.log_path, "wb"),
            stderr=subprocess.STDOUT,  # noqa: SIM115
            start_new_session=True,
            env=dict(os.environ, **(env or {})),
            preexec_fn=die_with_parent,
        )
        self._session = None

    @property
    def session(self):
        if self._session is None:
            import zenoh

            from smana.common.config import ZenohConfig
            from smana.common.zenoh_config import make_zenoh_config

            zc = ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{self.port}"])
            assert wait_for(lambda: self.log().count("zenoh router listening") > 0, 60), self.log()
            self._session = zenoh.open(make_zenoh_config(zc))
        return self._session

    def log(self, service: str | None = None) -> str:
        p = self.log_path if service is None else self.run_dir / "logs" / f"{service}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def alive(self, service: str) -> bool:
        from smana.common import keys

        return bool(
            list(self.session.liveliness().get(keys.alive(self.robot, service), timeout=1.0))
        )

    def status(self, service: str):
        from smana.common import keys
        from smana.common.query import QueryError, request

        try:
            return request(self.session, keys.status(self.robot, service), timeout_s=2.0)
        except QueryError:
            return None

    def query(self, service: str, name: str, body=None):
        from smana.common import keys
        from smana.common.query import request

        return request(self.session, keys.query(self.robot, service, name), body, 5.0)

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


def busy_loops(n: int = 2, seconds: float = 600.0) -> list[subprocess.Popen]:
    """Bounded busy loops, one per core: the machine of a fresh install that does other work."""
    code = f"import time\nt = time.time() + {seconds}\nwhile time.time() < t: pass\n"
    return [
        subprocess.Popen([sys.executable, "-c", code], preexec_fn=die_with_parent) for _ in range(n)
    ]


def test_first_start_on_a_cold_cache_and_busy_cores_kills_nothing_and_the_robot_moves(tmp_path):
    hogs = busy_loops()
    up = Up(
        tmp_path,
        ["explorer.time_budget_s=6", "deploy.recorder.enabled=false"],
        env={"NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")},
    )
    seen_starting = set()

    def ready() -> bool:
        # `smana status` sees the services that are still starting or compiling their kernels
        # (live already: they compile on a thread), and what they are doing. Ready once every
        # one is alive and has either been seen at it or is done compiling.
        from smana.deploy.status import collect

        compiling = False
        for row in collect(up.session, up.robot, 1.0):
            details = (row.get("status") or {}).get("details") or {}
            if details.get("startup_step"):
                seen_starting.add(row["service"])
            compiling |= details.get("kernels") not in (None, "ready")
        return all(up.alive(s) for s in SERVICES) and (bool(seen_starting) or not compiling)

    try:
        # (or the stack ended: then something was not ready, and the log says what)
        all_ready = wait_for(lambda: ready() or up.proc.poll() is not None, 900, 0.5)
        for h in hogs:
            h.kill()
        assert all_ready and up.proc.poll() is None, up.log()
        assert seen_starting, "no service was ever seen starting"
        # The robot moves: the explorer reports distance before its budget ends. A 6 s budget
        # leaves most of the garden unseen, which the report calls a failure (under half of the
        # reachable area usable): that warning alone is allowed.
        rc = up.proc.wait(600)
        warnings = [ln for ln in up.log().splitlines() if ln.startswith("  warning:")]
        assert rc in (0, 1) and "did not move" not in up.log(), up.log()
        assert all("as usable" in w for w in warnings) and (rc == 1) == bool(warnings), up.log()
    finally:
        for h in hogs:
            h.kill()
        up.close()
    log = up.log()
    assert "killing it" not in log and "restarting" not in log, log
    for s in SERVICES:
        assert "ready in" in up.log(s), up.log(s)
    state = json.loads((up.run_dir / "explorer" / "state.json").read_text())
    assert state["distance_m"] > 0.2, state
    assert "did not move" not in (up.run_dir / "report.md").read_text()


def test_kill9_of_each_service_comes_back_with_the_map_and_the_run_completes(tmp_path):
    # spares at once (their default wait of 20 s keeps them out of short runs); a budget of 45 s:
    # on a busy machine the waits for five spares ate a budget of 20 s before the first goal
    up = Up(
        tmp_path,
        ["explorer.time_budget_s=45", "deploy.recorder.enabled=false", "deploy.standby_delay_s=0"],
    )
    try:
        assert wait_for(lambda: all(up.alive(s) for s in SERVICES), 600, 0.5), up.log()
        for service in SERVICES:
            # a hot spare takes over when it is ready (it says "standing by" in the log)
            wait_for(lambda s=service: "standing by" in up.log(s), 120, 0.5)
            st = up.status(service)
            assert st is not None, up.log()
            if service == "mapper":
                # mid-stream, no autosave needed: the spare follows the journal
                assert wait_for(lambda: up.query("mapper", "stats")["voxels_occupied"] > 0, 60)
                before = up.query("mapper", "stats")
            t_kill = time.monotonic()
            os.kill(st.pid, signal.SIGKILL)

            def back(s=service, pid=st.pid):
                new = up.status(s)
                return new is not None and new.pid != pid and new.state == "running"

            assert wait_for(back, 120, 0.1), up.log(service)
            print(f"{service} back in {time.monotonic() - t_kill:.2f} s")
            if service == "mapper":
                # every cloud the dead mapper had answered for is in the spare's map (clouds
                # that came after the query may be too); observed voxels never go away
                after = up.query("mapper", "stats")
                print(
                    f"mapper: clouds {before['clouds']} -> {after['clouds']}, occupied "
                    f"{before['voxels_occupied']} -> {after['voxels_occupied']}, observed "
                    f"{before['voxels_observed']} -> {after['voxels_observed']}"
                )
                assert after["clouds"] >= before["clouds"], (before, after, up.log("mapper"))
                assert after["voxels_observed"] >= before["voxels_observed"], (before, after)
                if after["clouds"] == before["clouds"]:
                    assert after["voxels_occupied"] == before["voxels_occupied"], (before, after)
        # a run that recovered from its crashes still fails: each one is a warning
        assert up.proc.wait(600) == 1, up.log()
    finally:
        up.close()
    log = up.log()
    for service in SERVICES:
        assert f"{service} exited with status -9; restarting" in log, log
    report = (up.run_dir / "report.md").read_text()
    warnings = json.loads((up.run_dir / "metrics.json").read_text())["warnings"]
    assert sorted(w.split(" ")[0] for w in warnings) == sorted(SERVICES), warnings
    for w in warnings:
        assert " crashed " in w and "exit status -9; a hot spare took over" in w, warnings
        assert f"- {w}" in report and f"warning: {w}" in log, (report, log)
    metrics = json.loads((up.run_dir / "metrics.json").read_text())
    assert metrics["explorer"]["distance_m"] > 0.2, metrics["explorer"]


def test_a_run_without_its_planner_fails_loudly(tmp_path):
    sets = [
        "explorer.time_budget_s=2",
        "deploy.planner.enabled=false",
        "deploy.recorder.enabled=false",
        "explorer.startup_grace_s=3",
    ]
    up = Up(tmp_path, sets)
    try:
        code = up.proc.wait(600)
    finally:
        up.close()
    log = up.log()
    assert code == 1, log
    report = (up.run_dir / "report.md").read_text()
    assert report.split("\n")[2] == "## Warnings", report
    warnings = json.loads((up.run_dir / "metrics.json").read_text())["warnings"]
    assert any("planner" in w and "never came up" in w for w in warnings), warnings
    assert any("never saw a planner" in w for w in warnings), warnings
    assert any("did not move" in w for w in warnings), warnings
    assert "smana up: FAILED" in log and "warning: the planner" in log, log
