"""The user-facing pages (README.md, CHANGELOG.md, docs/**/*.md) read on their own: no issue
numbers of the project's tracker ("issue 29", "(issue 12)", "#36": a reader has no tracker to
look them up in) and no path of a developer's machine (`/work/...`, `/home/...`, `../shared`). A
reference to another project's tracker names it (`numba/numba#2350`) and links it. Generated
pages and sections are checked as they are: what writes them says none either."""

from __future__ import annotations

import re

import pytest

from tests.conftest import REPO

PAGES = sorted([REPO / "README.md", REPO / "CHANGELOG.md", *(REPO / "docs").rglob("*.md")])
ISSUE = re.compile(r"(?i)\bissues?\s+#?\d+|(?<![\w/#])#\d+\b")
MACHINE_PATH = re.compile(r"/work/|/home/|\.\./shared\b")
# the project's own work sessions and stops, which a reader cannot look up either
WORK_SESSION = re.compile(r"(?i)\b(?:at|of|since|before|after|in) stop \d+\b|\bsession \d+\b")


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(REPO)) for p in PAGES])
def test_a_page_names_no_issue_number_and_no_machine_path(page):
    found = []
    for number, line in enumerate(page.read_text().splitlines(), 1):
        found += [f"line {number}: {m.group()!r}" for m in ISSUE.finditer(line)]
        found += [f"line {number}: {m.group()!r}" for m in MACHINE_PATH.finditer(line)]
        found += [f"line {number}: {m.group()!r}" for m in WORK_SESSION.finditer(line)]
    assert not found, f"{page.relative_to(REPO)}: reword {found}"


def test_the_patterns():
    for bad in ("issue 29", "(Issue 12)", "issues 15 and 16", "see #36", "issue #1835"):
        assert ISSUE.search(bad), bad
    for fine in ("numba/numba#2350", "zenoh/issues/1835", "issue one more robot", "#### 10 km"):
        assert not ISSUE.search(fine), fine
    for bad in ("a NaN failed CI at stop 35", "since stop 31", "Session 2 (2026-11-22"):
        assert WORK_SESSION.search(bad), bad
    for fine in ("the robot stops 3 cm short", "stop 10 robots", "a zenoh session opens"):
        assert not WORK_SESSION.search(fine), fine
    assert MACHINE_PATH.search("see /work/shared/REFERENCE.md")
    assert MACHINE_PATH.search("../shared/seeds")
