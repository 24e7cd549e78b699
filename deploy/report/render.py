"""A run's report as text, made from metrics.json's values only: report.md (`render_markdown`)
and the table `smana up` / `smana replay` end with in the terminal (`summary_lines`)."""

from __future__ import annotations

from pathlib import Path

from smana.deploy.report.measures import (
    CLOSE_CALL_M,
    COVERAGE_TARGET,
    NO_SIMULATOR,
    as_percent,
    as_text,
)

# Why the two explored areas differ (the explorer's is in its progress plot, the report's here).
EXPLORED_AREAS = (
    "Two explored areas, measuring different things: *usable coverage* counts the cells of the "
    "world the robot could reach (traversable, with its radius of clearance, connected to its "
    "start) whose node in the final graph is known as traversable (a traversable class or a "
    "doubtful one, which the planner drives through at a cost; no obstacle, outside the safety "
    "zone): what the robot could drive on; *the explorer's own "
    "count* (`explorer/state.json` `explored_m2`, its progress plot) counts the known nodes its "
    "graph calls traversable when it last planned, reachable or not, in the robot's own "
    "(possibly noisy) frame, and misses what the map learned after that plan. *Known (any "
    "label)* counts the reachable cells under a known node whatever the graph calls it, "
    "obstacles included: a robot whose map is a field of false obstacles knows much and can "
    "use little of it."
)


def _guard(g: dict | None) -> str:
    """The guard's figures (services/explorer/guard.py) in a cell: '-' when there were none."""
    if not g:
        return "-"
    if not g.get("scans"):
        return "no safety scan: not guarded"
    return f"{g['slowed']} / {g['stopped']} ({g['scans']} scans)"


def _area(ex: dict, name: str) -> str:
    """`A m2 = S % of the reachable R m2` for one of exploration_coverage's areas."""
    return (
        f"{as_text(ex.get(f'{name}_area_m2'), '.1f', ' m2')} = "
        f"{as_percent(ex.get(f'{name}_share'))} of "
        f"the reachable {as_text(ex.get('reachable_area_m2'), '.1f', ' m2')}"
    )


def summary_rows(metrics: dict) -> list[tuple[str, str]]:
    """What happened in a run, as (figure, value) rows, from `metrics.json`'s values only: the one
    table `smana up` ends with in the terminal and that heads `report.md` (`summary_lines`,
    `render_markdown`). A figure the run did not measure is `-` (a replay has no ground truth)."""
    ex, ee = metrics.get("exploration") or {}, metrics.get("explorer") or {}
    rp, run = metrics.get("replay") or {}, metrics.get("run") or {}
    warnings = metrics.get("warnings") or []
    n = len(warnings)
    rows = [("outcome", f"FAILED ({n} warning{'s' * (n != 1)})" if warnings else "ok")]
    if metrics.get("fleet"):
        rows += fleet_summary_rows(metrics["fleet"])
    if metrics.get("ground_truth") == NO_SIMULATOR:
        rows.append(("ground truth", "none: the simulator was off"))
    if ex:
        rows.append(("usable coverage (against ground truth)", _area(ex, "usable")))
        rows.append(("false obstacles (free, blocked in the map)", _area(ex, "false_obstacle")))
        rows.append(("false free (obstacle, free in the map)", _area(ex, "false_free")))
    if ee:
        rows.append(
            ("explored area (explorer's own count)", as_text(ee.get("explored_m2"), ".1f", " m2"))
        )
    distance = ex.get("distance_m", rp.get("distance_m", ee.get("distance_m")))
    rows.append(("distance travelled", as_text(distance, ".1f", " m")))
    if ex:
        rows.append(
            (
                "collisions",
                f"{ex.get('collisions', '-')} ({ex.get('close_calls', '-')} close calls "
                f"under {CLOSE_CALL_M} m)",
            )
        )
    if ee:
        rows.append(
            (
                "path queries",
                f"{ee.get('path_queries') or 0} ({ee.get('path_ok') or 0} answered with a path)",
            )
        )
    if rp:
        rows.append(
            (
                "scans published / integrated",
                f"{rp.get('published', '-')} / {rp.get('acknowledged', '-')}",
            )
        )
    robot_s = ex.get("duration_robot_s", ee.get("elapsed_s", rp.get("duration_s")))
    wall_s = run.get("wall_time_s")  # the supervisor's, start to stop; else the explorer's
    wall_s = ee.get("wall_time_s") if wall_s is None else wall_s
    rows.append(
        (
            "duration",
            f"{as_text(robot_s, '.0f', ' s')} robot time, {as_text(wall_s, '.0f', ' s')} wall time",
        )
    )
    mc = metrics.get("map_content")
    voxels = mc.get("n_points") if isinstance(mc, dict) else None
    rows.append(("map", f"{voxels} occupied voxels" if voxels is not None else "-"))
    # the explorer's reason, and what stopped the stack (`explorer finished`, `--duration`, ...)
    why = [w for w in (ee.get("done_reason"), run.get("ended")) if w]
    rows.append(("ended because", f"{why[0]} ({why[1]})" if len(why) == 2 else "".join(why) or "-"))
    rows.append(("run directory", str(metrics.get("run_dir", "-"))))
    return rows


