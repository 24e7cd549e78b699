"""Take-overs of the explorer while a goal it was sent runs: each new explorer ends that goal at
once, and the goal's sender hears it.

Explorer processes on an isolated loopback router (tests/conftest.py), each started as a hot
spare the way `smana up` starts one, all with the same run directory (a take-over reads the last
process's state.json there); a stub planner and a stub robot (tests/test_explorer_service.py)
stand in for the rest. Four times: a goal is sent over `explorer/goal` and accepted, the robot
drives towards it, the explorer is killed (SIGKILL) once its checkpoint names the goal, and a
spare takes over. The new explorer's first feedback ends the goal "aborted" ("the explorer
restarted", error "stopped"), the robot stops, and the next goal is taken as usual."""

from __future__ import annotations

import json

import pytest

from smana.common import keys
from smana.common.messages import encode
from tests.conftest import wait_for
from tests.support.hot_spare import HotSpare, SpareChain
from tests.test_explorer_goals import Feedback, goal
from tests.test_explorer_service import BOUNDS, StubRobot, patch, stub_planner

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

GOALS = [(6.0, 4.0), (1.5, 6.5), (6.0, 1.5), (1.5, 1.5)]


def test_each_new_explorer_ends_the_goal_it_inherits_and_its_sender_hears_it(zenoh_stack):
    stack, s, robot = zenoh_stack, zenoh_stack.session, zenoh_stack.robot
    run_dir = stack.tmp / "run"
    args = [
        *BOUNDS,
        "--set",
        "explorer.control_rate_hz=20",
        "--set",
        'explorer.mode="navigate"',
        "--set",
        f'general.run_dir="{run_dir}"',
    ]
    planner, token = stub_planner(s, robot, [])
    bot = StubRobot(s, robot)
    chain = SpareChain(lambda: HotSpare(stack, "explorer", args))
    try:
        fb = Feedback(stack)
        chain.spare()
        chain.take_over()
        chain.wait_running()
        for k, (x, y) in enumerate(GOALS):
            chain.spare()  # the next one prepares while this one drives
            s.put(keys.graph_patch(robot), encode(patch(8.0)))  # all of 8 m x 8 m known terrain
            gid = f"goal{k}"
            r = goal(s, robot, x=x, y=y, id=gid)
            assert r["accepted"], r
            assert wait_for(lambda: abs(bot.v) > 0 or abs(bot.w) > 0, 20), chain.active.log()

            def checkpointed(g=gid) -> bool:
                try:
                    state = json.loads((run_dir / "explorer" / "state.json").read_text())
                except (OSError, ValueError):
                    return False
                return (state.get("goal") or {}).get("navigate") == g

            assert wait_for(checkpointed, 20, 0.05)
            chain.active.kill()
            chain.take_over()
            chain.wait_running()
            # the sender hears the goal end, from the new process
            assert wait_for(lambda g=gid: fb.reached(g, "aborted"), 20), fb.states(gid)
            last = fb.of(gid)[-1][1]
            assert last["error"] == "stopped" and "restarted" in last["reason"], last
            # and the robot drives to it no more
            assert wait_for(lambda: bot.v == 0.0 and bot.w == 0.0, 10)
            print(f"take-over {k + 1}: goal {gid} ended for its sender: {last['reason']}")
    finally:
        for sp in chain.spares:
            sp.kill()
        if chain.active is not None:
            chain.active.kill()
        bot.close()
        planner.undeclare()
        token.undeclare()
