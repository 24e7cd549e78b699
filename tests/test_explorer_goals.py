"""Goals sent to the explorer over Zenoh (`explorer/goal`, `goal/cancel`, `goal/feedback`) and
`smana goto`: the explorer's real process on an isolated loopback router, the test standing in for
the robot (integrates cmd_vel, publishes poses), the navgraph (one GraphPatch) and the planner (a
queryable answering straight-line paths), as in test_explorer_service.py. The simulator's closed
loop with every service is test_e2e_goals.py."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import threading
import time

import msgpack
import pytest

from smana.common import keys
from smana.common.messages import ServiceStatus, encode
from smana.common.query import request
from tests.conftest import wait_for
from tests.test_explorer_service import BOUNDS, StubRobot, patch, stub_planner

pytestmark = pytest.mark.multiprocess


class Feedback:
    """Every feedback sample, with the time it arrived."""

    def __init__(self, stack):
        self.items: list[tuple[float, dict]] = []
        self._lock = threading.Lock()
        self.sub = stack.subscriber(keys.explorer_goal_feedback(stack.robot), self._on)

    def _on(self, sample) -> None:
        with self._lock:
            self.items.append((time.monotonic(), msgpack.unpackb(sample.payload.to_bytes())))

    def of(self, gid: str) -> list[tuple[float, dict]]:
        with self._lock:
            return [(t, fb) for t, fb in self.items if fb["id"] == gid]

    def states(self, gid: str) -> list[str]:
        out = []
        for _, fb in self.of(gid):
            if not out or out[-1] != fb["state"]:
                out.append(fb["state"])
        return out

    def reached(self, gid: str, state: str) -> bool:
        return state in self.states(gid)


def status(s, robot) -> ServiceStatus:
    st = request(s, keys.status(robot, "explorer"), timeout_s=5)
    assert isinstance(st, ServiceStatus) and st.books_add_up(), st
    return st


def goal(s, robot, **body) -> dict:
    return request(s, keys.explorer_goal(robot), body, timeout_s=5)


def start_explorer(stack, *args) -> subprocess.Popen:
    proc = stack.service("explorer", *BOUNDS, "--set", "explorer.control_rate_hz=20", *args)
    stack.wait_alive("explorer", timeout_s=120)
    return proc


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def goto(stack, *args) -> subprocess.Popen:
    """`smana goto`, started with SIGINT ignored, as a parent that ignores it would start it:
    Ctrl-C must cancel its goal all the same."""
    return subprocess.Popen(
        [sys.executable, "-m", "smana.services.explorer.goto_cli", *stack.zenoh_args()]
        + ["--robot", stack.robot, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        preexec_fn=_ignore_sigint,
    )


def test_goals_are_checked_preempted_canceled_reached_and_followed_by_smana_goto(zenoh_stack):
    stack, s, robot = zenoh_stack, zenoh_stack.session, zenoh_stack.robot
    planner, token = stub_planner(s, robot, [])
    bot = StubRobot(s, robot)
    procs = []
    try:
        start_explorer(stack, "--set", 'explorer.mode="navigate"')
        s.put(keys.graph_patch(robot), encode(patch(8.0)))  # all of 8 m x 8 m known terrain
        fb = Feedback(stack)
        assert wait_for(lambda: request(s, keys.explorer_state(robot))["pose"] is not None, 10)

        # refused: each one answered, counted, and nothing changes
        refused = {
            "malformed": {"x": "one", "y": 2.0},
            "value": {"x": 1.0, "y": math.nan},
            "out_of_bounds": {"x": 9.0, "y": 2.0},
        }
        for kind, body in refused.items():
            r = goal(s, robot, **body)
            assert r["accepted"] is False and r["reason"], (kind, r)
        r = goal(s, robot, x=5.0, y=4.0, tolerance_m=0.0)
        assert r["accepted"] is False and "tolerance_m" in r["reason"]
        # JSON in, JSON out (any zenoh tool)
        r = request(s, keys.explorer_goal(robot), {"x": 1.0, "y": -1.0}, 5, as_json=True)
        assert r["accepted"] is False and "outside" in r["reason"], r
        raw = s.get(keys.explorer_goal(robot), payload=b"\xc1 not msgpack", timeout=5)
        assert msgpack.unpackb(next(iter(raw)).ok.payload.to_bytes())["accepted"] is False
        # a wildcard selector reaches the goal queryable too: it drives nothing
        wild = s.get(
            f"smana/{robot}/explorer/**", payload=msgpack.packb({"x": 5.0, "y": 4.0}), timeout=5
        )
        answers = [msgpack.unpackb(r.ok.payload.to_bytes()) for r in wild if r.ok is not None]
        mine = [a for a in answers if "reason" in a]  # the goal's and the cancel's replies
        assert len(mine) == 2 and not any(a.get("accepted") or a.get("canceled") for a in mine)
        assert wait_for(lambda: status(s, robot).rejected.get("selector") == 2, 5)
        st = status(s, robot)
        assert st.rejected.get("malformed") == 2 and st.rejected.get("value") == 2, st.rejected
        assert st.rejected.get("out_of_bounds") == 2
        assert request(s, keys.explorer_state(robot))["nav_goal"] is None
        assert bot.max_v == 0.0

        # accepted, then pre-empted by a second one
        r = goal(s, robot, x=6.0, y=4.0, id="first")
        assert r == {"accepted": True, "id": "first", "reason": ""}
        assert wait_for(lambda: bot.x > 1.5, 20), stack.log("explorer")
        r = goal(s, robot, x=3.0, y=6.5, id="second")
        assert r["accepted"] and r["id"] == "second"
        assert wait_for(lambda: fb.reached("first", "preempted"), 5), fb.states("first")
        assert wait_for(lambda: fb.reached("second", "active"), 5)
        state = request(s, keys.explorer_state(robot))
        assert state["nav_goal"]["id"] == "second" and state["mode"] == "navigating"
        assert wait_for(lambda: len(fb.of("second")) >= 6, 10)  # 3 s of feedback at least

        # feedback at >= 1 Hz while the goal runs
        times = [t for t, f in fb.of("second") if f["state"] == "active"]
        gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
        assert max(gaps) <= 1.0, gaps
        last = fb.of("second")[-1][1]
        assert last["goal"] == [3.0, 6.5, None] and last["distance_remaining_m"] > 0

        # a cancel stops the robot at once
        r = request(s, keys.explorer_goal_cancel(robot), {"id": None}, timeout_s=5)
        assert r == {"canceled": True, "id": "second", "reason": ""}
        assert wait_for(lambda: bot.v == 0.0 and bot.w == 0.0, 5.0)
        assert wait_for(lambda: fb.reached("second", "canceled"), 10)
        r = request(s, keys.explorer_goal_cancel(robot), {"id": "second"}, timeout_s=5)
        assert r["canceled"] is False and r["reason"]
        assert request(s, keys.explorer_state(robot))["nav_goal"]["state"] == "canceled"

        # `smana goto`: feedback lines, exit 0 once there
        t0 = time.monotonic()
        p = goto(stack, "5", "2", "--tolerance", "0.3")
        procs.append(p)
        out, _ = p.communicate(timeout=90)
        took_s = time.monotonic() - t0
        assert p.returncode == 0, out + stack.log("explorer")
        assert "accepted" in out and "m to go" in out and "succeeded" in out, out
        lines = [line for line in out.splitlines() if ": active," in line]
        assert 1 <= len(lines) <= took_s + 1, (took_s, out)  # at most a line a second
        assert math.hypot(bot.x - 5.0, bot.y - 2.0) <= 0.3 + 0.05

        # a goal the explorer refuses: one line, exit 1
        p = goto(stack, "50", "2")
        procs.append(p)
        out, _ = p.communicate(timeout=30)
        assert p.returncode == 1 and out.startswith("goal refused") and "outside" in out, out

        # Ctrl-C cancels its goal and exits 1
        p = goto(stack, "1", "6")
        procs.append(p)
        line = p.stdout.readline()
        assert "accepted" in line, line + stack.log("explorer")
        gid = line.split()[1]
        assert wait_for(lambda: bot.v != 0.0 or bot.w != 0.0, 10)
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=20)
        assert p.returncode == 1 and "canceled" in out, out
        assert wait_for(lambda: fb.reached(gid, "canceled"), 10)
        assert wait_for(lambda: bot.v == 0.0 and bot.w == 0.0, 5.0)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        bot.close()
        planner.undeclare()
        token.undeclare()


def test_exploration_pauses_during_a_goal_and_resumes_after_it(zenoh_stack):
    stack, s, robot = zenoh_stack, zenoh_stack.session, zenoh_stack.robot
    planner, token = stub_planner(s, robot, [])
    bot = StubRobot(s, robot)
    try:
        proc = start_explorer(stack)
        s.put(keys.graph_patch(robot), encode(patch(4.0)))  # the frontier: x = 4 m
        fb = Feedback(stack)
        state = lambda: request(s, keys.explorer_state(robot))  # noqa: E731
        assert wait_for(lambda: state()["n_plans"] >= 1 and bot.max_v > 0, 30)
        r = goal(s, robot, x=1.0, y=1.0, tolerance_m=0.3, id="aside")
        assert r["accepted"], r
        during = state()
        assert during["mode"] == "navigating" and during["nav_goal"]["id"] == "aside"
        # no exploration plan while the goal ran: every state that says "navigating" has the
        # count it had when the goal came (once the goal succeeds it may plan again at once)
        seen = []

        def reached() -> bool:
            st = state()
            seen.append((st["mode"], st["n_plans"]))
            return fb.reached("aside", "succeeded")

        assert wait_for(reached, 60), stack.log("explorer")
        navigating = {n for mode, n in seen if mode == "navigating"}
        assert navigating <= {during["n_plans"]}, (during["n_plans"], seen)
        assert math.hypot(bot.x - 1.0, bot.y - 1.0) <= 0.35
        # then it explores again
        assert wait_for(lambda: state()["n_plans"] > during["n_plans"], 10)
        assert state()["exploring"] and state()["nav_goal"]["state"] == "succeeded"
        # an explorer stopped while a goal runs says the goal ends there
        assert goal(s, robot, x=3.0, y=7.0, id="last")["accepted"]
        assert stack.stop(proc) == 0
        assert wait_for(lambda: fb.reached("last", "aborted"), 5), fb.states("last")
        assert "stopped" in fb.of("last")[-1][1]["reason"]
    finally:
        bot.close()
        planner.undeclare()
        token.undeclare()


def test_a_request_keeps_calling_while_waiting_until_the_reply(zenoh_stack):
    """What keeps a goal's feedback at its rate while the planner thinks (common/query.py)."""
    s = zenoh_stack.session

    def slow(query):
        def answer():
            time.sleep(0.4)  # simulated work: a planner thinking
            query.reply(query.key_expr, msgpack.packb({"ok": True}))
            query.drop()

        threading.Thread(target=answer, daemon=True).start()

    q = s.declare_queryable("smana/test/slow/path", slow)
    try:
        calls = []
        t0 = time.monotonic()
        reply = request(s, "smana/test/slow/path", {}, 5.0, while_waiting=lambda: calls.append(1))
        assert reply == {"ok": True} and time.monotonic() - t0 >= 0.4
        assert len(calls) >= 5  # every few tens of ms
    finally:
        q.undeclare()


