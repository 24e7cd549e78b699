"""docs/promises.md cannot rot: every test it names exists (its module imports and defines the
function; nothing is run), every quoted sentence is still in the document its table is for, and
every row either names a test, waits for a named change ("pending"), was corrected into a
measurement ("—"), or is an open gap ("open:", marked **open**)."""

from __future__ import annotations

import importlib
import re

import pytest

from tests.conftest import REPO

PROMISES = REPO / "docs" / "promises.md"
# The tables: heading -> the document its quotes come from (None: the --help texts).
DOCUMENTS = {
    "README.md": REPO / "README.md",
    "docs/tutorial.md": REPO / "docs" / "tutorial.md",
    "docs/deployment.md": REPO / "docs" / "deployment.md",
    "docs/ros2.md": REPO / "docs" / "ros2.md",
    "docs/risk.md": REPO / "docs" / "risk.md",
    "`--help` texts": None,
}
TEST_ID = re.compile(r"`(tests/[\w/]+\.py)::(\w+)(\[[^\]`]*\])?`")
QUOTE = re.compile(r"“([^”]+)”")


def rows() -> list[tuple[str, str, str, str]]:
    """(table heading, sentence cell, test cell, what-it-checks cell) of every table row."""
    out, heading = [], None
    for line in PROMISES.read_text().splitlines():
        if line.startswith("## "):
            heading = line[3:].strip()
        elif line.startswith("|") and heading in DOCUMENTS:
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            if cells[0] in ("sentence", "---") or set(line) <= set("|- "):
                continue
            assert len(cells) == 3, f"{heading}: a row of {len(cells)} cells: {line}"
            out.append((heading, *cells))
    return out


ROWS = rows()


def flat(text: str) -> str:
    return " ".join(text.split())


def test_every_document_has_its_table():
    headings = {h for h, *_ in ROWS}
    assert headings == set(DOCUMENTS), set(DOCUMENTS) - headings
    assert len(ROWS) >= 100


def exists(path: str, name: str) -> bool:
    module = importlib.import_module(path.removesuffix(".py").replace("/", "."))
    return callable(getattr(module, name, None))


@pytest.mark.parametrize("heading,sentence,tests,checks", ROWS, ids=[r[1][:50] for r in ROWS])
def test_each_row_names_a_test_that_exists_or_says_why_not(heading, sentence, tests, checks):
    ids = TEST_ID.findall(tests)
    if tests.startswith("pending: rewrite"):
        assert not ids, "a pending row names no test; its section is being rewritten"
        return
    if tests == "—":
        assert "**corrected**" in sentence, (
            "only a sentence corrected into a measurement has no test"
        )
        return
    if tests.startswith("pending: lead"):
        for path, name, _ in ids:
            assert (REPO / path).is_file() is False or not exists(path, name), (
                f"{path}::{name} exists now: drop 'pending: lead' from this row"
            )
        return
    if tests.startswith("open:"):
        assert "**open**" in sentence and not ids, "an open row is marked so and names no test"
        return
    if tests.startswith("`.ci/"):
        assert (REPO / tests.strip("`")).is_file(), tests
        return
    assert ids, f"no test named: {tests!r}"
    for path, name, _ in ids:
        assert (REPO / path).is_file(), f"no file {path}"
        assert exists(path, name), f"{path} has no test {name}"
    assert checks, "say what the test checks"


@pytest.mark.parametrize(
    "heading,sentence", [(h, s) for h, s, *_ in ROWS if DOCUMENTS[h] is not None]
)
def test_each_quoted_sentence_is_still_in_its_document(heading, sentence):
    quotes = QUOTE.findall(sentence)
    if not quotes:
        assert sentence.startswith("(the same sentence)"), f"quote the sentence: {sentence}"
        return
    text = flat(DOCUMENTS[heading].read_text())
    for quote in quotes:
        assert flat(quote) in text, f"{heading} no longer says: {quote}"


def test_the_parser_finds_ids_and_quotes():
    cell = "`tests/test_a.py::test_b`<br>`tests/test_c.py::test_d[x-1]`"
    assert [(p, n) for p, n, _ in TEST_ID.findall(cell)] == [
        ("tests/test_a.py", "test_b"),
        ("tests/test_c.py", "test_d"),
    ]
    assert QUOTE.findall("**corrected** “a `b` c”") == ["a `b` c"]
    assert exists("tests/test_promises.py", "test_the_parser_finds_ids_and_quotes")
    assert not exists("tests/test_promises.py", "test_that_is_not_there")