def summary_lines(metrics: dict, prog: str = "smana up") -> list[str]:
    """The terminal's end of `smana up` (or `smana replay --run`, `prog`): a headline
    (`smana up: ok` / `smana up: FAILED`), the `summary_rows` table, one line per warning."""
    warnings = metrics.get("warnings") or []
    rows = summary_rows(metrics)
    width = max(len(a) for a, _ in rows)
    lines = [f"{prog}: {'FAILED' if warnings else 'ok'}"]
    lines += [f"  {a:<{width}}  {b}" for a, b in rows[1:]]
    lines += [f"  warning: {w}" for w in warnings]
    return lines


def fleet_summary_rows(fleet: dict) -> list[tuple[str, str]]:
    """The fleet's lines of the summary table (from metrics.json's "fleet" section only)."""
    sim = fleet.get("sim") or {}
    robots = fleet.get("robots") or []
    n = len(robots)
    rows = [("fleet", f"{n} member{'s' if n != 1 else ''}: {', '.join(robots)}")]
    t95, d95 = fleet.get("time_to_95_s"), fleet.get("distance_to_95_m")
    rows.append(
        (
            f"to {100 * COVERAGE_TARGET:.0f} % known (any label)",
            "not reached"
            if t95 is None
            else f"{t95:.0f} s robot time, {as_text(d95, '.1f', ' m')} total distance",
        )
    )
    rows.append(("overlap of the members' maps", as_percent(fleet.get("overlap"))))
    contacts = sim.get("robot_contacts_total")
    rows.append(
        (
            "robot-robot contacts",
            f"{'-' if contacts is None else contacts} (minimum separation "
            f"{as_text(sim.get('min_separation_overall_m'), '.2f', ' m')})",
        )
    )
    mp = fleet.get("map") or {}
    if isinstance(mp.get("merged"), dict):
        rows.append(("merged map", _map_scores(mp["merged"])))
    for r, m in (fleet.get("members") or {}).items():
        own = mp.get(r)
        rows.append(
            (
                f"{r}",
                f"{as_text(m.get('distance_m', m.get('explorer_distance_m')), '.1f', ' m')}, "
                f"{m.get('n_goals', '-')} goals, {m.get('collisions', '-')} collisions, "
                f"{as_text(m.get('robot_time_s'), '.0f', ' s')} robot time"
                + (f"; own map {_map_scores(own)}" if isinstance(own, dict) else ""),
            )
        )
    return rows


def _map_scores(s: dict) -> str:
    return (
        f"error {as_text(s.get('reconstruction_error_mean_m'), '.3f', ' m')}, "
        f"classification {as_text(s.get('classification_ratio'), '.3f')}"
    )


