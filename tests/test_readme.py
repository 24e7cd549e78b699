"""The README's command examples work, read from the README itself.

Every `smana ...` command in a fenced shell block is either run or parsed:
- run: `--help`, `smana status` (against nothing: exits with its one-line message), `smana world
  info`, and `smana plan` against navgraph + planner processes on an isolated zenoh, fed the
  default world's ground truth (the world `smana up` explores) as one map delta;
- parsed: the long ones (`smana up`, experiments, replays, benchmarks, the viewer): the
  command's own argument parser accepts the flags used, and nothing runs.
The set-up commands around them (`python3 -m venv`, `pip install`, `python -m pytest`) are not run.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest

from smana.common import keys
from smana.common.messages import MapDelta, encode
from smana.common.query import request
from smana.common.zenoh_config import free_loopback_port
from smana.deploy.cli import COMMANDS
from smana.lab.bench import BENCHES
from tests.conftest import REPO, wait_for

README = REPO / "README.md"
SHELL_LANGS = {"bash", "sh", "shell", "console"}
FENCE = re.compile(r"^```(\w*)\s*$")
# The ground truth below this height is what a ground robot meets: tree crowns overhead would
# otherwise become obstacle nodes under them (the graph keeps a column's highest voxel).
GROUND_TRUTH_MAX_Z_M = 1.0
VOXEL_M = 0.1


def shell_blocks(text: str) -> list[str]:
    """The lines of the README's fenced shell blocks, continuation lines joined."""
    lines, lang = [], None
    for line in text.splitlines():
        m = FENCE.match(line.strip())
        if m:
            lang = (m.group(1) or "") if lang is None else None
            continue
        if lang in SHELL_LANGS:
            if lines and lines[-1].endswith("\\"):
                lines[-1] = lines[-1][:-1] + " " + line.strip()
            else:
                lines.append(line.strip())
    return [line for line in lines if line]


def smana_commands(text: str) -> list[tuple[str, list[str]]]:
    """(the README line, argv after `smana`) for every smana command; `[--flag]` counts as used."""
    out = []
    for line in shell_blocks(text):
        words = shlex.split(line.replace("[", "").replace("]", ""), comments=True)
        command: list[str] = []
        for w in [*words, "&&"]:
            if w in ("&&", "||", ";", "|"):
                if command and command[0].rsplit("/", 1)[-1] == "smana":
                    out.append((line, command[1:]))
                command = []
            else:
                command.append(w)
    return out


COMMANDS_IN_README = smana_commands(README.read_text())


def is_run(argv: list[str]) -> bool:
    return (
        "--help" in argv
        or "-h" in argv
        or argv[:1] in (["status"], ["plan"])
        or argv[:2] == ["world", "info"]
    )


class _Parsed(Exception):
    pass


def parse_only(argv: list[str]) -> argparse.Namespace:
    """Hand `argv` to the command's own `cli` and stop it as soon as its parser accepted them."""
    if argv[0] == "bench":
        target, rest = BENCHES[argv[1]], argv[2:]
    else:
        target, rest = COMMANDS[argv[0]][0], argv[1:]
    module, func = target.split(":")
    cli = getattr(importlib.import_module(module), func)
    original = argparse.ArgumentParser.parse_args

    def parse_args(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    argparse.ArgumentParser.parse_args = parse_args
    try:
        cli(rest)
    except _Parsed as parsed:
        return parsed.args[0]
    except SystemExit as exc:
        pytest.fail(f"`smana {' '.join(argv)}`: the parser refused it (exit {exc.code})")
    finally:
        argparse.ArgumentParser.parse_args = original
    pytest.fail(f"`smana {' '.join(argv)}` returned without parsing any arguments")


def smana(*argv: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "smana.deploy.cli", *argv],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
    )


def test_the_readme_has_the_examples_this_test_checks():
    assert [line for line in shell_blocks("```bash\nsmana up \\\n  --set a=1\n```\n")] == [
        "smana up  --set a=1"
    ]
    assert smana_commands("```bash\npython -m venv v && v/bin/smana up  # go\n```") == [
        ("python -m venv v && v/bin/smana up  # go", ["up"])
    ]
    run = [argv for _, argv in COMMANDS_IN_README if is_run(argv)]
    assert len(COMMANDS_IN_README) >= 20
    assert sum(argv[0] == "plan" for argv in run) >= 2  # a path, and a negative coordinate
    assert any(argv[0] == "status" for argv in run) and ["world", "info"] in run


LONG = [c for c in COMMANDS_IN_README if not is_run(c[1])]


