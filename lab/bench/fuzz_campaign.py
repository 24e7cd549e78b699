"""`smana bench fuzz --campaign N`: one command, N inputs over every family, in this machine's
processes, with books that must add up.

Families (`FAMILIES`; their classes are fuzz_families.py's), each input generated from (`--seed`,
family, index) alone, so any input can be made again and a campaign can stop and go on (`--resume`):

- `keys`: zenoh key expressions and selectors (wild chunks, `*`, `**`, `$*`, empty chunks,
  parameters, unicode, 10 kB), parsed as zenoh and a service do (`KeyExpr`, `Selector`, its
  parameters); a name smana accepts (`keys.check_name`) must make keys zenoh accepts;
- `messages`: smana's own messages (`lab/fuzz_messages.py`: valid, hostile, mutated msgpack and
  JSON) into the codec, as every service decodes them;
- `map_files`: valid and corrupt map files (`lab/fuzz_maps.py`) loaded as the mapper loads one; a
  file known to be corrupt must be refused, a loaded one must equal the file as saved;
- `journals`: the mapper's crash journal cut, bit-flipped or with a crafted record whose checksum
  holds (`lab/fuzz_journals.py`), replayed; every byte must end in the reader's books;
- `blocks`: block-store region files damaged, read back as the store reads one;
- `ros2_topics`: hostile `/odom`, `/points`, `/tf_static` and GetPlan requests
  (`lab/fuzz_ros2.py`) into the ROS 2 bridge's cores;
- `ros2_actions`: NavigateToPose and ComputePathToPose send_goal / cancel_goal / get_result
  requests (genuine, wild poses and frames, cut or flipped CDR, bad attachments) into the bridge's
  action server, the explorer and planner answering in this process;
- `bridge_smana`: smana's own messages (velocity commands for `/cmd_vel`, poses, map deltas,
  graph patches, explorer states), valid and hostile, into the bridge's handlers through the
  service's own decode-and-settle path.

Every input ends in exactly one counter: `accepted`, `rejected:<reason>`, `crash` (an exception
the target does not own, a wrong verdict, books that moved by other than one) or `hang` (no
answer within `--hang-s`). Inputs run in chunks (`--chunk`), each in a worker process of its own
under this one: a worker that dies or stops answering costs the input it was on (counted crash or
hang) and the chunk goes on after it in a new worker. Exit status 1 when anything crashed or
hung, or a family's counters do not add up to its inputs.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from smana.lab.bench.fuzz_families import TARGETS, Rejected, draw_for

FAMILIES = (
    "keys",
    "messages",
    "map_files",
    "journals",
    "blocks",
    "ros2_topics",
    "ros2_actions",
    "bridge_smana",
)
QUICK_INPUTS = 16  # per family with --quick
DEFAULT_CHUNK = 500


# -- the families -----------------------------------------------------------------------------
# Each is a class built once per worker (`setup` costs are paid per chunk) whose `run(i, d)`
# returns None (accepted) or raises Rejected; anything else it raises is a crash.

# -- the worker: one chunk of one family, a line per input ----------------------------------------


def worker(family: str, start: int, stop: int, seed: int, out: Path, plant: str = "") -> int:
    """Run inputs [start, stop) of `family`, appending one JSON line per input to `out`.
    `plant` (the tests): comma-separated FAMILY:I:crash|abort|hang, a fault planted at input I."""
    plants = [p for p in plant.split(",") if p]
    import tempfile

    with tempfile.TemporaryDirectory(prefix=f"smana-campaign-{family}-") as tmp:
        target = TARGETS[family](seed, tmp)
        with open(out, "a") as f:
            for i in range(start, stop):
                print(json.dumps({"start": i}), file=f, flush=True)
                planted = {p.rsplit(":", 1)[1] for p in plants if p.startswith(f"{family}:{i}:")}
                if "abort" in planted:
                    os.abort()
                if "hang" in planted:
                    time.sleep(3600)
                try:
                    if "crash" in planted:
                        raise RuntimeError("planted crash")
                    target.run(i, draw_for(seed, family, i))
                except Rejected as exc:
                    fate, note = "rejected:" + exc.reason, ""
                except Exception as exc:  # noqa: BLE001 - what the campaign is for: counted
                    fate, note = "crash", f"{type(exc).__name__}: {exc}"[:300]
                else:
                    fate, note = "accepted", ""
                print(json.dumps({"i": i, "fate": fate, "note": note}), file=f, flush=True)
    return 0


# -- the parent: plan, chunks, resume, books ----------------------------------------------------


def plan(total: int, chunk: int) -> list[tuple[str, int, int]]:
    """(family, start, stop) chunks: `total` inputs shared evenly over the families."""
    per = [total // len(FAMILIES) + (k < total % len(FAMILIES)) for k in range(len(FAMILIES))]
    return [
        (fam, s, min(s + chunk, n))
        for fam, n in zip(FAMILIES, per, strict=True)
        for s in range(0, n, chunk)
    ]


def read_chunk(path: Path) -> tuple[dict[int, dict], int | None]:
    """The inputs a chunk file settled, and the one begun last and never settled (or None)."""
    done: dict[int, dict] = {}
    begun = None
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:  # a line cut by a kill
                continue
            if "start" in rec:
                begun = rec["start"]
            else:
                done[rec["i"]] = rec
    return done, (begun if begun is not None and begun not in done else None)


def _settle_lost(path: Path, i: int, fate: str, note: str) -> None:
    with open(path, "a") as f:
        print(json.dumps({"i": i, "fate": fate, "note": note}), file=f, flush=True)


def run_chunk(
    family: str, start: int, stop: int, seed: int, path: Path, hang_s: float, plant: str
) -> None:
    """Run a chunk to its end, a new worker after each input that killed or hung one."""
    while True:
        done, lost = read_chunk(path)
        if lost is not None:  # the last worker died or was killed on it
            _settle_lost(path, lost, "crash", "the worker died on this input")
            done[lost] = {}
        todo = [i for i in range(start, stop) if i not in done]
        if not todo:
            return
        argv = [sys.executable, "-m", "smana.lab.bench.fuzz_campaign", "--worker", family]
        argv += [str(todo[0]), str(stop), str(seed), str(path), plant]
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, start_new_session=True)
        last, size = time.monotonic(), -1
        while proc.poll() is None:
            time.sleep(0.2)
            now_size = path.stat().st_size if path.exists() else 0
            if now_size != size:
                last, size = time.monotonic(), now_size
            elif time.monotonic() - last > hang_s:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                _, lost = read_chunk(path)
                if lost is not None:
                    _settle_lost(path, lost, "hang", f"no answer within {hang_s:g} s")
                break


def summary(run_dir: Path, chunks: list[tuple[str, int, int]]) -> dict:
    fams: dict[str, dict] = {
        f: {"planned": 0, "inputs": 0, "accepted": 0, "rejected": Counter(), "crash": 0, "hang": 0}
        for f in FAMILIES
    }
    notes = []
    for fam, start, stop in chunks:
        f = fams[fam]
        f["planned"] += stop - start
        done, _ = read_chunk(run_dir / "chunks" / f"{fam}-{start}.jsonl")
        for i, rec in done.items():
            if not start <= i < stop:
                continue
            f["inputs"] += 1
            fate = rec["fate"]
            if fate == "accepted":
                f["accepted"] += 1
            elif fate.startswith("rejected:"):
                f["rejected"][fate.split(":", 1)[1]] += 1
            else:
                f[fate] += 1
                if len(notes) < 50:
                    notes.append(f"{fam} #{i}: {fate}: {rec.get('note', '')}")
    for f in fams.values():
        f["adds_up"] = (
            f["inputs"]
            == f["planned"]
            == (f["accepted"] + sum(f["rejected"].values()) + f["crash"] + f["hang"])
        )
    ok = all(f["adds_up"] and not f["crash"] and not f["hang"] for f in fams.values())
    return {"ok": ok, "families": fams, "notes": notes}


def table(s: dict) -> str:
    rows = ["| family | inputs | accepted | rejected | crash | hang | adds up | top reasons |"]
    rows.append("|---|---:|---:|---:|---:|---:|---|---|")
    tot = Counter()
    for name, f in s["families"].items():
        rej = sum(f["rejected"].values())
        top = ", ".join(f"{k} {v}" for k, v in f["rejected"].most_common(3))
        rows.append(
            f"| {name} | {f['inputs']} | {f['accepted']} | {rej} | {f['crash']} | {f['hang']} | "
            f"{'yes' if f['adds_up'] else 'NO'} | {top} |"
        )
        tot.update(inputs=f["inputs"], accepted=f["accepted"], rejected=rej)
        tot.update(crash=f["crash"], hang=f["hang"])
    rows.append(
        f"| all | {tot['inputs']} | {tot['accepted']} | {tot['rejected']} | {tot['crash']} | "
        f"{tot['hang']} | | |"
    )
    return "\n".join(rows + [f"- {n}" for n in s["notes"]])


def campaign(
    run_dir: Path,
    total: int,
    seed: int = 0,
    chunk: int = DEFAULT_CHUNK,
    hang_s: float = 60.0,
    plant: str = "",
    progress=print,
) -> dict:
    """Run (or go on with) the campaign in `run_dir`; returns the summary (also campaign.json)."""
    (run_dir / "chunks").mkdir(parents=True, exist_ok=True)
    spec = {"total": total, "seed": seed, "chunk": chunk}
    spec_path = run_dir / "campaign-spec.json"
    if spec_path.exists() and json.loads(spec_path.read_text()) != spec:
        raise ValueError(f"{run_dir} holds another campaign: {spec_path.read_text().strip()}")
    spec_path.write_text(json.dumps(spec) + "\n")
    chunks = plan(total, chunk)
    t0, at_start = time.monotonic(), None
    last_print = 0.0
    for fam, start, stop in chunks:
        path = run_dir / "chunks" / f"{fam}-{start}.jsonl"
        done, _ = read_chunk(path)
        if len(done) < stop - start:
            run_chunk(fam, start, stop, seed, path, hang_s, plant)
        settled = sum(
            len(read_chunk(run_dir / "chunks" / f"{f}-{s}.jsonl")[0]) for f, s, _ in chunks
        )
        if at_start is None:
            at_start = settled - len(read_chunk(path)[0])
        now = time.monotonic()
        if now - last_print >= 2.0 or settled == total:
            last_print = now
            rate = (settled - at_start) / max(now - t0, 1e-9)
            eta = (total - settled) / rate if rate > 0 else float("inf")
            progress(
                f"{settled}/{total} inputs ({100 * settled / max(total, 1):.0f} %), "
                f"{rate:.0f}/s, ETA {_duration(eta)} (last: {fam} {start}..{stop})"
            )
    s = summary(run_dir, chunks)
    s["seconds"] = round(time.monotonic() - t0, 1)
    (run_dir / "campaign.json").write_text(json.dumps(s, indent=1, default=dict) + "\n")
    return s


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min" if s >= 3600 else f"{s:.0f} s"


if __name__ == "__main__" and sys.argv[1:2] == ["--worker"]:
    fam, a, b, sd, out = sys.argv[2:7]
    sys.exit(
        worker(fam, int(a), int(b), int(sd), Path(out), sys.argv[7] if len(sys.argv) > 7 else "")
    )