def render_markdown(m: dict) -> str:
    c = m["config"]
    rp = m.get("replay")
    lines = [f"# smana run: {Path(m['run_dir']).name}", ""]
    if m.get("warnings"):
        lines += ["## Warnings", "", "This run did not do its job:", ""]
        lines += [f"- {w}" for w in m["warnings"]]
        lines.append("")
    lines += ["## Summary", "", "| figure | value |", "|---|---|"]
    lines += [f"| {a} | {b} |" for a, b in summary_rows(m)]
    lines.append("")
    if rp:
        lines += [
            f"Replay of `{rp.get('dataset')}` ({rp.get('format')}, class table "
            f"`{rp.get('class_table')}`), map back-end `{c['backend']}` at "
            f"{c['map_resolution_m']} m, graph {c['graph_resolution_m']} m. No ground truth: the "
            "map is described, not measured.",
            "",
        ]
    elif m.get("ground_truth") == NO_SIMULATOR:
        lines += [
            f"Map back-end `{c['backend']}` at {c['map_resolution_m']} m, graph "
            f"{c['graph_resolution_m']} m. No ground truth: {NO_SIMULATOR[6:]}.",
            "",
        ]
    else:
        lines += [
            f"World `{c['world']}` seed {c['seed']}, map back-end `{c['backend']}` at "
            f"{c['map_resolution_m']} m, graph {c['graph_resolution_m']} m, label noise "
            f"`{c['label_noise']}`, pose noise {c['pose_noise_xy_m']} m / "
            f"{c['pose_noise_yaw_rad']} rad, class costs "
            f"{c['class_costs'] or 'from the class table'}.",
            "",
        ]
    if rp:
        lines += _replay_lines(rp)
    if m.get("fleet"):
        lines += _fleet_lines(m["fleet"])
    ex, ee = m.get("exploration") or {}, m.get("explorer") or {}
    if ex or ee:
        title = "## Exploration"
        if m.get("fleet"):
            title += " (the fleet: merged coverage, the members' figures added)"
        lines += [title, "", "| figure | value |", "|---|---|"]
        rows = [
            ("ended because", ee.get("done_reason") or "-"),
            (
                "wall time, the explorer's (the run's is in the summary)",
                as_text(ee.get("wall_time_s"), ".0f", " s"),
            ),
            ("robot time", as_text(ex.get("duration_robot_s"), ".0f", " s")),
            (
                "usable coverage: reachable traversable area (ground truth) under a node the "
                "final graph knows as traversable",
                _area(ex, "usable"),
            ),
            (
                "false obstacles: reachable traversable area under an obstacle or a safety zone "
                "of the final graph",
                _area(ex, "false_obstacle"),
            ),
            (
                "false free: obstacle area (ground truth) under a node the final graph knows as "
                "traversable",
                _area(ex, "false_free"),
            ),
            (
                "of which doubtful: under an unconfirmed obstacle class (passable at a cost)",
                _area(ex, "doubtful"),
            ),
            (
                "known (any label): reachable traversable area under a known node of the final "
                "graph, obstacles included",
                _area(ex, "known_reachable"),
            ),
            (
                "explored area, the explorer's own count (known nodes its graph calls "
                "traversable, at its last plan)",
                as_text(ee.get("explored_m2"), ".1f", " m2"),
            ),
            (
                "known graph area (every known node of the final graph, obstacles included)",
                as_text(ex.get("known_area_m2"), ".1f", " m2"),
            ),
            ("distance travelled", as_text(ex.get("distance_m"), ".1f", " m")),
            ("goals", str(ee.get("n_goals", "-"))),
            (
                "travelled nodes on terrain (vs grass, ground truth)",
                as_text(
                    100 * ex["terrain_share"] if ex.get("terrain_share") is not None else None,
                    ".0f",
                    " %",
                ),
            ),
            ("minimum clearance from obstacles", as_text(ex.get("min_clearance_m"), ".2f", " m")),
            (f"close calls (clearance < {CLOSE_CALL_M} m)", str(ex.get("close_calls", "-"))),
            ("collisions (footprint over an obstacle)", str(ex.get("collisions", "-"))),
            ("the guard (safety scan): commands slowed / stopped", _guard(ee.get("guard"))),
            ("trajectory measured from", ex.get("trajectory_source", "-")),
        ]
        if m.get("fleet"):
            # a fleet's explorers are its members' (the Fleet section): only what was measured
            rows = [(a, b) for a, b in rows if b not in ("-", "None")]
        lines += [f"| {a} | {b} |" for a, b in rows]
        lines.append("")
        if ex and ee:
            lines += [EXPLORED_AREAS, ""]
    mp = m.get("map")
    if isinstance(mp, dict) and mp.get("n_points"):
        lines += [
            "## Map against ground truth",
            "",
            f"{mp['n_points']} map points (`{mp.get('file')}`): reconstruction error "
            f"{as_text(mp['reconstruction_error_mean_m'], '.3f')} m mean, "
            f"{as_text(mp['reconstruction_error_std_m'], '.3f')} m std; classification ratio "
            f"{as_text(mp['classification_ratio'], '.3f')}.",
            "",
            "| class (map label) | points | error mean (m) | classification ratio |",
            "|---|---|---|---|",
        ]
        for name, s in mp["per_class"].items():
            lines.append(
                f"| {name} | {s['n_points']} | {as_text(s['error_mean_m'], '.3f')} | "
                f"{as_text(s['classification_ratio'], '.3f')} |"
            )
        lines.append("")
    elif mp:
        lines += ["## Map against ground truth", "", str(mp), ""]
    mc = m.get("map_content")
    if isinstance(mc, dict) and mc.get("n_points"):
        lines += [
            "## Map content",
            "",
            f"{mc['n_points']} occupied voxels.",
            "",
            "| class | voxels | share |",
            "|---|---|---|",
        ]
        lines += [
            f"| {name} | {s['points']} | {100 * s['share']:.1f} % |"
            for name, s in mc["per_class"].items()
        ]
        lines.append("")
    files = m.get("files") or {}
    if files.get("plots"):
        lines += ["## Plots", ""]
        lines += [f"![{k}]({v})" for k, v in files["plots"].items()]
        lines.append("")
    lines += ["## Files", ""]
    lines.append(
        f"- Rerun recording: `{files.get('recording')}` "
        f"({files.get('recording_bytes', 0) / 1e6:.1f} MB; `smana view {m['run_dir']}`)"
    )
    lines.append(f"- final map: `{files.get('map')}`, graph: `{files.get('graph')}`")
    lines.append(
        "- config used: `config.toml`; logs: " + ", ".join(f"`{p}`" for p in files.get("logs", []))
    )
    return "\n".join(lines) + "\n"


