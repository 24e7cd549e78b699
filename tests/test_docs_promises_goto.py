"""`smana goto --help`'s sentences the process tests (tests/test_explorer_goals.py) leave out:
"Exit status: 0 when the goal is reached (succeeded), 1 when it ends otherwise (aborted,
canceled, preempted)" for every end, and "Prints the goal's feedback, at most a line a second
(distance remaining along the path, an ETA at the speed made so far, time, recoveries), and how
it ended". The follower of the goal's feedback, in process, on feedback put in its queue."""

from __future__ import annotations

import queue

import pytest

from smana.services.explorer.goto_cli import ENDED, follow


def feedback(state: str, remaining: float, t: float, gid: str = "g") -> dict:
    return {
        "id": gid,
        "state": state,
        "distance_remaining_m": remaining,
        "navigation_time_s": t,
        "recoveries": 1,
        "reason": "" if state in ("active", "succeeded") else f"it was {state}",
    }


@pytest.mark.parametrize("end", ENDED)
def test_the_exit_status_is_0_only_when_the_goal_succeeded(end, capsys):
    q: queue.Queue = queue.Queue()
    for item in (
        feedback("active", 4.0, 0.0),
        feedback("active", 9.0, 1.0, gid="another goal's"),  # not followed
        feedback("active", 3.0, 1.0),
        feedback(end, 2.0 if end != "succeeded" else 0.1, 2.0),
    ):
        q.put(item)
    assert follow(q, "g", timeout_s=1.0) == (0 if end == "succeeded" else 1)
    lines = capsys.readouterr().out.splitlines()
    # the first feedback, then (within the same second) only the end, with its reason
    assert len(lines) == 2, lines
    assert lines[0] == "goal g: active, 4.00 m to go, 0.0 s, 1 recoveries"
    assert lines[-1].startswith(f"goal g: {end}, ") and "another" not in "".join(lines)
    if end != "succeeded":
        assert lines[-1].endswith(f"(it was {end})")


def test_a_line_a_second_at_most_with_an_eta_at_the_speed_made_so_far(capsys, monkeypatch):
    from smana.services.explorer import goto_cli

    ticks = [0.0, 0.4, 0.8, 1.2, 1.6, 2.5]  # when each feedback arrives

    def clock() -> float:
        return ticks.pop(0) if len(ticks) > 1 else ticks[0]

    monkeypatch.setattr(goto_cli.time, "monotonic", clock)
    q: queue.Queue = queue.Queue()
    for i, remaining in enumerate((5.0, 4.6, 4.2, 3.8, 3.4)):
        q.put(feedback("active", remaining, 0.4 * i))
    q.put(feedback("succeeded", 0.1, 2.5))
    assert follow(q, "g", timeout_s=1.0) == 0
    lines = capsys.readouterr().out.splitlines()
    # at 0.0 s and 1.2 s (a second after the last line), and the end
    to_go = [line.split(",")[1].strip() for line in lines]
    assert to_go == ["5.00 m to go", "3.80 m to go", "0.10 m to go"]
    # 1.2 m made good in 1.2 s: 3.8 m to go at 1 m/s
    assert "ETA 4 s" in lines[1]
