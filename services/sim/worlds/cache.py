"""Built worlds kept on disk, so that a sim started again does not generate its garden again.

A procedural garden takes about 1.5 s of CPU to generate (and imports scipy's graph and spatial
modules for it): most of a warm sim's start, and on 2 cores it holds back the other services of a
`smana up` starting at the same time. The same seed, `[sim.garden]` section, class table and world
code always give the same world (the garden's promise), so the world is pickled once under a key
made of exactly those and read back on the next start.

- Where: `$SMANA_WORLD_CACHE` (a folder; `off` for no cache), else `$XDG_CACHE_HOME/smana/worlds`
  (`~/.cache/smana/worlds`). A folder that cannot be written means no cache, never an error.
- The key holds a hash of every source file of the worlds package: a changed generator never reads
  a world an older one wrote. A file that does not load (cut short, another Python) is built again.
- Files are written to a temporary name and renamed, so two sims starting at once never read half
  a file.
- The folder keeps the `KEEP` worlds used last (a read touches its file); a world whose ground
  arrays pass `MAX_BYTES` is not stored (a large world is a file the size of its arrays).
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .world import World

ENV = "SMANA_WORLD_CACHE"
KEEP = 64  # worlds kept in the folder, the last used
MAX_BYTES = 64 << 20  # a world whose ground arrays are larger is built each time
log = logging.getLogger("smana.sim")


def folder() -> Path | None:
    """The cache folder in use, None when the cache is off."""
    env = os.environ.get(ENV, "")
    if env.lower() == "off":
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "smana" / "worlds"


@functools.cache
def _code_hash() -> str:
    """Every source file of the worlds package (and the ply reader a world may use)."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for f in sorted(here.glob("*.py")) + [here.parent / "ply.py"]:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def key(*parts: object) -> str:
    """A file name for a world made from `parts` (their reprs: plain values and frozen
    dataclasses, whose reprs are their contents) by the current world code."""
    h = hashlib.sha256(_code_hash().encode())
    for part in parts:
        h.update(repr(part).encode())
        h.update(b"\0")
    return h.hexdigest()[:32]


def cached(name: str, build: Callable[[], World]) -> World:
    """The world stored under `name` (`key(...)`), else `build()` and store it."""
    where = folder()
    if where is None:
        return build()
    path = where / f"{name}.pickle"
    try:
        with open(path, "rb") as f:
            world = pickle.load(f)
    except FileNotFoundError:
        pass
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign file: build it again
        log.warning("world cache %s does not load (%s): building the world again", path, exc)
    else:
        try:
            os.utime(path)  # used last: kept when the folder is pruned
        except OSError:  # pruned meanwhile by another sim: the world read is whole
            pass
        return world
    world = build()
    if world.ground.heights.nbytes + world.ground.classes.nbytes > MAX_BYTES:
        return world
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        where.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            pickle.dump(world, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)
        _prune(where)
    except OSError as exc:
        log.info("world cache %s not written (%s)", where, exc)
        try:
            tmp.unlink(missing_ok=True)  # a disk that filled up: no half file left behind
        except OSError:
            pass
    return world


def _prune(where: Path) -> None:
    """Keep the `KEEP` files used last; another sim may be pruning too."""
    files = []
    for f in where.glob("*.pickle"):
        try:
            files.append((f.stat().st_mtime, f))
        except FileNotFoundError:
            continue
    for _, f in sorted(files, reverse=True)[KEEP:]:
        f.unlink(missing_ok=True)
