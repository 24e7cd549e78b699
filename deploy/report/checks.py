"""What in a finished run's figures says it did not do its job: the warnings that head report.md,
end the terminal summary and make `smana up` / `smana replay` exit 1."""

from __future__ import annotations

from smana.deploy.report.measures import (
    COVERAGE_TARGET,
    KNOWN_CURVE,
    MOVED_M,
    SIM_SUMMARY,
    USABLE_FLOOR,
    as_percent,
    as_text,
)

# How the warnings about what the robot did (not about a service) begin: the experiments
# (lab/experiments/) count a run that ends with these alone as a measured failure, not as
# missing data.
OUTCOME_WARNINGS = (
    "the robot did not move",
    "no path query was ever answered",
    "the robot knows only",
    "the robot's own map closed it in",
)


def run_warnings(metrics: dict, explored: bool) -> list[str]:
    """What in a finished run's figures says it did not do its job. `explored`: the run was an
    exploration (the explorer ran), so it should have answered paths, moved the robot and come
    to know at least half the reachable area as usable; an explorer that ended `closed_in` (its
    own map left it no reachable view) failed too."""
    out = []
    ee = metrics.get("explorer")
    if explored and ee is None:
        out.append("the explorer left no state (explorer/state.json): it never ran to its end")
    if ee:
        queries, ok = int(ee.get("path_queries") or 0), int(ee.get("path_ok") or 0)
        errs = ee.get("path_errors") or {}
        if queries and not ok:
            detail = ", ".join(f"{k} x{v}" for k, v in sorted(errs.items())) or "no detail"
            out.append(f"no path query was ever answered with a path ({queries} asked: {detail})")
        if ee.get("done_reason") == "no_graph":
            out.append("the explorer never received a navigation graph (ended `no_graph`)")
        if ee.get("done_reason") == "no_planner":
            out.append("the explorer never saw a planner (ended `no_planner`)")
        if ee.get("done_reason") == "closed_in":
            out.append("the robot's own map closed it in (explorer ended: closed_in)")
    if explored:
        ex = metrics.get("exploration") or {}
        dist = ex.get("distance_m", (ee or {}).get("distance_m"))
        if dist is None or dist < MOVED_M:
            out.append(f"the robot did not move ({as_text(dist, '.2f', ' m')} travelled)")
        out += usable_warnings(ex)
    return out + replay_warnings(metrics.get("replay") or {})


def usable_warnings(ex: dict) -> list[str]:
    """A run (or a fleet) that stopped while it knew under USABLE_FLOOR of the reachable area as
    usable (`usable_share`, measured against ground truth; nothing without one)."""
    share = ex.get("usable_share")
    if share is None or share >= USABLE_FLOOR:
        return []
    return [
        f"the robot knows only {as_percent(share)} of the reachable area as usable (under "
        f"{100 * USABLE_FLOOR:.0f} %: {as_text(ex.get('usable_area_m2'), '.1f', ' m2')} of "
        f"{as_text(ex.get('reachable_area_m2'), '.1f', ' m2')}; "
        f"{as_percent(ex.get('false_obstacle_share'))} of it is an obstacle or a safety zone "
        "in its map)"
    ]


def replay_warnings(rp: dict) -> list[str]:
    """What in a replay's figures says it did not do its job: a scan lost in lockstep (where
    nothing may be lost; realtime drops are by design and only reported), a recorder that
    missed poses the replay published or did not stop cleanly."""
    out = []
    if rp.get("mode") == "lockstep" and rp.get("lost"):
        out.append(
            f"{rp['lost']} scan(s) lost in lockstep: no MapDelta even after resending "
            "them, so the map misses them (see logs/mapper.log)"
        )
    published, recorded = rp.get("poses_published"), rp.get("poses_recorded")
    if published is not None and recorded is not None and recorded < published:
        out.append(
            f"the recorder recorded {recorded} of the {published} poses the replay "
            "published (see logs/recorder.log): its recording is incomplete"
        )
    if recorded is not None and not rp.get("recorder_stopped_cleanly", True):
        out.append(
            "the recorder did not stop cleanly (no recorder.json): its recording may be "
            "incomplete (see logs/recorder.log)"
        )
    return out


def fleet_warnings(fleet: dict) -> list[str]:
    """What in a fleet's figures says it did not do its job: a robot-robot contact, a fleet that
    knows under half the reachable area as usable, a member whose explorer left no state or that
    did not move while the fleet knew less than 95 % of it (and each member's explorer checks)."""
    out = []
    sim = fleet.get("sim") or {}
    total = sim.get("robot_contacts_total")
    if sim.get("summary") is None and fleet.get("simulated", True):
        out.append(f"the simulator left no {SIM_SUMMARY}: robot-robot contacts are unknown")
    elif total:
        pairs = ", ".join(f"{k} x{v}" for k, v in sorted(sim["robot_contacts"].items()) if v)
        out.append(f"{total} robot-robot contact(s) ({pairs or 'no pair named'})")
    out += [w.replace("the robot knows", "the fleet knows") for w in usable_warnings(fleet)]
    # A member left nothing to do (the others saw its part: a small world, a spawn that sees it
    # all) may stay put: its standing still is a failure only when the fleet fell short.
    covered = (fleet.get(KNOWN_CURVE) or 0.0) >= COVERAGE_TARGET
    for r, m in (fleet.get("members") or {}).items():
        ee = None
        if m.get("state"):
            ee = {k: m.get(k) for k in ("path_queries", "path_ok", "path_errors", "done_reason")}
        dist = m.get("distance_m", m.get("explorer_distance_m"))
        where = f"robots/{r}/explorer/state.json"
        for w in run_warnings({"explorer": ee, "exploration": {"distance_m": dist}}, True):
            idle = w.startswith("the robot did not move") and covered
            idle &= (ee or {}).get("done_reason") in ("no_view_worth_it", "no_frontier")
            if not idle:
                out.append(f"{r}: " + w.replace("explorer/state.json", where))
    return out
