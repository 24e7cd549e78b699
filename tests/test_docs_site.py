"""The documentation site builds: `mkdocs build --strict` (mkdocs.yml) turns every warning into a
failure, so a broken link, a missing anchor or a page left out of the nav fails this test. Skipped
only where MkDocs is not installed (the `test` extra installs it)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None,
    reason="mkdocs and mkdocs-material are not installed (pip install -e '.[docs]')",
)


def test_the_site_builds_without_a_warning(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet"]
        + ["--config-file", str(REPO / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},  # Material's banner about its future
    )
    log = done.stdout + done.stderr
    assert done.returncode == 0 and "WARNING" not in log, log
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "reference" / "config" / "index.html").is_file()


def test_every_page_is_in_the_nav():
    """A page outside the nav is a warning in mkdocs.yml (validation.nav.omitted_files), and the
    build above fails on it; this says which page, without a build."""
    import yaml

    def pages(nav):
        for item in nav:
            value = next(iter(item.values())) if isinstance(item, dict) else item
            if isinstance(value, list):
                yield from pages(value)
            else:
                yield value

    config = yaml.load((REPO / "mkdocs.yml").read_text(), Loader=yaml.SafeLoader)
    listed = set(pages(config["nav"]))
    docs = REPO / "docs"
    found = {p.relative_to(docs).as_posix() for p in docs.rglob("*.md")}
    assert found - listed == set(), "pages missing from mkdocs.yml's nav"
    assert listed - found == set(), "nav entries with no page"
