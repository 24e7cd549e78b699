"""The ROS 2 family of `smana bench fuzz` (issue 25), bounded: a few hundred hostile /odom,
/points, /tf_static and GetPlan inputs (mutated CDR, wild values, bad attachments) to a real
`smana ros2` process over an isolated loopback zenoh (the family's own router on a free port,
multicast and gossip off), each fate predicted; and, in-process, the cases and their
predictions themselves."""

from __future__ import annotations

import pytest

pytest.importorskip("rosbags")

from smana.common.config import SmanaConfig  # noqa: E402
from smana.lab.bench.fuzz import cli  # noqa: E402
from smana.lab.bench.fuzz_ros2 import CONFIG, Ros2Family, table  # noqa: E402
from smana.lab.fuzz_ros2 import KINDS, TOPICS, Ros2Inputs, Ros2Reference  # noqa: E402
from smana.lab.fuzz_values import RandomDraw  # noqa: E402
from smana.services.ros2.rmw import RosTypes  # noqa: E402

TYPES = RosTypes()


def _cases(seed: int, n: int, t0: float = 1.7e9):
    inputs = Ros2Inputs(TYPES, RandomDraw(seed), t0)
    out = [inputs.genuine(t) for t in ("tf_static", "odom", "odom", "odom")]
    return out + [inputs.case(TOPICS[i % len(TOPICS)]) for i in range(n)]


def test_every_topic_gets_every_kind_and_both_fates(tmp_path):
    (tmp_path / "c.toml").write_text(CONFIG)
    ref = Ros2Reference(SmanaConfig.load(tmp_path / "c.toml"), TYPES)
    cases = _cases(0, 2000)
    fates = {(c.topic, c.kind): set() for c in cases}
    for c in cases:
        fate = ref.fate(c)
        fates[(c.topic, c.kind)].add(fate)
        if c.refuse is not None:  # where the generator knows, the cores agree
            assert c.refuse == (fate != "accepted"), (c.topic, c.kind, c.how, fate)
    assert ref.crashes == []
    assert set(fates) == {(t, k) for t in TOPICS for k in KINDS}
    for t in TOPICS:
        seen = set().union(*(f for (topic, _), f in fates.items() if topic == t))
        assert "accepted" in seen and "malformed" in seen, (t, seen)
    assert {"value", "pose_jump", "no_transform", "stamp"} <= set(ref.fates), ref.fates
    assert all(ref.received.values()), ref.received
    # the same seed makes the same payloads (attachments carry the time they were made)
    assert [c.payload for c in _cases(0, 200)] == [c.payload for c in cases[:204]]


@pytest.mark.multiprocess
@pytest.mark.slow
def test_fuzz_ros2_topics_and_getplan(tmp_path):
    family = Ros2Family(tmp_path / "ros2", inputs=300, seed=5, oversize=4)
    f = family.run()
    report = table(f)
    assert f.crashes == 0 and f.tracebacks == 0 and f.exit_code == 0, report
    assert f.ok, report
    topics = {k.split(":")[0] for k in f.by_kind}
    assert topics == set(TOPICS), report
    # every input in exactly one counter, and the counters as predicted
    assert f.msgs_in == f.accepted + sum(f.rejected.values()) and not f.dropped, report
    assert f.rejected == f.predicted and f.rejected.get("malformed", 0) > 20, report
    assert f.rejected["oversize"] == 4, report  # one on each topic and one GetPlan
    assert f.received == f.received_predicted and f.received["clouds"] > 0, report
    assert f.checks["a genuine Odometry reaches robot/pose after the fuzz"], report
    # a hostile /tf_static cache answered its history query at start-up, each reply as predicted
    assert sum(f.history.values()) == 20 and f.history.get("history_refused"), report
    assert f.checks["the /tf_static history taken and refused as predicted"], report
    assert f.checks["a genuine GetPlan is answered with the planner's path after the fuzz"]
    assert f.plan_replies["ok"] > 0 and f.plan_replies["err"] > 0 and not f.plan_replies["none"]


def _misuse(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as e:
        cli(list(argv))
    assert e.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("smana bench fuzz"), lines
    return lines[0]


def test_bench_fuzz_with_nothing_to_fuzz_is_one_line_and_exit_2(capsys):
    assert "nothing to fuzz" in _misuse(capsys, "--inputs", "0", "--map-files", "0", "--ros2", "0")


def test_bench_fuzz_ros2_without_rosbags_is_one_line_and_exit_2(capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "rosbags", None)  # hidden, as Python hides a module
    line = _misuse(capsys, "--inputs", "0", "--map-files", "0", "--ros2", "10")
    assert "pip install 'smana[ros2]'" in line and "--ros2 0" in line


@pytest.mark.multiprocess
@pytest.mark.slow
def test_bench_fuzz_ros2_flag_runs_the_family_alone(tmp_path, capsys):
    import json

    code = cli(["--inputs", "0", "--map-files", "0", "--ros2", "200", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    (run,) = tmp_path.iterdir()
    result = json.loads((run / "fuzz.json").read_text())
    ros2 = result["ros2"]
    # 200 fuzzed, 4 to establish the track, genuine odometry and one GetPlan after
    assert result["ok"] and 200 + 4 + 2 <= ros2["inputs"] <= 200 + 4 + 15, out
    assert ros2["rejected"]["oversize"] == 4, out  # --oversize 6: one per ROS 2 key
    assert f"ROS 2 family: {ros2['inputs']} inputs" in out and result["keys"] == {}, out
