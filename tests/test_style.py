"""The house style holds: ruff (pinned in pyproject.toml) finds nothing to lint and nothing to
reformat, so a contributor's `ruff format` never rewrites someone else's lines; and no test waits
by the clock where it can wait for an event."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["lint", "format"])
def test_ruff_finds_nothing_to_change(command):
    out = subprocess.run(
        [sys.executable, "-m", "ruff", *command, "."],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr


# A test waits for an event (a status, a delta, a declaration seen: tests/conftest.py `wait_for`,
# `ZenohStack.publisher` / `subscriber`), never for a fixed time. A sleep inside a loop polls or
# paces a publisher; one marked `# simulated work` stands for a slow handler.
WORK_MARK = "# simulated work"


def settle_sleeps(source: str) -> list[int]:
    """The lines of `sleep(...)` calls that no loop of their own function encloses and that are
    not marked as simulated work."""
    tree = ast.parse(source)
    lines = source.splitlines()
    parent = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        if name != "sleep" or WORK_MARK in lines[node.lineno - 1]:
            continue
        up, in_loop = node, False
        while up in parent and not in_loop:
            up = parent[up]
            if isinstance(up, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef):
                break
            in_loop = isinstance(up, ast.For | ast.While | ast.AsyncFor | ast.comprehension)
        if not in_loop:
            found.append(node.lineno)
    return found


def test_the_settle_sleep_finder_tells_a_wait_from_a_poll():
    src = (
        "import time\n"
        "def settle():\n"
        "    time.sleep(0.3)\n"  # line 3: a fixed wait
        "def poll(pred):\n"
        "    while not pred():\n"
        "        time.sleep(0.05)\n"  # polling: fine
        "    for _ in range(3):\n"
        "        def later():\n"
        "            sleep(1)\n"  # line 9: its own function has no loop
        "    time.sleep(0.2)  # simulated work\n"
    )
    assert settle_sleeps(src) == [3, 9]


def test_no_test_waits_by_the_clock():
    bare = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in sorted((ROOT / "tests").rglob("*.py"))
        for line in settle_sleeps(path.read_text())
    ]
    assert not bare, f"fixed settle-sleeps (wait for an event instead): {bare}"
