"""The generated references are current: docs/reference/config.md (every config key) and
docs/reference/cli.md (every command's options) are what `python -m smana.lab.docs_reference`
makes from the code now. A new key, a changed default, a reworded comment or `--help` text fails
here until the pages are written again."""

from __future__ import annotations

import argparse
import dataclasses

from smana.common.config import SmanaConfig
from smana.common.config.section import items
from smana.lab import docs_cli_reference, docs_reference
from tests.conftest import REPO


def test_the_committed_references_are_what_the_code_generates():
    stale = [
        str(path)
        for path, text in docs_reference.pages().items()
        if not (REPO / path).is_file() or (REPO / path).read_text() != text
    ]
    assert not stale, f"stale: {', '.join(stale)}; run `{docs_reference.COMMAND}` and commit them"


def _keys(section, where: str):
    for name, value in items(section):
        if dataclasses.is_dataclass(value):
            yield from _keys(value, f"{where}.{name}")
        else:
            yield f"{where}.{name}"


def test_every_config_key_is_in_the_reference():
    page = docs_reference.config_reference()
    config = SmanaConfig()
    missing = []
    for f in dataclasses.fields(config):
        for key in _keys(getattr(config, f.name), f.name):
            parts = key.split(".")
            if parts[0] == "deploy" and len(parts) == 3:  # [deploy.<service>] is one table
                key = f"deploy.<service>.{parts[2]}"
            if f"| `{key}` |" not in page:
                missing.append(key)
    assert not missing, missing


def _row(page: str, key: str) -> list[str]:
    line = next(line for line in page.splitlines() if line.startswith(f"| `{key}` |"))
    return [c.strip() for c in line.strip("|").split(" | ")]


def test_types_ranges_units_and_meanings_come_from_the_code():
    page = docs_reference.config_reference()
    assert _row(page, "mapper.resolution_m")[1:5] == ["float", "`0.1`", "(0, 10.0]", "m"]
    assert _row(page, "sim.noise")[3] == "`off`, `none`, `low`, `medium`, `high`, `realistic`"
    # a key with no comment of its own: the sentence of another comment that names it
    assert "falling linearly to 0 at clearance_m" in _row(page, "planner.clearance_m")[5]
    readers = page.split("## [planner]")[1].split("Read by: ")[1].split(".\n")[0]
    assert {"`planner`", "`explorer`"} <= set(readers.split(", ")), readers
    # through common/geometric.py, which the replay and ros2 services import
    geometric = page.split("## [geometric]")[1].split("Read by: ")[1].split(".\n")[0]
    assert geometric == "`replay`, `ros2`", geometric


def test_comments_are_read_above_beside_and_continued():
    assert docs_reference._comments(_Toy) == {
        "a_m": "above it; beside it",
        "b_s": "one sentence (that goes on over two lines)",
        "e": "A sentence that names c: found by name.",
        "c": "A sentence that names c: found by name.",
        "d": "",
    }
    assert docs_reference.unit_of("a_m", "") == "m"
    assert docs_reference.unit_of("speed_mps", "") == "m/s"
    assert docs_reference.unit_of("cell", "side of a cell, m") == "m"


@dataclasses.dataclass
class _Toy:
    # above it
    a_m: float = 1.0  # beside it
    b_s: float = 2.0  # one sentence (that goes on
    # over two lines)
    # A sentence that names c: found by name.
    e: int = 0
    c: int = 0
    d: int = 0


def test_the_cli_reference_has_every_command_and_option():
    page = docs_cli_reference.cli_reference()
    for name, (target, _) in docs_cli_reference.commands().items():
        assert f"## `smana {name}`" in page, name
        parser = docs_cli_reference.parser_of(target) if name != "bench" else None
        for action in getattr(parser, "_actions", []):
            if isinstance(action, argparse._HelpAction) or not action.option_strings:
                continue
            assert f"`{action.option_strings[0]}`" in page, (name, action.option_strings)
    assert "## `smana bench`" in page and "### `smana bench planner`" in page
    assert "/work/" not in page and str(REPO) not in page  # defaults made relative
