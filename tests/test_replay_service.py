"""The replay service in-process on the fake zenoh (tests/support/fake_zenoh.py), against a
stand-in mapper in the test (a liveliness token, a scan subscriber and a MapDelta publisher):
lockstep loses nothing and publishes exactly what the core prepares; realtime counts what a slow
mapper misses. `smana replay --run` still starts the real stack as processes."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.messages import MapDelta, Pose, SemanticCloud, decode, encode
from smana.lab.data import synthetic as syn
from smana.services.replay.player import END, Pacer, ScanFeed
from smana.services.replay.prepare import prepare_scan
from smana.services.replay.readers import open_dataset
from tests.conftest import wait_for

N_SCANS = 6
N_RUN = 12  # the --run sequence: scans large enough that the mapper and recorder have work


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    params = syn.SyntheticConfig(n_scans=N_SCANS, beams=16, columns=256, noise_m=0.0)
    syn.write_rellis_sequence(root, params)
    return root


@pytest.fixture(scope="module")
def run_params():
    return syn.SyntheticConfig(n_scans=N_RUN, beams=32, columns=1024, noise_m=0.0)


@pytest.fixture(scope="module")
def dataset_12(tmp_path_factory, run_params):
    root = tmp_path_factory.mktemp("synthetic12")
    syn.write_rellis_sequence(root, run_params)
    return root


class FakeMapper:
    """Acknowledges each scan with an empty MapDelta after `delay_s`, like the mapper would."""

    def __init__(self, session, robot, delay_s=0.0, topic="scan"):
        self.session, self.robot, self.delay_s = session, robot, delay_s
        self.clouds: list[SemanticCloud] = []
        self.poses: list[Pose] = []
        self._q: queue.Queue = queue.Queue()
        self._pub = session.declare_publisher(keys.map_delta(robot))
        key = keys.scan(robot) if topic == "scan" else keys.cloud(robot)
        self._subs = [
            session.declare_subscriber(key, lambda s: self._q.put(s.payload.to_bytes())),
            session.declare_subscriber(
                keys.pose(robot), lambda s: self.poses.append(decode(s.payload.to_bytes(), Pose))
            ),
        ]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, daemon=True)
        self._thread.start()
        self._token = session.liveliness().declare_token(keys.alive(robot, "mapper"))

    def _work(self):
        while not self._stop.is_set():
            try:
                payload = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            if self.delay_s and self._q.qsize():  # latest wins, like the real one
                while self._q.qsize():
                    payload = self._q.get()
            cloud = decode(payload, SemanticCloud)
            self.clouds.append(cloud)
            time.sleep(self.delay_s)
            self._pub.put(
                encode(MapDelta(stamp_s=cloud.stamp_s, seq=len(self.clouds), cloud_seq=cloud.seq))
            )

    def close(self):
        self._stop.set()
        self._thread.join()
        self._token.undeclare()
        for s in self._subs:
            s.undeclare()
        self._pub.undeclare()


def run_replay(stack, dataset, *extra, timeout_s=60.0):
    proc = stack.service("replay", str(dataset), "--run-dir", str(stack.tmp / "run"), *extra)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        stack.stop(proc)
        raise AssertionError("replay did not finish:\n" + stack.log(proc)) from None
    summary_path = stack.tmp / "run" / "replay.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    return proc.returncode, summary


def test_lockstep_publishes_every_scan_as_prepared(fake_stack, dataset):
    zenoh_stack = fake_stack
    mapper = FakeMapper(zenoh_stack.session, zenoh_stack.robot, delay_s=0.05)
    try:
        code, summary = run_replay(zenoh_stack, dataset, "--lockstep")
    finally:
        mapper.close()
    assert code == 0, zenoh_stack.log("replay")
    assert [c.seq for c in mapper.clouds] == list(range(1, N_SCANS + 1))
    assert summary["published"] == summary["acknowledged"] == N_SCANS
    assert summary["lost"] == 0 and summary["resends"] == 0
    assert summary["latency"]["mean_ms"] >= 50  # it did wait for each delta
    table = ClassTable.load("rellis3d")
    with open_dataset(dataset) as reader:
        for cloud, scan in zip(mapper.clouds, reader, strict=True):
            pc = prepare_scan(scan, table, max_range_m=10.0, min_range_m=0.5)
            np.testing.assert_array_equal(cloud.points, pc.points)
            np.testing.assert_array_equal(cloud.labels, pc.labels)
            np.testing.assert_allclose(cloud.sensor_position, scan.pose[:3, 3])
            assert cloud.source == "lidar" and cloud.stamp_s == pytest.approx(scan.stamp_s)
            assert np.linalg.norm(cloud.points - pc.sensor_position, axis=1).max() <= 10.0 + 1e-4
    assert len(mapper.poses) == N_SCANS
    assert summary["points_published"] == sum(len(c.points) for c in mapper.clouds)
    per_scan = summary["per_scan"]
    assert [r[0] for r in per_scan] == list(range(1, N_SCANS + 1))
    assert [r[4] for r in per_scan] == [len(c.points) for c in mapper.clouds]
    assert all(r[5] >= 50 for r in per_scan)


def test_realtime_counts_what_a_slow_mapper_misses(fake_stack, dataset):
    zenoh_stack = fake_stack
    # 10 Hz x 4 = 25 ms between scans, a mapper taking 120 ms per scan
    mapper = FakeMapper(zenoh_stack.session, zenoh_stack.robot, delay_s=0.12)
    try:
        code, summary = run_replay(zenoh_stack, dataset, "--realtime", "--rate", "4")
    finally:
        mapper.close()
    assert code == 0, zenoh_stack.log("replay")
    assert summary["published"] == N_SCANS
    assert summary["lost"] + summary["late_integrated"] > 0, {
        k: v for k, v in summary.items() if k != "per_scan"
    }
    assert summary["acknowledged"] == len({c.seq for c in mapper.clouds})
    assert summary["acknowledged"] + summary["lost"] == N_SCANS
    assert summary["lost"] == summary["overtaken"] + summary["unacknowledged"]
    assert summary["wall_s"] < 2.0  # it did not wait for the mapper between scans


def test_waits_for_the_mapper_then_gives_up(fake_stack, dataset):
    zenoh_stack = fake_stack
    code, summary = run_replay(zenoh_stack, dataset, "--set", "replay.wait_timeout_s=1.0")
    assert code == 1 and summary is None
    assert "mapper not alive after 1 s" in zenoh_stack.log("replay")


def test_bad_dataset_is_a_clear_error(tmp_path):
    (tmp_path / "velodyne").mkdir()
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.replay", str(tmp_path), "--info"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "label folder is missing" in out.stderr
    assert "--label-field none" in out.stderr  # and what to do with unlabelled scans


def test_info_lists_skipped_scans(dataset):
    lab = dataset / "Rellis-3D" / "00000" / "os1_cloud_node_semantickitti_label_id"
    data = (lab / "000002.label").read_bytes()
    (lab / "000002.label").unlink()
    try:
        out = subprocess.run(
            [sys.executable, "-m", "smana.services.replay", str(dataset), "--info"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        (lab / "000002.label").write_bytes(data)
    assert out.returncode == 0, out.stderr
    assert f"rellis3d, {N_SCANS - 1} scans at 10.00 Hz" in out.stdout
    assert "000002.bin: no label file" in out.stdout
    assert "class table rellis3d, published on robot/scan" in out.stdout


# -- pacing rules, with a fake clock ------------------------------------------------------------


class FakeClock:
    """Creeps forward by 1 us per reading, as a real clock does between two calls."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        self.t += 1e-6
        return self.t