@pytest.mark.parametrize("line,argv", LONG, ids=[" ".join(argv)[:60] for _, argv in LONG])
def test_long_commands_parse(line, argv):
    assert argv[0] in COMMANDS, f"{line}: no command {argv[0]!r}"
    if argv[0] == "bench":
        assert argv[1] in BENCHES, f"{line}: no benchmark {argv[1]!r}"
    parse_only(argv)


def test_quick_commands_run():
    ran = 0
    for line, argv in COMMANDS_IN_README:
        if not is_run(argv) or argv[0] == "plan":
            continue
        if argv[0] == "status":  # against nothing: a port where no router listens
            port = free_loopback_port()
            argv = [*argv, "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
        out = smana(*argv)
        where = f"`{line}`: exit {out.returncode}\n{out.stdout}\n{out.stderr}"
        assert "Traceback" not in out.stderr, where
        if argv[0] == "status":
            assert out.returncode == 2, where
            assert len(out.stderr.strip().splitlines()) == 1 and "smana up" in out.stderr, where
        else:
            assert out.returncode == 0, where
            if argv[:2] == ["world", "info"]:
                assert json.loads(out.stdout)["bounds"], where
            else:
                assert "usage" in (out.stdout + out.stderr).lower(), where
        ran += 1
    assert ran >= 3


def default_world_delta() -> MapDelta:
    """The default world's ground truth below GROUND_TRUTH_MAX_Z_M, as one map delta of
    VOXEL_M voxels: the map `smana up`'s mapper converges to."""
    from smana.common.classes import ClassTable
    from smana.common.config import SmanaConfig
    from smana.services.sim.worlds import build_world

    cfg = SmanaConfig.load()
    world = build_world(cfg.sim, ClassTable.load(cfg.general.class_table))
    points, labels = world.gt_cloud(VOXEL_M / 2)
    low = points[:, 2] < GROUND_TRUTH_MAX_Z_M
    cells, first = np.unique(
        np.floor(points[low] / VOXEL_M).astype(np.int64), axis=0, return_index=True
    )
    n = len(cells)
    return MapDelta(
        stamp_s=1.0,
        seq=1,
        cloud_seq=1,
        backend="octree-max",
        resolution_m=VOXEL_M,
        centres=((cells + 0.5) * VOXEL_M).astype(np.float32),
        labels=labels[low][first].astype(np.uint16),
        confidences=np.ones(n, np.float32),
        occupied=np.ones(n, np.uint8),
        values=np.full(n, 2.0, np.float32),
    )


@pytest.mark.multiprocess
def test_plan_examples_find_a_path_in_the_default_world(zenoh_stack):
    stack = zenoh_stack
    plans = [(line, argv) for line, argv in COMMANDS_IN_README if argv[0] == "plan"]
    stack.service("navgraph")
    stack.service("planner")
    delta = default_world_delta()
    stack.wait_alive("navgraph")
    stack.wait_alive("planner")
    stack.publisher(keys.map_delta(stack.robot)).put(encode(delta))

    def stats(service):
        return request(stack.session, keys.query(stack.robot, service, "stats"), timeout_s=5)

    assert wait_for(lambda: stats("navgraph")["deltas"] == 1)
    graph_seq = stats("navgraph")["patch_seq"]
    assert wait_for(lambda: stats("planner")["last_patch_seq"] == graph_seq)
    for line, argv in plans:
        out = smana(*argv, *stack.zenoh_args(), "--robot", stack.robot)
        assert out.returncode == 0, f"`{line}`: exit {out.returncode}\n{out.stdout}{out.stderr}"
        assert out.stdout.startswith("path: "), out.stdout


TUTORIAL = REPO / "docs" / "tutorial.md"
COMMANDS_IN_TUTORIAL = smana_commands(TUTORIAL.read_text())


def test_the_tutorial_walks_through_every_step():
    steps = {
        argv[0] if argv[0] != "bench" else f"bench {argv[1]}" for _, argv in COMMANDS_IN_TUTORIAL
    }
    assert {"up", "view", "plan", "world", "experiment", "bench replay", "replay"} <= steps


@pytest.mark.parametrize(
    "line,argv", COMMANDS_IN_TUTORIAL, ids=[" ".join(a)[:60] for _, a in COMMANDS_IN_TUTORIAL]
)
def test_tutorial_commands_parse(line, argv):
    """Every command of docs/tutorial.md is one its command's parser accepts (the pictures were
    made by running them; the README's test runs the quick ones)."""
    assert argv[0] in COMMANDS, f"{line}: no command {argv[0]!r}"
    parse_only(argv)
