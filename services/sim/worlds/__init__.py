"""Simulator worlds: one module per kind of world, found by name in a lazy registry.

    sim.world = "garden"              # procedural (garden.py, [sim.garden])
    sim.world = "ply:PATH"            # from a labelled cloud (cloud.py, [sim.ply]); a bare path
                                      # to a .ply file means the same
    sim.world = "mypkg.worlds:Maze"   # out of tree: any importable WorldSource subclass

A kind of world is a `WorldSource` (base.py) whose `build(config, classes)` returns a `World`
(world.py: ground, objects, and the queries evaluation needs). Its module is imported only when
it is used (`WORLDS` is a `smana.common.registry.Registry`). Adding one to smana is one module
here plus one line in `WORLDS`; a plugin needs no edit of smana (`module:Class`), or calls
`register()` in-process. A world with knobs declares them beside its code, as `config_key` and
`config_class` on its source (garden.py's `GardenConfig`, kept in params.py so that a config
loads without scipy): the config loader reads them from
`[sim.<config_key>]` (`config_sections`), a plugin's too. The parts worlds are made of:
`geometry.py` (primitives), `ground.py` (height field and rasters), `objects.py` (labelled
objects and walls); `preview.py` draws a world from above.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from smana.common.classes import ClassTable
from smana.common.config import SimConfig
from smana.common.registry import Registry

from .base import WorldError, WorldSource
from .params import BUILT_IN

if TYPE_CHECKING:
    from .world import World

# what the package re-exports, imported when first asked for: loading a config reads the worlds'
# parameters (params.py) and must not cost scipy and the world's geometry
_LAZY = {
    **dict.fromkeys(("BOX", "CYLINDER", "ELLIPSOID", "SHAPES", "SPHERE", "Primitive"), "geometry"),
    **dict.fromkeys(("GroundModel", "Raster"), "ground"),
    "WorldObject": "objects",
    "World": "world",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _is_source(cls) -> bool:
    return isinstance(cls, type) and callable(getattr(cls, "build", None))


# world name -> "module:Class" of its WorldSource, imported when first used
WORLDS = Registry(
    "sim.world",
    {
        "garden": "smana.services.sim.worlds.garden:Garden",
        "ply": "smana.services.sim.worlds.cloud:PlyWorld",
    },
    check=_is_source,
    kind="world class",
    error=WorldError,
    # their parameters, in a module without scipy: a config loads without the worlds' code
    params={
        name: f"smana.services.sim.worlds.params:{section.__name__}"
        for name, section in BUILT_IN.items()
    },
)

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
    "config_sections",
    "register",
    "spawn_clearance_m",
    "world_source",
]


def register(name: str, source: str | type[WorldSource]) -> None:
    """Make `sim.world = "NAME"` (or `"NAME:ARG"`) build worlds with `source` (a WorldSource
    subclass, or its "module:Class")."""
    if not name.isidentifier():
        raise ValueError(f"a world name must be an identifier, got {name!r}")
    WORLDS.register(name, source)


def world_source(spec: str) -> WorldSource:
    """The source a `sim.world` value names (module docstring); WorldError in one line if none."""
    name, sep, arg = spec.partition(":")
    if name in WORLDS:
        return WORLDS.get(name)(arg if sep else None)
    cls_name, _, plugin_arg = arg.partition(":")
    if sep and cls_name.isidentifier() and all(p.isidentifier() for p in name.split(".")):
        return WORLDS.get(f"{name}:{cls_name}")(plugin_arg or None)
    if spec.lower().endswith(".ply") or Path(spec).is_file():
        return WORLDS.get("ply")(spec)
    known = ", ".join(f"{n}:ARG" if n == "ply" else n for n in WORLDS.names())
    raise WorldError(
        f"sim.world: {spec!r} is neither 'garden' nor a PLY file, nor a known world "
        f"({known}) or a module:Class"
    )


def spawn_clearance_m(config: SimConfig) -> float:
    """The clearance the sim's robot spawns with (`World.spawn_pose`): its radius and 5 cm."""
    return config.robot.radius_m + 0.05


def build_world(config: SimConfig, classes: ClassTable | None = None) -> World:
    """The world a `[sim]` section describes (`config.world`); the same config, the same world."""
    classes = classes or ClassTable.load("garden3drms")
    world = world_source(config.world).build(config, classes)
    from .world import World

    if not isinstance(world, World):
        raise WorldError(f"sim.world: {config.world!r} built a {type(world).__name__}, not a World")
    return world


def _plugin(spec: str) -> str | None:
    """The module:Class a `sim.world` value names out of tree, None for a registered world."""
    name, sep, arg = spec.partition(":")
    cls_name = arg.partition(":")[0]
    if name in WORLDS or not (sep and cls_name.isidentifier()):
        return None
    return f"{name}:{cls_name}" if all(p.isidentifier() for p in name.split(".")) else None


def config_sections(world: str = "") -> dict[str, type]:
    """{config_key: section class} of every registered world (and of `world`, when it names a
    plugin by module:Class): what `[sim.<config_key>]` may hold (common/config/sim.py)."""
    plugin = _plugin(world)
    return WORLDS.sections((plugin,) if plugin else ())