def test_pacer_lockstep_waits_resends_and_gives_up():
    clock = FakeClock()
    p = Pacer("lockstep", ack_timeout_s=5.0, max_resends=1, clock=clock)
    assert p.ready(0.0)
    p.on_published(1, 0, 0.0, b"a")
    assert not p.ready(0.1)
    clock.t += 0.2
    assert p.on_ack(1) == pytest.approx(0.2, abs=1e-4) and p.ready(0.1)
    p.on_published(2, 1, 0.1, b"b")
    clock.t += 6
    assert [f.seq for f in p.overdue()] == [2] and p.resends == 1
    clock.t += 6
    assert p.overdue() == [] and p.lost == 1 and p.ready(0.2)
    assert p.unacknowledged == 1 and p.overtaken == 0


def test_pacer_realtime_schedule_and_late_counts():
    clock = FakeClock()
    p = Pacer("realtime", rate_factor=2.0, period_s=0.05, clock=clock)
    assert p.ready(10.0)  # the first scan goes out at once
    p.on_published(1, 0, 10.0, b"")  # t0: stamp 10.0 at wall 100.0
    assert not p.ready(10.1)  # due at 100.05
    clock.t = 100.0501
    assert p.ready(10.1)
    p.on_published(2, 1, 10.1, b"")
    clock.t = 100.2  # stamp 10.2 was due at 100.1: 0.1 s late > one period
    p.on_published(3, 2, 10.2, b"")
    assert p.late_published == 1
    assert p.on_ack(3) == pytest.approx(0.0, abs=1e-4)
    assert p.lost == p.overtaken == 2  # 1 and 2 were overtaken: the mapper dropped them
    assert p.on_ack(1) is None and p.unacknowledged == 0


