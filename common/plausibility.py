"""Is an input plausible? Checks a service makes before a message may change its state.

The codec (`messages.py`) refuses what no robot can produce (NaN, coordinates beyond 1000 km,
stamps beyond the year 2286). What is left here needs the stream's history:

- `StampGate`: a stamp must lie within `window_s` of its stream's clock. The clock is the newest
  accepted stamp; it may advance at most `max_rate` seconds of stream time per wall second (a
  simulator at its real-time factor, a lockstep replay faster than the recording). It is set by
  agreement, never by one message: it locks once `agree` consecutive stamps are consistent with
  each other, and moves to a new clock (a restarted simulator, a new dataset) only when `relock`
  consecutive stamps agree with each other and not with it.
- `PoseGate`: a pose may not be further from the last accepted one than the robot can travel in
  the time between their stamps (`max_speed_mps`, plus `slack_m` for localisation noise); it
  relocks the same way (a robot respawned or relocalised).
- `SequenceFollower`: a numbered stream (MapDelta from the mapper, GraphPatch from navgraph) is
  followed per producer session. A message from another producer, a sequence number that goes
  back or jumps far ahead asks for a resync from the producer's snapshot instead of being
  applied, so a spoofed or stale number can neither freeze nor wipe a consumer's state.

Each check returns a verdict and never raises; services turn refusals into `Reject`s (counted by
kind). No zenoh here: the gates are tested in-process against their rules.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

# -- stamps --------------------------------------------------------------------------------------


@dataclass
class Verdict:
    ok: bool
    reason: str = ""  # why not
    reset: bool = False  # accepted, and the gate moved to a new clock / place with it
    kind: str = ""  # why not, as the rejection kind services count: `settling` while a clock or
    # place is being established, `stamp` or `pose_jump` against an established one


class _AgreementGate:
    """What both gates share: a reference (a stream's clock, a robot's place) set once `agree`
    consecutive items are consistent with each other, then moved only by `relock` consecutive
    items consistent with each other and not with it. Subclasses say what consistent means."""

    def __init__(self, agree: int, relock: int, accept_while_acquiring: bool):
        self.agree, self.relock = agree, relock
        self.accept_while_acquiring = accept_while_acquiring
        self.locked = False
        self.ref: tuple | None = None
        self._candidates: deque[tuple] = deque(maxlen=max(agree, relock))
        self.resets = 0

    def _consistent(self, a: tuple, b: tuple) -> bool:
        raise NotImplementedError

    def _fits(self, item: tuple) -> bool:
        """Is `item` consistent with the established reference?"""
        return self._consistent(self.ref, item)

    def _advance(self, item: tuple) -> None:
        """An accepted item moves the reference."""
        self.ref = item

    def _lock(self, item: tuple) -> None:
        self.ref = item

    def _all_consistent(self, items) -> bool:
        items = list(items)
        return all(self._consistent(a, b) for a, b in zip(items, items[1:]))

    def _judge(self, item: tuple, settling: str) -> Verdict | None:
        """The verdict on `item`, or None for an outlier of an established reference (the
        subclass says why). `settling` says what is not yet established."""
        if not self.locked:
            self._candidates.append(item)
            recent = list(self._candidates)[-self.agree :]
            if len(recent) >= self.agree and self._all_consistent(recent):
                self.locked = True
                self._lock(item)
                self._candidates.clear()
                return Verdict(True)
            if self.accept_while_acquiring:
                return Verdict(True)
            return Verdict(
                False, f"{settling} not yet established ({len(recent)} messages)", kind="settling"
            )
        if self._fits(item):
            self._advance(item)
            self._candidates.clear()
            return Verdict(True)
        # An outlier, or the first items of a new clock or place (a restarted simulator).
        self._candidates.append(item)
        if len(self._candidates) >= self.relock and self._all_consistent(self._candidates):
            self._lock(item)
            self._candidates.clear()
            self.resets += 1
            return Verdict(True, reset=True)
        return None


class StampGate(_AgreementGate):
    """Plausibility of one stream's stamps (see the module docstring). The reference is the
    newest accepted stamp and the wall time it came; the clock's upper bound rises with wall time
    at `max_rate` from where the clock was set (locked), so that a burst of stamps each just
    inside the window cannot walk the clock ahead."""

    def __init__(
        self,
        window_s: float = 5.0,
        max_rate: float = 100.0,
        agree: int = 3,
        relock: int = 5,
        accept_while_acquiring: bool = True,
        clock=time.monotonic,
    ):
        super().__init__(agree, relock, accept_while_acquiring)
        self.window_s, self.max_rate = window_s, max_rate
        self._wall = clock
        self._envelope = (0.0, 0.0)  # (stream time, wall time) the upper bound rises from

    @property
    def t(self) -> float | None:
        """The stream's clock."""
        return None if self.ref is None else self.ref[0]

    @property
    def t_wall(self) -> float:
        return 0.0 if self.ref is None else self.ref[1]

    def _consistent(self, a: tuple, b: tuple) -> bool:
        """Could stamp b (at wall time b) follow stamp a on one clock?"""
        (ta, wa), (tb, wb) = a, b
        return ta - self.window_s <= tb <= ta + self.window_s + self.max_rate * max(0.0, wb - wa)

    def _high(self, now: float) -> float:
        """The latest the stream's clock can plausibly be at wall time `now`: it rises at
        `max_rate` from where it was set, whatever the messages since said."""
        t0, w0 = self._envelope
        return t0 + self.max_rate * max(0.0, now - w0)

    def _fits(self, item: tuple) -> bool:
        t, now = item
        return self.ref[0] - self.window_s <= t <= self._high(now) + self.window_s

    def _lock(self, item: tuple) -> None:
        self.ref = self._envelope = item

    def _advance(self, item: tuple) -> None:
        if item[0] > self.ref[0]:
            self.ref = item

    def check(self, stamp_s: float) -> Verdict:
        now = self._wall()
        item = (float(stamp_s), now)
        if not math.isfinite(item[0]):
            return Verdict(False, "stamp is not finite", kind="stamp")
        verdict = self._judge(item, "stream clock")
        if verdict is not None:
            return verdict
        return Verdict(
            False,
            f"stamp {item[0]:.6g} s outside [{self.t - self.window_s:.6g}, "
            f"{self._high(now) + self.window_s:.6g}] around the stream's clock",
            kind="stamp",
        )


