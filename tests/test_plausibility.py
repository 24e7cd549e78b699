"""The plausibility gates (stamps, poses, numbered streams) against their rules, and against slow
obvious references on random streams."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smana.common.plausibility import (
    APPLY,
    COVERED,
    PRODUCER,
    SEQUENCE,
    PoseGate,
    SequenceFollower,
    StampGate,
)


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def fed(gate: StampGate, clock: FakeClock, stamps, dt_wall=0.05):
    out = []
    for s in stamps:
        out.append(gate.check(s))
        clock.t += dt_wall
    return out


def test_a_steady_stream_locks_and_passes():
    clock = FakeClock()
    gate = StampGate(window_s=2.0, max_rate=10.0, clock=clock)
    verdicts = fed(gate, clock, [0.05 * i for i in range(100)])
    assert all(v.ok for v in verdicts) and gate.locked and gate.resets == 0


# the clock stands at ~11 s: far behind, far ahead, and ahead by more than the window allows
@pytest.mark.parametrize("bad", [0.0, -1e9, 1e9, 14.0])
def test_one_wild_stamp_is_refused_and_the_clock_stays(bad):
    clock = FakeClock()
    gate = StampGate(window_s=2.0, max_rate=1.5, clock=clock)
    fed(gate, clock, [10 + 0.05 * i for i in range(20)])
    v = gate.check(bad)
    assert not v.ok and "outside" in v.reason
    assert fed(gate, clock, [11.05, 11.1])[-1].ok
    assert gate.t == pytest.approx(11.1)


def test_no_clock_from_one_message():
    clock = FakeClock()
    gate = StampGate(window_s=1.0, max_rate=2.0, accept_while_acquiring=False, clock=clock)
    v = fed(gate, clock, [1e6, 5.0, 5.05, 5.1])
    assert [x.ok for x in v] == [False, False, False, True]  # three agreeing stamps lock it
    assert gate.t == pytest.approx(5.1)


def test_a_restarted_stream_relocks_after_agreeing_stamps():
    clock = FakeClock()
    gate = StampGate(window_s=1.0, max_rate=2.0, relock=5, clock=clock)
    fed(gate, clock, [300 + 0.05 * i for i in range(10)])
    v = fed(gate, clock, [0.05 * i for i in range(6)])  # a simulator restarted at t = 0
    assert [x.ok for x in v] == [False] * 4 + [True, True]
    assert v[4].reset and gate.resets == 1


def test_interleaved_spoofs_never_relock():
    clock = FakeClock()
    gate = StampGate(window_s=1.0, max_rate=2.0, relock=3, clock=clock)
    fed(gate, clock, [50 + 0.05 * i for i in range(5)])
    for i in range(20):
        assert gate.check(50.3 + 0.05 * i).ok
        assert not gate.check(9000 + i).ok  # consistent spoofs, but never consecutive
        clock.t += 0.05
    assert gate.resets == 0


class ReferenceClock:
    """The rule of a locked StampGate, written out plainly: a stamp is taken when it is no more
    than `window` behind the newest one taken, nor more than `window` ahead of where the clock
    can be: where it was set, plus `rate` times the wall time since."""

    def __init__(self, t, wall, window, rate):
        self.newest, self.t0, self.wall0 = t, t, wall
        self.window, self.rate = window, rate

    def take(self, stamp, now) -> bool:
        high = self.t0 + self.rate * (now - self.wall0)
        ok = self.newest - self.window <= stamp <= high + self.window
        if ok:
            self.newest = max(self.newest, stamp)
        return ok


def test_locked_gate_matches_the_rule_on_random_streams():
    rng = np.random.default_rng(3)
    for _ in range(20):
        clock = FakeClock()
        gate = StampGate(window_s=1.0, max_rate=3.0, relock=10**9, clock=clock)
        fed(gate, clock, [0.0, 0.1, 0.2])
        ref = ReferenceClock(gate.t, gate.t_wall, 1.0, 3.0)
        for _ in range(300):
            clock.t += rng.uniform(0, 0.5)
            stamp = gate.t + rng.normal(0.5, 2.0)
            assert gate.check(stamp).ok == ref.take(stamp, clock.t)


def test_a_burst_of_stamps_just_inside_the_window_cannot_walk_the_clock():
    # each stamp 4.9 s ahead of the last, all at once, the genuine stream in between: this once
    # walked the clock 490 s ahead in no time
    clock = FakeClock()
    gate = StampGate(window_s=5.0, max_rate=1.0, relock=5, clock=clock)
    fed(gate, clock, [10.0, 10.05, 10.1])
    for k in range(1, 100):
        spoof = gate.check(10.1 + 4.9 * k)
        assert spoof.ok == (k == 1)  # the first is inside the window, the rest beyond it
        assert gate.check(10.1 + 0.001 * k).ok  # and the genuine stream goes on
    assert gate.resets == 0


def test_pose_gate_refuses_a_jump_and_follows_driving():
    gate = PoseGate(max_speed_mps=2.0, slack_m=0.5)
    t, x = 0.0, 0.0
    for _ in range(3):
        assert not gate.locked
        gate.check(t, (x, 0, 0))
        t += 0.05
        x += 0.05
    assert gate.locked
    v = gate.check(t, (x + 1000.0, 0, 0))  # a 1 km jump
    assert not v.ok and "jumped" in v.reason
    for _ in range(50):  # 1 m/s is fine
        assert gate.check(t, (x, 0, 0)).ok
        t += 0.05
        x += 0.05


def test_pose_gate_relocks_on_a_respawned_robot():
    gate = PoseGate(max_speed_mps=1.0, slack_m=0.2, relock=4)
    for i in range(5):
        gate.check(0.1 * i, (0.1 * i, 0, 0))
    v = [gate.check(10 + 0.1 * i, (50.0, 50.0, 0)) for i in range(4)]
    assert [x.ok for x in v] == [False, False, False, True] and v[-1].reset


def test_pose_gate_matches_distance_rule():
    rng = np.random.default_rng(1)
    gate = PoseGate(max_speed_mps=1.5, slack_m=0.3, relock=10**9)
    for i in range(3):
        gate.check(0.1 * i, (0, 0, 0))
    for _ in range(300):
        t0, *p0 = gate.ref
        t = t0 + rng.uniform(0, 1)
        p = np.array(p0) + rng.normal(0, 1.0, 3)
        expect = math.dist(p0, p) <= 0.3 + 1.5 * (t - t0)
        assert gate.check(t, p).ok == expect


def follow(f: SequenceFollower, producer: str, seq: int) -> tuple[str, str]:
    """check, and advance when the message is applied (as a service does)."""
    action, why = f.check(producer, seq)
    if action == APPLY:
        f.advance(producer, seq)
    return action, why


def test_sequence_follows_one_producer():
    f = SequenceFollower(max_jump=100)
    assert follow(f, "A", 1) == (APPLY, "")
    assert follow(f, "A", 2) == (APPLY, "")
    action, why = follow(f, "A", 5)  # a gap: applied, resync asked
    assert action == APPLY and "2 messages missed" in why and f.want_resync
    f.synced("A", 7)
    assert follow(f, "A", 6)[0] == COVERED  # in the snapshot
    assert follow(f, "A", 8)[0] == APPLY and not f.want_resync


def test_spoofed_numbers_neither_freeze_nor_wipe():
    f = SequenceFollower(max_jump=1000)
    f.synced("A", 10)
    assert follow(f, "A", 11)[0] == APPLY
    action, _ = follow(f, "A", 2**63 - 1)  # far ahead: refused, the stream goes on
    assert action == SEQUENCE and f.want_resync
    assert follow(f, "A", 12)[0] == APPLY
    assert follow(f, "A", 11)[0] == SEQUENCE  # went back (after the snapshot): refused
    assert follow(f, "B", 1)[0] == PRODUCER  # a stranger, or a restart: resync decides
    f.synced("B", 3)  # the snapshot says B is the producer now (a restarted navgraph)
    assert follow(f, "B", 4)[0] == APPLY
    assert follow(f, "A", 13)[0] == PRODUCER


def test_a_message_refused_after_the_sequence_check_does_not_move_the_stream():
    f = SequenceFollower()
    f.synced("A", 5)
    assert f.check("A", 6)[0] == APPLY  # ...then its payload is refused: no advance
    assert follow(f, "A", 6)[0] == APPLY  # the genuine 6 still applies


def test_joining_mid_stream_asks_for_the_snapshot():
    f = SequenceFollower()
    assert follow(f, "A", 40)[0] == APPLY and "joined" in f.want_resync
