"""The explorer's two clocks, both kept across restarts (no zenoh): robot time, which runs on
from the poses' stamps across a restarted simulator (its stamps start again), and the wall-time
budget (`explorer.time_budget_s`), spent by the run's earlier processes and by this one since it
had a map, after a start-up whose patience is `explorer.startup_grace_s` more."""

from __future__ import annotations

from smana.common.config.explorer import ExplorerConfig


class RobotClock:
    """Robot time = a pose's stamp + an offset. When the stamps' clock restarts (the stamp gate
    says so, or a stamp falls a stamp window behind), the offset grows so that robot time runs
    on from where it was; `floor` is where an earlier process of the run left it."""

    def __init__(self, stamp_window_s: float):
        self.stamp_window_s = stamp_window_s
        self.offset = 0.0
        self.floor: float | None = None  # robot time of the run's checkpoint

    def robot_time(self, stamp: float, last: float | None, reset: bool) -> tuple[float, bool]:
        """(robot time of a pose stamped `stamp`, whether the stamps' clock restarted there):
        `last` is the robot time reached (None before the first pose: the floor), `reset` the
        stamp gate's word that the stamps started again."""
        t = stamp + self.offset
        last = self.floor if last is None else last
        if last is not None and (reset or t < last - self.stamp_window_s):
            self.offset += last - t
            return last, True
        return t, False


class Budget:
    """The wall time exploration may spend: counted from the first tick with a map (a cold numba
    cache may keep the planner from the map for long), plus what the run's earlier processes
    spent (`spent_before`, from the checkpoint)."""

    def __init__(self, config: ExplorerConfig, created: float):
        self.config = config
        self.created = created  # when this process started waiting
        self.started: float | None = None  # when it started spending
        self.spent_before = 0.0

    def start(self, now: float) -> None:
        if self.started is None:
            self.started = now

    def spent(self, now: float) -> float:
        """Wall time spent on the budget: by earlier processes of this run, and by this one
        since it had a map."""
        return self.spent_before + (0.0 if self.started is None else now - self.started)

    def exhausted(self, now: float) -> bool:
        return self.spent(now) > self.config.time_budget_s

    def waited(self, now: float) -> float:
        return now - self.created

    def out_of_patience(self, now: float) -> bool:
        """No map (or no planner) yet, after the budget and the start-up's grace."""
        patience = self.config.time_budget_s + self.config.startup_grace_s
        return self.started is None and self.waited(now) > patience
