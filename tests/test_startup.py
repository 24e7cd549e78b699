"""Start-up off the critical path: a service whose kernels compile in the background is live
meanwhile, says so in its status, answers its status while a handler waits for a kernel, and
handles what waited once they are loaded; `SMANA_KERNELS=foreground` keeps the old order.
`smana warmup` compiles the kernels in one process; `smana bench startup --quick` runs and prints
its rows (no timing asserted)."""

from __future__ import annotations

import threading

import pytest

from smana.common import keys
from smana.common.cli import config_from_args, make_parser
from smana.common.messages import ServiceStatus
from smana.common.query import request
from smana.common.service import KERNELS_ENV, Service
from tests.conftest import wait_for

GATE = threading.Event()  # set: the "kernels" are compiled


class SlowKernels(Service):
    """prepare() stands for a cold numba compile; `use` for a handler calling a kernel (which
    waits for numba's compile lock: here, for the gate)."""

    name = "slowk"
    prepare_in_background = True

    def prepare(self) -> None:
        GATE.wait(30)

    def setup(self) -> None:
        self.queryable(keys.key(self.robot, "slowk", "use"), self.on_use)

    def on_use(self, req):
        GATE.wait(30)
        return {"ok": True}


def slowk_cli(argv=None) -> int:
    args = make_parser("slowk", "test").parse_args(argv)
    return SlowKernels(config_from_args(args)).run()


def status(stack) -> ServiceStatus:
    st = request(stack.session, keys.status(stack.robot, "slowk"), timeout_s=5)
    assert isinstance(st, ServiceStatus)
    return st


def test_live_while_kernels_compile_then_ready(fake_stack, monkeypatch):
    monkeypatch.delenv(KERNELS_ENV, raising=False)
    GATE.clear()
    try:
        run = fake_stack.start("slowk", slowk_cli, "--robot", fake_stack.robot)
        fake_stack.wait_alive("slowk", timeout_s=10)  # live with the kernels not compiled
        st = status(fake_stack)
        assert st.state == "running" and st.details["kernels"] == "compiling"
        assert "kernels" in st.details["startup_step"] and st.books_add_up()
        # a query that needs a kernel waits for it, on the main loop ...
        answers = []
        asker = threading.Thread(
            target=lambda: answers.append(
                request(fake_stack.session, keys.key(fake_stack.robot, "slowk", "use"), None, 20)
            )
        )
        asker.start()
        assert wait_for(lambda: run.service.books.in_flight == 1, 5)
        # ... while the status is still answered (from the zenoh callback)
        assert status(fake_stack).details["kernels"] == "compiling"
        GATE.set()
        asker.join(20)
        assert answers == [{"ok": True}]
        assert wait_for(lambda: status(fake_stack).details.get("kernels") == "ready", 5)
        st = status(fake_stack)
        assert st.details["kernels_s"] >= st.details["ready_s"] and st.books_add_up()
        assert fake_stack.stop(run) == 0
    finally:
        GATE.set()


def test_foreground_kernels_before_live(fake_stack, monkeypatch):
    monkeypatch.setenv(KERNELS_ENV, "foreground")
    GATE.clear()
    try:
        run = fake_stack.start("slowk", slowk_cli, "--robot", fake_stack.robot)
        assert wait_for(lambda: status(fake_stack).state == "starting", 10)
        assert not list(fake_stack.session.liveliness().get(keys.alive("test", "slowk")))
        GATE.set()
        fake_stack.wait_alive("slowk", timeout_s=10)
        assert status(fake_stack).details["kernels"] == "ready"
        assert fake_stack.stop(run) == 0
    finally:
        GATE.set()


def test_warmup_compiles_a_services_kernels(capsys):
    from smana.deploy.warmup import cli

    assert cli(["--services", "navgraph", "--profile"]) == 0
    out = capsys.readouterr().out
    assert "[1/1] navgraph  kernels ready in" in out and "smana warmup: done" in out


def test_warmup_misuse():
    from smana.deploy.warmup import cli

    with pytest.raises(SystemExit) as exc:
        cli(["--services", "sim"])
    assert exc.value.code == 2


@pytest.mark.multiprocess
@pytest.mark.slow
def test_bench_startup_quick(capsys):
    from smana.lab.bench.startup import cli

    assert cli(["--quick"]) == 0
    out = capsys.readouterr().out
    for start in ("cold", "warm", "kill"):
        assert f"{start:<6}navgraph" in out
    assert "live ratio" in out and "load average" in out and "CPU" in out
