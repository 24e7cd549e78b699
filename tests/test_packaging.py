"""The package as users install it: the wheel carries every source file, the version is one
number everywhere a run records it, and the lock file pins what pyproject.toml asks for.

The full check of an installed wheel (a clean venv, outside the checkout, `smana up` to `ok`) is
tests/wheel_smoke.py: `.ci/run` runs it on Python 3.13; here with SMANA_WHEEL_SMOKE=1.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

from smana.common.config import SmanaConfig
from smana.common.version import smana_version
from tests import wheel_smoke
from tests.conftest import REPO

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())


def test_wheel_carries_every_source_file(tmp_path):
    """Built as a user's pip would (sdist, then the wheel from it): no folder falls out, as
    `smana.services.sim.worlds` once did from a hand-kept package list."""
    wheel, sdist = wheel_smoke.build(tmp_path)
    wheel_smoke.check_wheel(wheel)
    assert "smana/services/sim/worlds/garden.py" in wheel_smoke.wheel_files(wheel)
    assert "smana/common/classes/rellis3d.toml" in wheel_smoke.wheel_files(wheel)
    assert wheel.name == f"smana-{PYPROJECT['project']['version']}-py3-none-any.whl"


def test_check_wheel_names_a_missing_file(tmp_path):
    """The contents check fails when a file of the tree is not in the wheel."""
    import zipfile

    wheel = tmp_path / "smana-0-py3-none-any.whl"
    files = sorted(wheel_smoke.tree_files())
    with zipfile.ZipFile(wheel, "w") as z:
        for name in files[1:]:
            z.writestr(name, "")
    with pytest.raises(wheel_smoke.SmokeError, match="1 files of the tree are not in the wheel"):
        wheel_smoke.check_wheel(wheel)


def test_version_is_pyprojects_and_semantic():
    v = PYPROJECT["project"]["version"]
    assert re.fullmatch(r"\d+\.\d+\.\d+", v), v
    assert smana_version() == v  # the installed metadata (pip install -e . re-reads pyproject)
    r = subprocess.run(
        [sys.executable, "-m", "smana.deploy", "--version"], capture_output=True, text=True
    )
    assert r.returncode == 0 and r.stdout.strip() == v
    changelog = (REPO / "CHANGELOG.md").read_text()
    assert f"## [{v}]" in changelog, "CHANGELOG.md has no section for this version"


def test_config_written_into_a_run_names_the_version(tmp_path):
    path = SmanaConfig.load(None, []).write(tmp_path / "config.toml")
    first = path.read_text().splitlines()[0]
    assert first == f"# written by smana {smana_version()}"
    assert SmanaConfig.load(path, []) == SmanaConfig.load(None, [])  # the header reads back


def _locked() -> dict[str, list[tuple[Version, str]]]:
    """requirements/lock.txt as name -> [(version, marker)]."""
    out: dict[str, list] = {}
    for line in (REPO / "requirements" / "lock.txt").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        req = Requirement(line)
        (spec,) = req.specifier
        assert spec.operator == "==", line
        out.setdefault(req.name.lower(), []).append((Version(spec.version), str(req.marker)))
    return out


def test_lock_pins_every_dependency_within_its_range():
    """Every dependency and extra of pyproject.toml is pinned in the lock file, to a version its
    range allows (the lock is regenerated, never edited: see its first lines)."""
    locked = _locked()
    project = PYPROJECT["project"]
    wanted = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        wanted += extra
    for text in wanted:
        req = Requirement(text)
        name = req.name.lower()
        assert name in locked, f"{name} is not in requirements/lock.txt"
        for v, _marker in locked[name]:
            assert req.specifier.contains(v, prereleases=True), (text, str(v))
    header = (REPO / "requirements" / "lock.txt").read_text().splitlines()[1]
    assert "uv pip compile pyproject.toml --all-extras --universal" in header


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("SMANA_WHEEL_SMOKE") != "1", reason="set SMANA_WHEEL_SMOKE=1 (.ci/run runs it)"
)
def test_wheel_smoke(tmp_path):
    r = subprocess.run(
        [sys.executable, str(REPO / "tests" / "wheel_smoke.py"), "--keep", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert r.returncode == 0 and r.stdout.strip().endswith("wheel smoke: ok"), r.stdout + r.stderr
    assert json.loads((tmp_path / "elsewhere" / "run" / "metrics.json").read_text())


def test_the_smoke_takes_subcommands_not_an_options_choices():
    """`smana goto`'s usage has `[--mode {peer,client,router}]` and positionals x y: the wheel
    smoke once ran `smana goto peer --help` (exit 2) as if `peer` were a subcommand."""
    goto = (
        "usage: smana goto [-h] [--mode {peer,client,router}] [--yaw RAD]\n"
        "                  [--workloads {a b,c d} [{a b,c d} ...]] x y\n\nsend a goal"
    )
    assert wheel_smoke.subcommands(goto) == []
    world = "usage: smana world [-h] [--mode {peer,client}] {export,preview,info} ...\n\nworlds"
    assert wheel_smoke.subcommands(world) == ["export", "preview", "info"]