class PoseGate(_AgreementGate):
    """Plausibility of one pose stream's positions (see the module docstring). The reference is
    the last accepted (stamp, x, y, z)."""

    def __init__(
        self,
        max_speed_mps: float = 3.0,
        slack_m: float = 1.0,
        agree: int = 3,
        relock: int = 5,
    ):
        super().__init__(agree, relock, accept_while_acquiring=False)
        self.max_speed_mps, self.slack_m = max_speed_mps, slack_m

    def _consistent(self, a: tuple, b: tuple) -> bool:
        reach = self.slack_m + self.max_speed_mps * abs(b[0] - a[0])
        return math.dist(a[1:], b[1:]) <= reach

    def check(self, stamp_s: float, xyz) -> Verdict:
        item = (float(stamp_s), float(xyz[0]), float(xyz[1]), float(xyz[2]))
        verdict = self._judge(item, "position")
        if verdict is not None:
            return verdict
        d = math.dist(self.ref[1:], item[1:])
        return Verdict(
            False,
            f"pose jumped {d:.3g} m in {abs(item[0] - self.ref[0]):.3g} s "
            f"(at most {self.slack_m:g} m + {self.max_speed_mps:g} m/s)",
            kind="pose_jump",
        )


# -- numbered streams ----------------------------------------------------------------------------

APPLY = "apply"  # in order (or a small gap, with a resync asked): apply it
COVERED = "covered"  # already in the snapshot we synced from: drop it
# Refusals (a resync is asked), named as the rejection kinds services count them under:
PRODUCER = "producer"  # from another producer than the one followed
SEQUENCE = "sequence"  # gone back, or jumped more than max_jump ahead


class SequenceFollower:
    """Follows one producer's numbered stream. `check(producer, seq)` says what to do with a
    message and changes nothing but `want_resync` (why a resync from the producer's snapshot is
    needed); `advance(producer, seq)` records a message once it was applied, so that one that
    passes here but is refused by a later check (a bad payload) does not move the stream on. The
    caller asks the snapshot and calls `synced` with its producer and sequence number."""

    def __init__(self, max_jump: int = 1000):
        self.max_jump = max_jump
        self.producer: str | None = None
        self.last: int | None = None
        self.synced_seq: int | None = None  # the sequence number of the snapshot synced from
        self.want_resync = ""

    def synced(self, producer: str, seq: int) -> None:
        self.producer, self.last, self.synced_seq = producer, int(seq), int(seq)
        self.want_resync = ""

    def _ask(self, why: str) -> None:
        if not self.want_resync:
            self.want_resync = why

    def check(self, producer: str, seq: int) -> tuple[str, str]:
        """(APPLY | COVERED | PRODUCER | SEQUENCE, why); an APPLY with a why applies across a
        gap."""
        seq = int(seq)
        if self.producer is None:
            # Nothing synced yet (the producer did not answer at start): follow the first
            # producer seen, and ask for its snapshot unless this is the stream's first message.
            if seq != 1:
                self._ask(f"joined {producer[:8]}'s stream at {seq}")
            return APPLY, ""
        if producer != self.producer:
            self._ask(f"a message from producer {producer[:8]!r}, following {self.producer[:8]!r}")
            return PRODUCER, f"from producer {producer[:8]!r}, not {self.producer[:8]!r}"
        if seq <= self.last:
            if self.synced_seq is not None and seq <= self.synced_seq:
                return COVERED, ""
            self._ask(f"sequence went back from {self.last} to {seq}")
            return SEQUENCE, f"sequence number {seq} after {self.last}"
        if seq > self.last + self.max_jump:
            self._ask(f"sequence jumped from {self.last} to {seq}")
            return SEQUENCE, f"sequence number {seq} jumps {seq - self.last} ahead of {self.last}"
        if seq > self.last + 1:
            why = f"{seq - self.last - 1} messages missed before {seq}"
            self._ask(why)
            return APPLY, why
        return APPLY, ""

    def advance(self, producer: str, seq: int) -> None:
        """A message `check` said to apply was applied."""
        if self.producer is None:
            self.producer = producer
        self.last = int(seq)