# -- the read-ahead feed, in-process ------------------------------------------------------------


def drain(feed):
    items = []
    while True:
        item = feed.get(timeout=10.0)
        assert item is not None, "the feed stalled"
        if item is END:
            return items
        items.append(item)


def test_feed_reports_a_scan_broken_after_indexing_and_goes_on(dataset, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    reader = open_dataset(copy)
    lab = copy / "Rellis-3D" / "00000" / "os1_cloud_node_semantickitti_label_id" / "000003.label"
    lab.write_bytes(lab.read_bytes()[:-8])  # damaged after the reader indexed it
    feed = ScanFeed(reader, ClassTable.load("rellis3d"), 10.0, 0.5, "lidar", start=1, count=4)
    items = drain(feed.start())
    feed.stop()
    assert [i.index for i in items] == [1, 2, 3, 4]
    assert [bool(i.error) for i in items] == [False, False, True, False]
    assert "000003.label" in items[2].error
    cloud = decode(items[0].cloud, SemanticCloud)
    assert (
        cloud.seq == 1 and cloud.source == "lidar" and len(cloud.points) == items[0].prepared.n_out
    )


def test_feed_stops_while_blocked_on_a_full_queue(dataset):
    feed = ScanFeed(open_dataset(dataset), ClassTable.load("rellis3d"), 10.0, 0.5, "lidar", ahead=1)
    feed.start()
    assert wait_for(feed._queue.full, 10)  # the thread now waits to put its second scan
    t0 = time.monotonic()
    feed.stop()
    assert time.monotonic() - t0 < 2.0 and not feed._thread.is_alive()


@pytest.mark.multiprocess
def test_run_starts_the_stack_and_writes_the_run_dir(dataset_12, run_params, tmp_path):
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    run = tmp_path / "run"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "smana.services.replay",
            str(dataset_12),
            "--run",
            "--run-dir",
            str(run),
            "--set",
            f'deploy.router_listen=["tcp/127.0.0.1:{port}"]',
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "smana replay: ok" in out.stdout
    summary = json.loads((run / "replay.json").read_text())
    assert summary["published"] == summary["acknowledged"] == N_RUN and summary["lost"] == 0
    # Every pose the replay published is in its own trajectory and in the recorder's, and the
    # distance is the path the synthetic robot drove (1.5 m/s along the trail for 1.1 s).
    published = np.loadtxt(run / "replay_trajectory.csv", delimiter=",", skiprows=1)
    recorded = np.loadtxt(run / "trajectory_pose.csv", delimiter=",", skiprows=1)
    assert summary["poses_published"] == len(published) == len(recorded) == N_RUN
    np.testing.assert_allclose(recorded, published, atol=2e-4)
    recorder = json.loads((run / "recorder.json").read_text())
    assert recorder["recorded"]["pose"] == N_RUN and recorder["dropped"] == {}
    assert recorder["recorded"]["delta"] >= N_RUN
    for name in ("config.toml", "map.npz", "graph.npz", "metrics.json", "report.md"):
        assert (run / name).is_file(), name
    config = (run / "config.toml").read_text()
    assert 'class_table = "rellis3d"' in config and 'inputs = ["scan"]' in config
    metrics = json.loads((run / "metrics.json").read_text())
    rp = metrics["replay"]
    assert rp["published"] == N_RUN and metrics["warnings"] == []
    true_m = run_params.speed_mps * (N_RUN - 1) / run_params.rate_hz
    assert rp["distance_m"] == pytest.approx(true_m, rel=0.03)
    assert rp["distance_source"] == "the poses the replay published"
    assert rp["poses_recorded"] == N_RUN
    with np.load(run / "graph.npz") as g:
        assert (g["flags"] & 1).sum() > 100  # known nodes
    # the report is the replay's: the dataset and its figures, the map's content, no ground truth
    report = (run / "report.md").read_text()
    assert "## Replay" in report and "## Map content" in report and "World `" not in report
    assert "## Warnings" not in report
    assert f"| published / integrated | {N_RUN} / {N_RUN} |" in report
    assert f"| poses published / recorded by the recorder | {N_RUN} / {N_RUN} |" in report
    assert f"| distance covered by the poses | {rp['distance_m']:.2f} m (measured on the " in report
    assert metrics["ground_truth"] == "none: a replayed dataset" and "exploration" not in metrics
    assert rp["latency_per_point_us"] > 0
    content = metrics["map_content"]
    assert content["n_points"] > 0 and sum(c["share"] for c in content["per_class"].values()) == (
        pytest.approx(1.0)
    )
    for plot in ("graph", "replay_latency"):
        assert (run / metrics["files"]["plots"][plot]).stat().st_size > 1000, plot


def test_pacer_realtime_priming_starts_the_clock_at_the_first_ack():
    clock = FakeClock()
    p = Pacer("realtime", period_s=0.1, clock=clock, prime=True)
    p.on_published(1, 0, 5.0, b"")
    clock.t += 0.4  # the first integration loads the mapper's kernels
    assert not p.ready(5.1)
    assert p.on_ack(1) == pytest.approx(0.4, abs=1e-4)
    assert p.late_integrated == 0  # the priming scan is not late
    assert not p.ready(5.1)  # the clock starts now: 5.1 is due one period later
    clock.t += 0.1001
    assert p.ready(5.1)
    p.on_published(2, 1, 5.1, b"")
    assert p.late_published == 0


def test_pacer_priming_gives_up_with_the_ack_timeout():
    clock = FakeClock()
    p = Pacer("realtime", period_s=0.1, ack_timeout_s=2.0, clock=clock, prime=True)
    p.on_published(1, 0, 5.0, b"")
    clock.t += 3.0
    p.overdue()
    assert p.lost == 1 and p.priming_seq is None and p.ready(5.0)


@pytest.fixture
def dataset_with_an_empty_scan(dataset, tmp_path):
    """The synthetic sequence with scan 2 all void (an ignored class): nothing of it is left to
    publish but its pose."""
    import shutil

    copy = tmp_path / "empty_scan"
    shutil.copytree(dataset, copy)
    lab = copy / "Rellis-3D" / "00000" / "os1_cloud_node_semantickitti_label_id" / "000002.label"
    lab.write_bytes(np.zeros(lab.stat().st_size // 4, np.uint32).tobytes())
    return copy


def test_lockstep_goes_on_past_an_empty_scan(fake_stack, dataset_with_an_empty_scan):
    zenoh_stack = fake_stack
    # The scans after an empty one are acknowledged by their own numbers: nothing is waited for
    # in vain (resent after ack_timeout_s) nor counted lost.
    mapper = FakeMapper(zenoh_stack.session, zenoh_stack.robot)
    try:
        code, summary = run_replay(
            zenoh_stack,
            dataset_with_an_empty_scan,
            "--lockstep",
            "--set",
            "replay.ack_timeout_s=20",
        )
    finally:
        mapper.close()
    assert code == 0, zenoh_stack.log("replay")
    assert summary["empty"] == 1 and summary["published"] == N_SCANS - 1
    assert summary["acknowledged"] == N_SCANS - 1 and summary["lost"] == summary["resends"] == 0
    assert [c.seq for c in mapper.clouds] == [r[0] for r in summary["per_scan"]]
    assert len(mapper.poses) == N_SCANS  # the empty scan's pose too
