"""Start-up off the critical path: a service whose kernels compile in the background is live
meanwhile and says so in its status; its samples and queries wait in order and are handled once
the kernels are loaded, a query that waited too long gets `warming_up`;
`SMANA_KERNELS=foreground` keeps the old order. `smana warmup` compiles the kernels in one
process; `smana bench startup --quick` runs and prints its rows (no timing asserted)."""

from __future__ import annotations

import threading
import time

import pytest

from smana.common import keys
from smana.common import service as service_module
from smana.common.cli import config_from_args, make_parser
from smana.common.messages import Pose, ServiceStatus, encode
from smana.common.query import QueryError, request
from smana.common.service import KERNELS_ENV, Service
from tests.conftest import wait_for

GATE = threading.Event()  # set: the "kernels" are compiled


class SlowKernels(Service):
    """prepare() stands for a cold numba compile; `use` and `pose` for handlers that call a
    kernel."""

    name = "slowk"
    prepare_in_background = True

    def prepare(self) -> None:
        GATE.wait(30)

    def setup(self) -> None:
        self.seen: list[str] = []
        self.queryable(keys.key(self.robot, "slowk", "use"), lambda req: {"seen": self.seen})
        self.subscribe(keys.key(self.robot, "slowk", "pose"), self.on_pose, Pose)

    def on_pose(self, pose: Pose) -> None:
        assert GATE.is_set(), "a handler ran before the kernels were loaded"
        self.seen.append(pose.frame_id)


def slowk_cli(argv=None) -> int:
    args = make_parser("slowk", "test").parse_args(argv)
    return SlowKernels(config_from_args(args)).run()


def status(stack) -> ServiceStatus | None:
    try:
        st = request(stack.session, keys.status(stack.robot, "slowk"), timeout_s=5)
    except QueryError:
        return None
    assert isinstance(st, ServiceStatus)
    return st


def use(stack):
    return request(stack.session, keys.key(stack.robot, "slowk", "use"), None, 5)


def test_live_while_kernels_compile_then_ready(fake_stack, monkeypatch):
    monkeypatch.delenv(KERNELS_ENV, raising=False)
    GATE.clear()
    try:
        run = fake_stack.start("slowk", slowk_cli, "--robot", fake_stack.robot)
        alive = keys.alive(fake_stack.robot, "slowk")  # live with the kernels not compiled
        assert wait_for(lambda: list(fake_stack.session.liveliness().get(alive)), 10)
        st = status(fake_stack)
        assert st.state == "running" and st.details["kernels"] == "compiling"
        assert "kernels" in st.details["startup_step"] and st.books_add_up()
        # a query waits, then gets a clear answer rather than a timeout
        with pytest.raises(QueryError) as exc:
            use(fake_stack)
        assert exc.value.kind == "warming_up" and "compiling" in str(exc.value)
        # samples wait, in order, for the kernels
        pub = fake_stack.publisher(keys.key(fake_stack.robot, "slowk", "pose"))
        for name in ("a", "b", "c"):
            pub.put(encode(Pose(stamp_s=1.0, frame_id=name)))
        assert wait_for(lambda: status(fake_stack).pending == 3, 5)
        st = status(fake_stack)
        assert st.details["kernels"] == "compiling" and st.books_add_up()
        assert st.dropped == {"warming_up": 1}
        # a query that comes while they compile is answered once they are loaded, in its turn
        monkeypatch.setattr(service_module, "WARMING_UP_HOLD_S", 30.0)  # (a loaded machine)
        answers = []
        asker = threading.Thread(target=lambda: answers.append(use(fake_stack)))
        asker.start()
        assert wait_for(lambda: status(fake_stack).pending == 4, 5)
        GATE.set()
        asker.join(10)
        assert answers == [{"seen": ["a", "b", "c"]}]
        assert wait_for(lambda: status(fake_stack).details.get("kernels") == "ready", 5)
        st = status(fake_stack)
        assert st.details["kernels_s"] >= st.details["ready_s"] and st.books_add_up()
        assert 0 < st.details["ready_cpu_s"] <= time.process_time()
        assert st.rejected == {} and st.pending == 0
        assert fake_stack.stop(run) == 0
    finally:
        GATE.set()


def test_foreground_kernels_before_live(fake_stack, monkeypatch):
    monkeypatch.setenv(KERNELS_ENV, "foreground")
    GATE.clear()
    try:
        run = fake_stack.start("slowk", slowk_cli, "--robot", fake_stack.robot)
        assert wait_for(lambda: (status(fake_stack) or ServiceStatus()).state == "starting", 10)
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

    # The background order only: the foreground one (the order before) doubles the time, and
    # the comparison is the full run's (docs/benchmarks.md).
    assert cli(["--quick", "--only", "background"]) == 0
    out = capsys.readouterr().out
    for start in ("cold", "warm", "kill"):
        assert f"{start:<6}navgraph" in out
    assert "back live s" in out and "load average" in out and "CPU" in out
    # the CPU each start spent to get live, and what that bounds on this machine's cores
    assert "back cpu s" in out and "background warm: all 1 live in" in out
    assert "s of CPU to get there" in out
