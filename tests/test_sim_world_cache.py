"""The built-world cache (services/sim/worlds/cache.py): a garden read back is the garden generated,
bit for bit; a key per seed, section, class table and world code; a damaged file is built again;
`off` writes nothing; the folder keeps the worlds used last and no world too large; a cached world
carries the sim's spawn pose; and a sim on a warm cache imports neither the garden generator nor
scipy."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from smana.common.config import SimConfig
from smana.services.sim.worlds import build_world, cache, spawn_clearance_m
from smana.services.sim.worlds.garden import generate
from smana.services.sim.worlds.params import GardenConfig

SMALL = GardenConfig(size_m=6.0)


def config(seed: int = 5) -> SimConfig:
    return dataclasses.replace(SimConfig(), seed=seed, garden=SMALL)


def same_world(a, b) -> bool:
    ga, gb = a.ground, b.ground
    return (
        ga.origin_xy == gb.origin_xy
        and ga.resolution_m == gb.resolution_m
        and np.array_equal(ga.heights, gb.heights)
        and ga.heights.dtype == gb.heights.dtype
        and np.array_equal(ga.classes, gb.classes)
        and ga.classes.dtype == gb.classes.dtype
        and [(o.kind, o.class_id, o.primitives) for o in a.objects]
        == [(o.kind, o.class_id, o.primitives) for o in b.objects]
        and (a.name, a.seed) == (b.name, b.seed)
    )


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.ENV, str(tmp_path / "worlds"))
    return tmp_path / "worlds"


def test_a_cached_garden_is_the_generated_one(folder):
    built = build_world(config())
    files = list(folder.glob("*.pickle"))
    assert len(files) == 1
    again = build_world(config())  # read back
    assert list(folder.glob("*.pickle")) == files
    assert same_world(again, built)
    assert same_world(again, generate(5, SMALL))
    assert again.classes is not None and again.free_fraction() == built.free_fraction()
    build_world(config(seed=6))  # another seed, another file
    assert len(list(folder.glob("*.pickle"))) == 2


def test_the_key_follows_the_section_the_classes_and_the_code(monkeypatch):
    base = cache.key("garden", 5, SMALL, "garden3drms")
    assert base == cache.key("garden", 5, GardenConfig(size_m=6.0), "garden3drms")
    assert base != cache.key("garden", 5, GardenConfig(size_m=7.0), "garden3drms")
    assert base != cache.key("garden", 5, SMALL, "another table")
    monkeypatch.setattr(cache, "_code_hash", lambda: "changed code")
    assert base != cache.key("garden", 5, SMALL, "garden3drms")


def test_a_damaged_file_is_built_again(folder):
    built = build_world(config())
    (path,) = folder.glob("*.pickle")
    path.write_bytes(path.read_bytes()[:100])
    assert same_world(build_world(config()), built)
    assert same_world(build_world(config()), built)  # rewritten whole
    assert len(path.read_bytes()) > 100


def test_the_folder_keeps_the_worlds_used_last(folder, monkeypatch):
    monkeypatch.setattr(cache, "KEEP", 2)
    build_world(config(seed=1))
    first = set(folder.glob("*.pickle"))
    build_world(config(seed=2))
    build_world(config(seed=1))  # read back: used last
    build_world(config(seed=3))  # a third: seed 2's goes
    kept = set(folder.glob("*.pickle"))
    assert len(kept) == 2 and first <= kept


def test_a_large_world_is_not_stored(folder, monkeypatch):
    monkeypatch.setattr(cache, "MAX_BYTES", 1000)
    assert same_world(build_world(config()), generate(5, SMALL))
    assert not list(folder.glob("*"))


def test_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.ENV, "off")
    assert cache.folder() is None
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    build_world(config())
    assert not list(tmp_path.rglob("*.pickle"))


def test_a_folder_that_cannot_be_written_is_no_cache(tmp_path, monkeypatch):
    blocker = tmp_path / "a file"
    blocker.write_text("")
    monkeypatch.setenv(cache.ENV, str(blocker / "worlds"))
    assert same_world(build_world(config()), generate(5, SMALL))


def test_a_cached_world_carries_the_sims_spawn_pose(folder):
    cfg = config()
    built = build_world(cfg)  # generated, its spawn pose worked out before it was stored
    again = build_world(cfg)  # read back
    r = spawn_clearance_m(cfg)
    assert r in again._spawn
    fresh = generate(5, SMALL)
    assert again.spawn_pose(r) == built.spawn_pose(r) == fresh.spawn_pose(r)
    assert again.spawn_pose(0.3) == fresh.spawn_pose(0.3)  # another radius: worked out


def test_a_warm_sim_does_not_import_the_generator_nor_scipy(folder):
    """Import budget: on a warm cache the world and its spawn pose cost a file read, not the
    generator's imports nor scipy's (0.15 s of CPU)."""
    build_world(config())
    probe = (
        "import dataclasses, sys\n"
        "from smana.common.config import SimConfig\n"
        "from smana.services.sim.worlds import build_world, spawn_clearance_m\n"
        "from smana.services.sim.worlds.params import GardenConfig\n"
        "cfg = dataclasses.replace(SimConfig(), seed=5, garden=GardenConfig(size_m=6.0))\n"
        "build_world(cfg).spawn_pose(spawn_clearance_m(cfg))\n"
        "heavy = ('smana.services.sim.worlds.garden_3drms', 'scipy')\n"
        "bad = [m for m in heavy if m in sys.modules]\n"
        "print(bad)\n"
    )
    env = {"PATH": "/usr/bin:/bin", cache.ENV: str(folder)}
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    # and the probe can fail: a cold cache imports them
    env[cache.ENV] = str(folder.parent / "cold")
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120
    )
    assert "garden_3drms" in out.stdout