def _replay_lines(rp: dict) -> list[str]:
    lat = rp.get("latency") or {}
    rate = rp.get("recorded_rate_hz")
    lockstep = rp.get("mode") == "lockstep"
    mode = rp.get("mode", "-")
    if mode == "realtime" and rp.get("rate_factor"):
        mode += f" x{rp['rate_factor']:g}"
    kept = rp.get("points_kept_share")
    kept = None if kept is None else 100 * kept
    if lockstep:  # nothing may be lost: a loss is a failure (and a warning above)
        losses = (
            "lost (no MapDelta after 3 resends) / resent",
            f"{rp.get('lost', '-')} / {rp.get('resends', '-')}",
        )
    else:  # the mapper keeps the newest scan only: what it cannot keep up with, it drops
        losses = (
            "not integrated: overtaken by a newer scan / unacknowledged",
            f"{rp.get('overtaken', '-')} / {rp.get('unacknowledged', '-')}",
        )
    recorded = rp.get("poses_recorded")
    rows = [
        ("mode", mode),
        ("recorded rate", as_text(rate, ".1f", " Hz")),
        ("scans in the dataset (readable)", str(rp.get("scans", "-"))),
        ("skipped by the reader", str(len(rp.get("skipped_by_reader") or []))),
        ("published / integrated", f"{rp.get('published', '-')} / {rp.get('acknowledged', '-')}"),
        (
            "empty after filtering / unreadable",
            f"{rp.get('empty', '-')} / {len(rp.get('read_errors') or [])}",
        ),
        losses,
        (
            "late: published / integrated",
            f"{rp.get('late_published', '-')} / {rp.get('late_integrated', '-')}",
        ),
        (
            "integration latency mean / p95 / max",
            f"{as_text(lat.get('mean_ms'), '.0f')} / {as_text(lat.get('p95_ms'), '.0f')} / "
            f"{as_text(lat.get('max_ms'), '.0f')} ms",
        ),
        ("latency per point (mean scan)", as_text(rp.get("latency_per_point_us"), ".2f", " us")),
        (
            "points kept",
            f"{rp.get('points_published', '-')} of {rp.get('points_in', '-')} "
            f"({as_text(kept, '.0f', ' %')})",
        ),
        (
            "dropped: out of range / ignored class / non-finite",
            f"{rp.get('points_out_of_range', '-')} / {rp.get('points_ignored_class', '-')} / "
            f"{rp.get('points_nonfinite', '-')}",
        ),
        ("throughput", as_text(rp.get("scans_per_s"), ".1f", " scans/s")),
        (
            "poses published / recorded by the recorder",
            f"{rp.get('poses_published', '-')} / {'no recorder' if recorded is None else recorded}",
        ),
        (
            "distance covered by the poses",
            as_text(rp.get("distance_m"), ".2f", " m")
            + (f" (measured on {rp['distance_source']})" if rp.get("distance_source") else ""),
        ),
    ]
    lines = [
        "## Replay",
        "",
        "| figure | value |",
        "|---|---|",
        *[f"| {a} | {b} |" for a, b in rows],
        "",
    ]
    if not lockstep and rp.get("overtaken"):
        lines += [
            f"Realtime: {rp['overtaken']} of the {rp.get('published', '-')} scans were "
            "overtaken by a newer one before the mapper integrated them: dropped as stale "
            "by its latest-wins input (or on the way, by the link's DROP congestion "
            "control), as on a robot whose mapper is slower than its sensor. Not a failure "
            "of the replay: `--lockstep` integrates every scan.",
            "",
        ]
    return lines


