"""The house style holds: ruff (pinned in pyproject.toml) finds nothing to lint and nothing to
reformat, so a contributor's `ruff format` never rewrites someone else's lines; no test waits by
the clock where it can wait for an event; no product file is longer than a newcomer can read
(MAX_LINES); and no private name (a leading underscore) is imported across modules."""

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


# -- the product's files: short, and what they share is public ----------------------------------
# The product is every Python file the wheel ships (setup.py's four folders); the tests are not.
PRODUCT = ("common", "services", "deploy", "lab")
MAX_LINES = 600
# Files still over MAX_LINES, to be split by idea. The list may only shrink: a file that is
# split (or gone) must leave it, and no other file may join it.
STILL_LONG = {
    "lab/bench/fuzz.py",
    "lab/fuzz_messages.py",
}
# The API of a named tuple, whose names start with an underscore so as not to clash with fields.
NAMED_TUPLE_API = {"_fields", "_replace", "_asdict", "_make", "_field_defaults"}


def product_files() -> list[Path]:
    return [p for d in PRODUCT for p in sorted((ROOT / d).rglob("*.py"))]


def test_no_product_file_is_over_the_line_limit():
    files = product_files()
    assert len(files) > 200  # the scan found the product
    lengths = {p.relative_to(ROOT).as_posix(): len(p.read_text().splitlines()) for p in files}
    long = {f for f, n in lengths.items() if n > MAX_LINES}
    new = sorted(f"{f} ({lengths[f]} lines)" for f in long - STILL_LONG)
    assert not new, f"over {MAX_LINES} lines (split it by idea): {new}"
    done = sorted(STILL_LONG - long)
    assert not done, f"no longer over {MAX_LINES} lines (take them off STILL_LONG): {done}"


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports(source: str, module: str) -> list[str]:
    """Where `source` (the module `module`, e.g. `smana.services.mapper.service`; a package's
    `__init__` is the package) takes a private name from another smana module: `from m import
    _x`, a module path with a private part (`m._grid`), or `m._x` on a name it imported from
    smana. (A private name used inside its own module is what private means.)"""
    tree = ast.parse(source)
    package = module.rsplit(".", 1)[0]
    found, bound = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("smana."):
                    if any(_private(part) for part in a.name.split(".")):
                        found.append(f"{node.lineno}: import {a.name}")
                    bound.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom):
            name = node.module or ""
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                name = ".".join(base + ([name] if name else []))
            if not name.startswith("smana"):
                continue
            if any(_private(part) for part in name.split(".")):
                found.append(f"{node.lineno}: from {name} import ...")
            for a in node.names:
                if _private(a.name):
                    found.append(f"{node.lineno}: from {name} import {a.name}")
                bound.add(a.asname or a.name)
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and _private(node.attr)
            and node.attr not in NAMED_TUPLE_API
            and isinstance(node.value, ast.Name)
            and node.value.id in bound
        ):
            found.append(f"{node.lineno}: {node.value.id}.{node.attr}")
    return found


def test_the_private_import_finder_sees_each_form():
    src = (
        "from smana.services.mapper.journal import _FRAME, frame\n"  # line 1: _FRAME
        "from smana.services.mapper._grid import OBSERVED\n"  # line 2: a private module
        "from .kernels import _step\n"  # line 3: relative
        "from smana.lab.experiments import exploration as ex\n"
        "import smana.common.query as q\n"
        "ex._load(1)\n"  # line 6: through a module
        "q._parse(b'')\n"  # line 7
        "def f(self, t):\n"
        "    self._x = t._fields\n"  # own attributes and a named tuple's API: fine
        "    from smana.services.mapper.journal import __doc__\n"  # a dunder: fine
    )
    found = [hit.split(":")[0] for hit in private_imports(src, "smana.services.explorer.frontier")]
    assert found == ["1", "2", "3", "6", "7"], found


def test_no_private_name_is_imported_across_modules():
    found = []
    for path in product_files():
        rel = path.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        module = ".".join(["smana", *parts])
        if rel.name == "__init__":
            module += ".__init__"  # its relative imports start from the package itself
        found += [
            f"{path.relative_to(ROOT)}:{hit}" for hit in private_imports(path.read_text(), module)
        ]
    assert not found, "private names imported across modules (make them public):\n" + "\n".join(
        found
    )
