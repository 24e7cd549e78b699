"""The coordinator service: the `ClaimBook` on the fleet's keys (`smana/<fleet>/coordinator/...`).

- query `coordinator/claim/<member>`, one key per member: `{"goal": [x, y]}` claims a goal for
  that member, `{"goal": null}` releases its claim (a `"robot"` field, if any, must name the same
  member); the reply is `{"ok": true, "granted": bool, "holder": the member whose goal is too near
  (or null), "claims": {member: [x, y]}}`. Refused and counted: a selector that is not the exact
  key (`claim/*`, `**`: `selector`), another member's name in the body (`member`), a goal that is
  not finite or lies outside the fleet's area, `navgraph.bounds_*_xy` (`value`);
- `coordinator/claims` (published on each change and every second, also a query): `{"claims":
  {member: [x, y]}, "version": n, "stamp_s": wall time}`: what every explorer discounts its views
  with;
- in: each member's `explorer/state`, which keeps its claim alive (or ends it when the member has
  no goal any more); a member silent for `fleet.pose_timeout_s` x 5 loses its claim.

Who asks matters, and a query does not say who sent it (zenoh's source info and attachment are
whatever the sender writes). So each member claims on a key of its own, and on a secured
deployment the access-control policy lets only that member's identities (`<member>.explorer`,
and its router) send a query there, by that exact key (`deploy/acl.py`); the checks above
hold on an unsecured one too.
"""

from __future__ import annotations

import time

import msgpack

from smana.common import keys
from smana.common.config import ConfigError, SmanaConfig
from smana.common.service import Reject, Service, run_service

from .claims import ClaimBook

PUBLISH_PERIOD_S = 1.0


class CoordinatorService(Service):
    name = "coordinator"
    tick_period_s = 0.2

    def __init__(self, config: SmanaConfig):
        super().__init__(config)
        fc = config.fleet
        if not fc.robots:
            raise ConfigError(
                "the coordinator needs a fleet: set fleet.robots (or smana up --robots N)"
            )
        nc = config.navgraph
        self.book = ClaimBook(
            fc.robots,
            fc.goal_separation_m,
            ttl_s=5 * fc.pose_timeout_s,
            stall_s=fc.claim_stall_s,
            bounds=(nc.bounds_min_xy, nc.bounds_max_xy),
        )
        self._published = -1
        self._stalled: list[str] = []
        self._next_publish = 0.0

    def setup(self) -> None:
        r = self.robot
        self.claims_pub = self.publisher(keys.claims(r), reliable_block=True)
        for m in self.book.members:
            self.queryable(keys.claim(r, m), lambda req, m=m: self.on_claim(m, req))
        self.queryable(keys.claims(r), lambda req: self._claims())
        self.queryable(keys.query(r, "coordinator", "stats"), lambda req: self.book.stats())
        for m in self.book.members:
            self.subscribe(keys.explorer_state(m), lambda b, m=m: self.on_state(m, b))

    def on_claim(self, robot: str, req) -> dict:
        if req.key != keys.claim(self.robot, robot):  # a wildcard reaches every member's key
            raise Reject("selector", f"claim: {req.key} is not {keys.claim(self.robot, robot)}")
        body = req.body()
        goal = body.get("goal", "missing")
        if goal == "missing":
            raise Reject("missing_field", 'a claim is {"goal": [x, y] or null}')
        if body.get("robot", robot) != robot:
            raise Reject("member", f"claim for {body.get('robot')!r} on {robot}'s key")
        now = time.monotonic()
        try:
            if goal is None:
                self.book.release(robot, now)
                granted, holder = True, None
            else:
                if not isinstance(goal, list | tuple) or len(goal) != 2:
                    raise ValueError(f"goal must be [x, y], got {goal!r}")
                granted, holder = self.book.claim(robot, goal, now)
        except (TypeError, ValueError, OverflowError) as exc:  # 1e400 as a JSON integer
            raise Reject("value", f"claim: {str(exc)[:200]}") from None
        self._publish()
        claims = self.book.snapshot(now)
        return {"ok": True, "granted": granted, "holder": holder, "claims": claims}

    def on_state(self, robot: str, payload: bytes) -> None:
        try:
            state = msgpack.unpackb(payload)
            goal = state.get("goal") if isinstance(state, dict) else None
            xy = None if not goal else [float(v) for v in goal["xy"]][:2]
            if xy is not None and len(xy) < 2:  # found by smana bench fuzz: an IndexError
                raise ValueError(f"goal.xy must be [x, y], got {goal['xy']!r}")
            dist = state.get("distance_m") if isinstance(state, dict) else None
            dist = float(dist) if isinstance(dist, int | float) else None
        except Exception as exc:
            raise Reject("malformed", f"explorer state of {robot}: {exc}") from None
        if isinstance(state, dict) and state.get("mode") == "done":
            xy = None
        self.book.confirm(robot, xy, time.monotonic(), dist)

    def tick(self) -> None:
        now = time.monotonic()
        for r in self.book.expire(now):
            self.note("claim_expired", f"{r} silent: its goal is free again")
        stalled = self.book.stalled_members(now)
        if stalled != self._stalled:
            for r in set(stalled) - set(self._stalled):
                self.note("claim_stalled", f"{r} has not moved: its goal holds nobody back")
            self._stalled = stalled
            self._publish()
        elif self.book.version != self._published or now >= self._next_publish:
            self._publish()

    def _claims(self) -> dict:
        book, now = self.book, time.monotonic()
        return {
            "claims": book.snapshot(now),
            "stalled": book.stalled_members(now),
            "version": book.version,
            "stamp_s": time.time(),
        }

    def _publish(self) -> None:
        self._published = self.book.version
        self._next_publish = time.monotonic() + PUBLISH_PERIOD_S
        self.claims_pub.put(self._claims())

    def status_details(self) -> dict:
        return self.book.stats()


def main(config: SmanaConfig) -> int:
    return run_service(CoordinatorService, config)