def test_smana_goto_without_an_explorer_or_without_feedback(zenoh_stack):
    """No explorer answers: one line, exit 2. An explorer that accepts and then says nothing: exit
    1 after --feedback-timeout."""
    stack, s = zenoh_stack, zenoh_stack.session
    p = goto(stack, "1", "2")
    out, _ = p.communicate(timeout=30)
    assert p.returncode == 2 and len(out.strip().splitlines()) == 1, out
    assert "no service answered" in out and "Traceback" not in out

    def mute(query):
        query.reply(query.key_expr, msgpack.packb({"accepted": True, "id": "m", "reason": ""}))

    q = s.declare_queryable(keys.explorer_goal(stack.robot), mute)
    try:
        p = goto(stack, "1", "2", "--feedback-timeout", "1")
        out, _ = p.communicate(timeout=30)
        assert p.returncode == 1 and "no feedback for 1 s" in out, out
    finally:
        q.undeclare()


def test_a_refused_goal_query_ends_at_once_and_echoes_no_oversized_id(zenoh_stack):
    """A goal query the explorer cannot read is answered and ended at once (a querier's get()
    returns, it does not wait for its timeout), counted once; a refusal echoes no invalid id."""
    stack, s, robot = zenoh_stack, zenoh_stack.session, zenoh_stack.robot
    start_explorer(stack, "--set", 'explorer.mode="navigate"')
    unreadable = [
        b"\xc1 not msgpack",
        msgpack.packb([1.0, 2.0]),
        b"\x91" * 100_000 + b"\xc0",  # a deep nest
        b"\xdd\xff\xff\xff\xff",  # an array declaring 4 G items
    ]
    long_id = msgpack.packb({"x": 1.0, "y": 1.0, "id": "a" * 10_240})
    for payload in [*unreadable, long_id]:
        t0 = time.monotonic()
        replies = list(s.get(keys.explorer_goal(robot), payload=payload, timeout=10.0))
        took_s = time.monotonic() - t0
        assert took_s < 3.0, (payload[:20], took_s)  # ended, not timed out
        assert len(replies) == 1 and replies[0].ok is not None, replies
        r = msgpack.unpackb(replies[0].ok.payload.to_bytes())
        assert r["accepted"] is False and r["reason"] and r["id"] == "", r
    st = status(s, robot)
    assert st.rejected.get("malformed") == len(unreadable) + 1, st.rejected
    assert request(s, keys.explorer_state(robot))["nav_goal"] is None