def _fleet_lines(fleet: dict) -> list[str]:
    """report.md's "Fleet" section."""
    sim = fleet.get("sim") or {}
    mp = fleet.get("map") or {}
    lines = [
        "## Fleet",
        "",
        f"Fleet `{fleet.get('name')}`: {len(fleet.get('robots') or [])} members sharing one map "
        "and one navigation graph. Coverage is the merged graph's, against ground truth; the "
        "overlap is the share of the explored reachable area observed by more than one member "
        "(a cell observed by a member: an occupied voxel in its column in that member's own "
        "map); time and total distance to 95 % are read off the fleet's coverage curve (the "
        "largest explored area any member had reported, rescaled to the ground truth at the "
        "end).",
        "",
        "| figure | value |",
        "|---|---|",
        (
            "| merged coverage of the reachable traversable area | "
            f"{as_percent(fleet.get('coverage'))} of "
            f"{as_text(fleet.get('reachable_area_m2'), '.1f', ' m2')} |"
        ),
        f"| overlap | {as_percent(fleet.get('overlap'))} |",
        f"| time to 95 % (robot time) | {as_text(fleet.get('time_to_95_s'), '.0f', ' s')} |",
        f"| total distance to 95 % | {as_text(fleet.get('distance_to_95_m'), '.1f', ' m')} |",
        f"| total distance | {as_text(fleet.get('total_distance_m'), '.1f', ' m')} |",
        f"| robot-robot contacts | {sim.get('robot_contacts_total', '-')} |",
        f"| minimum separation | {as_text(sim.get('min_separation_overall_m'), '.2f', ' m')} |",
        f"| simulated time | {as_text(sim.get('sim_time_s'), '.0f', ' s')} |",
        "",
        "| member | distance (m) | goals | robot time (s) | wall time (s) | collisions | "
        "observed share | map error (m) | classification ratio | ended because |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    seen = fleet.get("observed_share_per_member") or {}
    for who in ["merged", *(fleet.get("members") or {})]:
        m = (fleet.get("members") or {}).get(who, {})
        s = mp.get(who) if isinstance(mp.get(who), dict) else {}
        lines.append(
            f"| {'merged map' if who == 'merged' else who} | "
            f"{as_text(m.get('distance_m', m.get('explorer_distance_m')), '.1f')} | "
            f"{m.get('n_goals', '-')} | {as_text(m.get('robot_time_s'), '.0f')} | "
            f"{as_text(m.get('wall_time_s'), '.0f')} | {m.get('collisions', '-')} | "
            f"{as_percent(seen.get(who))} | "
            f"{as_text(s.get('reconstruction_error_mean_m'), '.3f')} | "
            f"{as_text(s.get('classification_ratio'), '.3f')} | {m.get('done_reason') or '-'} |"
        )
    pairs = sim.get("min_separation_m") or {}
    if pairs:
        lines += ["", "| pair | contacts | minimum separation (m) |", "|---|---|---|"]
        for k, v in sorted(pairs.items()):
            lines.append(f"| {k} | {(sim.get('robot_contacts') or {}).get(k, 0)} | {v:.2f} |")
    return lines + [""]
