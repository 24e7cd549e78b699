"""The one registry helper (common/registry.py) that back-ends, worlds and readers share: lazy
`module:Class` entries, `register` / `get` / `names`, and one error, a one-line `ConfigError`
naming the key, the known names, or what to install."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from smana.common.config import ConfigError
from smana.common.registry import Registry, RegistryError
from smana.services.mapper import backends
from smana.services.replay import readers
from smana.services.sim import worlds
from tests.conftest import REPO
from tests.support.toy_reader import ToyReader


class Base:
    pass


class Good(Base):
    config_key, config_class = "good", dict


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    """Modules on the path: one that marks when it is imported, one whose dependency is missing."""
    mark = tmp_path / "imported"
    (tmp_path / "reg_marker.py").write_text(
        f"open({str(mark)!r}, 'w').close()\nclass Marked:\n    pass\n"
    )
    (tmp_path / "reg_needs_dep.py").write_text("import no_such_dependency_pkg.sub\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return mark


def one_line(info) -> str:
    text = str(info.value)
    assert "\n" not in text and isinstance(info.value, ConfigError)
    return text


def test_names_and_lookups_are_uniform_and_lazy(plugins):
    reg = Registry("thing.kind", {"good": Good, "marked": "reg_marker:Marked"})
    assert reg.names() == ["good", "marked"] and list(reg) == reg.names() and len(reg) == 2
    assert "good" in reg and "other" not in reg
    assert not plugins.exists()  # a spec is imported when it is first used, not before
    assert reg.get("marked").__name__ == "Marked" and plugins.exists()
    assert reg.get("good") is Good and reg.get(f"{__name__}:Good") is Good  # by module:Class
    reg.register("good", "reg_marker:Marked")  # registering again replaces
    assert reg.get("good").__name__ == "Marked"
    copy = reg.copy()
    copy.unregister("good")
    assert "good" in reg and "good" not in copy  # a copy is independent (tests restore with it)


def test_every_failure_is_one_line_naming_the_key():
    reg = Registry("thing.kind", {"good": Good, "spec": f"{__name__}:Good"}, base=Base)
    with pytest.raises(RegistryError) as info:
        reg.get("nope")
    assert one_line(info) == (
        "thing.kind: expected one of ['good', 'spec'] or a module:Class spec, got 'nope'"
    )
    with pytest.raises(RegistryError) as info:
        reg.get("no_such_module_xyz:Thing")
    assert "cannot import 'no_such_module_xyz': no module 'no_such_module_xyz'" in one_line(info)
    with pytest.raises(RegistryError) as info:
        reg.get(f"{__name__}:Missing")
    assert f"{__name__} has no Base class 'Missing'" in one_line(info)
    with pytest.raises(RegistryError) as info:
        reg.get(f"{__name__}:one_line")  # there, but not a Base
    assert "is not a Base class" in one_line(info)
    with pytest.raises(RegistryError) as info:
        reg.register("bad", dict)  # a class is checked when registered
    assert "is not a Base class" in one_line(info)
    with pytest.raises(RegistryError) as info:
        reg.register("bad", "no_colon")
    assert "expected package.module:Class" in one_line(info)
    no_specs = Registry("thing.kind", {"good": Good}, specs=False)
    with pytest.raises(RegistryError) as info:
        no_specs.get(f"{__name__}:Good")
    assert one_line(info).endswith("expected one of ['good'], got 'tests.test_registry:Good'")


def test_a_missing_dependency_names_what_to_install(plugins):
    reg = Registry("thing.kind", {"dep": "reg_needs_dep:Thing"})
    with pytest.raises(RegistryError) as info:
        reg.get("dep")
    assert one_line(info).endswith(
        "cannot import 'reg_needs_dep': it needs 'no_such_dependency_pkg', which is not installed"
        " (pip install no_such_dependency_pkg)"
    )
    hinted = Registry(
        "thing.kind",
        {"dep": "reg_needs_dep:Thing"},
        hints={"no_such_dependency_pkg": "pip install 'smana[extra]'"},
    )
    with pytest.raises(RegistryError, match=r"\(pip install 'smana\[extra\]'\)$"):
        hinted.get("dep")


def test_sections_are_the_variants_declared_parameters(plugins):
    reg = Registry(
        "thing.kind", {"good": Good, "marked": "reg_marker:Marked", "dep": "reg_needs_dep:X"}
    )
    assert reg.sections() == {"good": dict}  # no parameters, or not importable: left out


def test_backends_worlds_and_readers_share_it():
    for registry, what in ((backends.BACKENDS, "mapper.backend"), (worlds.WORLDS, "sim.world")):
        assert isinstance(registry, Registry) and registry.what == what
    assert isinstance(readers.READERS, Registry) and readers.READERS.what == "replay.format"
    with pytest.raises(RegistryError) as info:
        readers.reader_class("nope")
    assert one_line(info).startswith("replay.format: expected one of ['semantickitti', ")
    with pytest.raises(worlds.WorldError) as info:  # worlds keep their own subclass
        worlds.world_source("no_such_module_xyz:World")
    assert isinstance(info.value, RegistryError) and one_line(info).startswith("sim.world: ")


def test_a_reader_registers_as_a_class_too(monkeypatch):
    monkeypatch.setattr(readers, "READERS", readers.READERS.copy())
    readers.register("toy", ToyReader)
    assert readers.reader_class("toy") is ToyReader


def test_smana_mapper_names_a_missing_dependency_in_one_line(tmp_path):
    (tmp_path / "needs_dep_backend.py").write_text("import no_such_dependency_pkg\n")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "smana.services.mapper",
            "--set",
            "mapper.backend=needs_dep_backend:Map",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)])},
    )
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "smana mapper: mapper.backend: 'needs_dep_backend:Map': cannot import 'needs_dep_backend':"
        " it needs 'no_such_dependency_pkg', which is not installed (pip install"
        " no_such_dependency_pkg)"
    ]


def test_a_config_and_its_variants_sections_load_without_the_variants_code():
    """Reading a config, its back-ends' and worlds' sections included, imports their parameter
    modules only (backends/params.py, worlds/params.py): no numba, no scipy, no kernel, so that
    `smana status`, the supervisor and a service's start do not pay for them."""
    code = (
        "import sys\n"
        "from smana.common.config import SmanaConfig\n"
        "cfg = SmanaConfig.load(None, ['mapper.resolution_m=0.2', 'mapper.tsdf.min_weight=2',\n"
        "                              'sim.garden.clutter=0.3'])\n"
        "assert cfg.mapper.tsdf.min_weight == 2 and cfg.sim.garden.clutter == 0.3\n"
        "heavy = ('numba', 'scipy', 'smana.services.mapper.backends.tsdf',\n"
        "         'smana.services.mapper.backends.base', 'smana.services.sim.worlds.garden')\n"
        "print([m for m in heavy if m in sys.modules])\n"
        "from smana.services.mapper.backends import backend_class\n"
        "print(backend_class('tsdf').config_class is type(cfg.mapper.tsdf))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.split("\n")[:2] == ["[]", "True"], out.stdout + out.stderr


def test_commands_and_warm_ups_resolve_through_the_one_helper(capsys):
    """`smana <name>`'s target and `smana warmup`'s classes are `load_spec` look-ups: a target
    that is not in this build is the helper's one line and exit 2, not a traceback."""
    from smana.deploy import cli, warmup

    assert cli.call("ghost", "smana.services.no_such_service.__main__:cli", []) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("smana ghost: 'smana.services.no_such_service.__main__:cli'")
    assert "\n" not in err
    assert cli.call("ghost", "smana.deploy.status:no_such_function", []) == 2
    assert "has no command 'no_such_function'" in capsys.readouterr().err
    from smana.common.registry import load_spec

    for name, spec in warmup.WARMUPS.items():
        assert load_spec(spec).name == name
