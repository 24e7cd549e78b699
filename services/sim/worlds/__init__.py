"""Simulator worlds: one module per kind of world, found by name in a lazy registry.

    sim.world = "garden"              # procedural (garden.py, [sim.garden])
    sim.world = "ply:PATH"            # from a labelled cloud (cloud.py, [sim.ply]); a bare path
                                      # to a .ply file means the same
    sim.world = "mypkg.worlds:Maze"   # out of tree: any importable WorldSource subclass

A kind of world is a `WorldSource` (base.py) whose `build(config, classes)` returns a `World`
(world.py: ground, objects, and the queries evaluation needs). Its module is imported only when
it is used. Adding one to smana is one module here plus one line in `WORLDS`; a plugin needs no
edit of smana (`module:Class`), or calls `register()` in-process. The parts worlds are made of:
`geometry.py` (primitives), `ground.py` (height field and rasters), `objects.py` (labelled
objects and walls); `preview.py` draws a world from above.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from smana.common.classes import ClassTable
from smana.common.config import SimConfig

from .base import WorldError, WorldSource
from .geometry import BOX, CYLINDER, ELLIPSOID, SHAPES, SPHERE, Primitive
from .ground import GroundModel, Raster
from .objects import WorldObject
from .world import World

# world name -> "module:Class" of its WorldSource, imported when first used
WORLDS: dict[str, str | type[WorldSource]] = {
    "garden": "smana.services.sim.worlds.garden:Garden",
    "ply": "smana.services.sim.worlds.cloud:PlyWorld",
}

__all__ = [
    "BOX",
    "CYLINDER",
    "ELLIPSOID",
    "SHAPES",
    "SPHERE",
    "WORLDS",
    "GroundModel",
    "Primitive",
    "Raster",
    "World",
    "WorldError",
    "WorldObject",
    "WorldSource",
    "build_world",
    "register",
    "world_source",
]


def register(name: str, source: str | type[WorldSource]) -> None:
    """Make `sim.world = "NAME"` (or `"NAME:ARG"`) build worlds with `source` (a WorldSource
    subclass, or its "module:Class")."""
    if not name.isidentifier():
        raise ValueError(f"a world name must be an identifier, got {name!r}")
    WORLDS[name] = source


def world_source(spec: str) -> WorldSource:
    """The source a `sim.world` value names (module docstring); WorldError in one line if none."""
    name, sep, arg = spec.partition(":")
    if name in WORLDS:
        return _load(WORLDS[name], spec)(arg if sep else None)
    cls_name, _, plugin_arg = arg.partition(":")
    if sep and cls_name.isidentifier() and all(p.isidentifier() for p in name.split(".")):
        return _load(f"{name}:{cls_name}", spec)(plugin_arg or None)
    if spec.lower().endswith(".ply") or Path(spec).is_file():
        return _load(WORLDS["ply"], spec)(spec)
    known = ", ".join(f"{n}:ARG" if n == "ply" else n for n in WORLDS)
    raise WorldError(
        f"sim.world: {spec!r} is neither 'garden' nor a PLY file, nor a known world "
        f"({known}) or a module:Class"
    )


def build_world(config: SimConfig, classes: ClassTable | None = None) -> World:
    """The world a `[sim]` section describes (`config.world`); the same config, the same world."""
    classes = classes or ClassTable.load("garden3drms")
    world = world_source(config.world).build(config, classes)
    if not isinstance(world, World):
        raise WorldError(f"sim.world: {config.world!r} built a {type(world).__name__}, not a World")
    return world


def _load(entry: str | type[WorldSource], spec: str) -> type[WorldSource]:
    if not isinstance(entry, str):
        return entry
    module, _, cls_name = entry.partition(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (module == exc.name or module.startswith(exc.name + ".")):
            raise WorldError(
                f"sim.world: {spec!r}: no module {module!r} (is its folder on PYTHONPATH?)"
            ) from None
        raise WorldError(
            f"sim.world: {spec!r}: {module} needs {exc.name!r}, which is not installed"
        ) from None
    cls = getattr(mod, cls_name, None)
    if not (isinstance(cls, type) and callable(getattr(cls, "build", None))):
        raise WorldError(f"sim.world: {spec!r}: {module} has no world class {cls_name!r}")
    return cls
