"""`smana bench fuzz --campaign`/`--quick`: every input of every family ends in one counter, a
crash, a dead worker or a hang is counted and fails the run, and a campaign goes on where it
stopped (lab/bench/fuzz_campaign.py)."""

from __future__ import annotations

import json

import msgpack

from smana.lab.bench import fuzz_campaign as fc
from smana.lab.bench import fuzz_families as ff
from smana.lab.bench.fuzz import cli

QUICK = fc.QUICK_INPUTS


def _run(capsys, *argv: str) -> tuple[int, dict, str]:
    rc = cli(["--quick", *argv])
    out = capsys.readouterr().out
    written = out.rsplit("written: ", 1)[1].strip()
    return rc, json.loads(open(written).read()), out


def _families_add_up(s: dict) -> None:
    for name in fc.FAMILIES:
        f = s["families"][name]
        assert f["inputs"] == f["planned"] == QUICK, name
        total = f["accepted"] + sum(f["rejected"].values()) + f["crash"] + f["hang"]
        assert total == QUICK and f["adds_up"], name


def test_the_quick_campaign_crosses_every_family_with_no_crash(tmp_path, capsys):
    rc, s, out = _run(capsys, "--out", str(tmp_path), "--chunk", "8")
    assert rc == 0 and s["ok"], out
    _families_add_up(s)
    assert all(s["families"][f]["crash"] == s["families"][f]["hang"] == 0 for f in fc.FAMILIES)
    # both fates are reached where 16 inputs are enough to say so
    for name in ("messages", "map_files", "journals", "blocks", "ros2_actions", "bridge_smana"):
        f = s["families"][name]
        assert sum(f["rejected"].values()) > 0, name


def test_planted_crash_dead_worker_and_hang_are_counted_and_fail_the_run(tmp_path, capsys):
    plant = "keys:2:crash,journals:5:abort,blocks:9:hang"
    rc, s, out = _run(
        capsys, "--out", str(tmp_path), "--chunk", "8", "--hang-s", "5", "--plant", plant
    )
    assert rc == 1 and not s["ok"] and "FAILED" in out
    _families_add_up(s)  # the chunk went on after each: every input still ends in one counter
    fam = s["families"]
    assert (fam["keys"]["crash"], fam["journals"]["crash"], fam["blocks"]["hang"]) == (1, 1, 1)
    assert any("keys #2: crash: RuntimeError: planted crash" in n for n in s["notes"])
    assert any("journals #5: crash: the worker died" in n for n in s["notes"])
    assert any("blocks #9: hang" in n for n in s["notes"])
    # resumable: a lost chunk is run again, the others are kept as they are
    run_dir = next(tmp_path.glob("campaign-*"))
    chunks = run_dir / "chunks"
    kept = {p.name: p.read_text() for p in chunks.iterdir()}
    (chunks / "bridge_smana-8.jsonl").unlink()
    rc = cli(["--resume", str(run_dir)])
    assert rc == 1  # the planted faults are still in the books
    s = json.loads((run_dir / "campaign.json").read_text())
    _families_add_up(s)
    assert {
        p.name: p.read_text() for p in chunks.iterdir() if p.name != "bridge_smana-8.jsonl"
    } == {k: v for k, v in kept.items() if k != "bridge_smana-8.jsonl"}
    assert "ETA" in capsys.readouterr().err


def test_a_goal_of_one_number_in_an_explorer_state_is_refused_by_the_bridge():
    # found by the campaign: it reached convert.pose_stamped and failed there (internal)
    svc = ff._bridge()
    state = msgpack.packb({"goal": {"xy": [1.0]}, "path": [[0.0, 0.0]], "t_s": 1.0})
    for body in (state, msgpack.packb({"goal": {"xy": [1.0, float("nan")]}, "t_s": 1.0})):
        with svc.books.lock:
            svc.books.received += 1
            svc.books.in_flight += 1
        svc._handle_payload(svc.on_explorer_state, None, body, False)
    assert svc.books.rejected == {"value": 2}
