"""A replay's report on hand-made run directories: losses worded for the mode (a lockstep loss is
a failure, a realtime drop is the mapper's latest-wins input doing its job), the distance measured
on the poses the replay published, and warnings when scans were lost in lockstep or the recorder
missed poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smana.common.config import SmanaConfig
from smana.deploy import report

N = 12


def summary(mode: str, published: int = N, lost: int = 0, stale: int = 0) -> dict:
    """replay.json as the replay writes it (the figures the report reads)."""
    unacked = lost - stale
    return {
        "dataset": "/data/seq",
        "format": "rellis3d",
        "class_table": "rellis3d",
        "topic": "scan",
        "mode": mode,
        "rate_factor": 2.0,
        "recorded_rate_hz": 10.0,
        "scans": published,
        "published": published,
        "empty": 0,
        "skipped_by_reader": [],
        "read_errors": [],
        "acknowledged": published - lost,
        "lost": lost,
        "overtaken": stale,
        "unacknowledged": unacked,
        "resends": 3 * unacked if mode == "lockstep" else 0,
        "late_published": 0,
        "late_integrated": 0,
        "latency": {"mean_ms": 80.0, "p95_ms": 90.0, "max_ms": 95.0},
        "points_in": 1000,
        "points_published": 600,
        "points_out_of_range": 400,
        "points_ignored_class": 0,
        "points_nonfinite": 0,
        "wall_s": 2.0,
        "scans_per_s": 6.0,
        "poses_published": published,
        "distance_m": 1.1,
        "trajectory": "replay_trajectory.csv",
        "per_scan": [[k + 1, k, f"{k:06d}", 0.1 * k, 50, 80.0] for k in range(published)],
    }


def write_poses(path, n: int) -> None:
    """n poses 0.1 m apart along x, one every 0.1 s."""
    t = 0.1 * np.arange(n)
    rows = np.column_stack([t, 0.1 * np.arange(n), np.zeros(n), np.ones(n), np.zeros(n)])
    np.savetxt(path, rows, delimiter=",", fmt="%.4f", header="t_s,x_m,y_m,z_m,yaw_rad", comments="")


@pytest.fixture
def cfg():
    return SmanaConfig.load(None, ["general.class_table=rellis3d"])


def run_report(run_dir, cfg, s: dict, recorded: int | None = N, clean_stop: bool = True):
    """The report of a replay that published s["poses_published"] poses, of which the recorder
    (when `recorded` is not None) recorded the first `recorded`."""
    write_poses(run_dir / "replay_trajectory.csv", s["poses_published"])
    if recorded is not None:
        (run_dir / "recording.rrd").write_bytes(b"rrd")
        write_poses(run_dir / "trajectory_pose.csv", recorded)
        if clean_stop:
            (run_dir / "recorder.json").write_text(json.dumps({"recorded": {"pose": recorded}}))
    report.write_report(run_dir, cfg, replay=s)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    return metrics, (run_dir / "report.md").read_text()


def test_lockstep_without_loss_is_clean(tmp_path, cfg):
    m, md = run_report(tmp_path, cfg, summary("lockstep"))
    assert m["warnings"] == [] and "## Warnings" not in md
    assert "| lost (no MapDelta after 3 resends) / resent | 0 / 0 |" in md
    assert "overtaken" not in md
    assert f"| poses published / recorded by the recorder | {N} / {N} |" in md


def test_a_lockstep_loss_is_a_warning_at_the_top(tmp_path, cfg):
    m, md = run_report(tmp_path, cfg, summary("lockstep", lost=2))
    assert len(m["warnings"]) == 1 and "2 scan(s) lost in lockstep" in m["warnings"][0]
    assert md.index("## Warnings") < md.index("## Replay")
    assert "| lost (no MapDelta after 3 resends) / resent | 2 / 6 |" in md


def test_realtime_drops_are_reported_as_overtaken_not_as_lost(tmp_path, cfg):
    m, md = run_report(tmp_path, cfg, summary("realtime", lost=3, stale=3))
    assert m["warnings"] == [] and "## Warnings" not in md
    assert "| not integrated: overtaken by a newer scan / unacknowledged | 3 / 0 |" in md
    assert "lost (no MapDelta" not in md
    assert "Realtime: 3 of the 12 scans were overtaken" in md and "dropped as stale" in md
    assert m["replay"]["acknowledged"] == N - 3 and m["replay"]["overtaken"] == 3


def test_distance_comes_from_the_replay_and_missed_poses_are_a_warning(tmp_path, cfg):
    m, md = run_report(tmp_path, cfg, summary("lockstep"), recorded=5)
    rp = m["replay"]
    # measured on the 12 poses the replay published, not on the 5 the recorder heard
    assert rp["distance_m"] == pytest.approx(0.1 * (N - 1))
    assert rp["distance_source"] == "the poses the replay published"
    assert rp["poses_recorded"] == 5
    assert m["warnings"] == [
        f"the recorder recorded 5 of the {N} poses the replay published "
        "(see logs/recorder.log): its recording is incomplete"
    ]
    assert "| distance covered by the poses | 1.10 m (measured on the poses the replay " in md


def test_a_recorder_that_did_not_stop_cleanly_is_a_warning(tmp_path, cfg):
    m, _ = run_report(tmp_path, cfg, summary("lockstep"), clean_stop=False)
    assert len(m["warnings"]) == 1 and "did not stop cleanly" in m["warnings"][0]


def test_without_a_recorder_nothing_is_expected_of_it(tmp_path, cfg):
    m, md = run_report(tmp_path, cfg, summary("realtime"), recorded=None)
    assert m["warnings"] == [] and m["replay"]["poses_recorded"] is None
    assert f"| poses published / recorded by the recorder | {N} / no recorder |" in md
