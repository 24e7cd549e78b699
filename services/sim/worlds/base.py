"""What a kind of world is: a `WorldSource` turns the `[sim]` config into a `World`.

    class MyWorld(WorldSource):
        def build(self, config, classes):
            return World(ground, objects, classes, name="mine")

`sim.world = "NAME"` or `"NAME:ARG"` picks a source from the registry (`worlds/__init__.py`);
`self.arg` is the text after the colon (a path, a variant), None without one. A source outside
smana is named by its `module:Class`. The source only describes the world (numpy arrays and
primitives); `scene.BulletScene` turns it into PyBullet bodies.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

from smana.common.registry import RegistryError

if TYPE_CHECKING:
    from smana.common.classes import ClassTable
    from smana.common.config import SimConfig

    from .world import World


class WorldError(RegistryError):
    """A world cannot be built from the given parameters or data, or `sim.world` names none (a
    `ConfigError`, so a `ValueError`: one line)."""


class WorldSource:
    """Base of every kind of world (module docstring). Subclasses implement `build`."""

    # its parameters, beside its code: a config `Section` read from `[sim.<config_key>]`
    config_key: ClassVar[str | None] = None
    config_class: ClassVar[type | None] = None

    def __init__(self, arg: str | None = None):
        self.arg = arg

    def build(self, config: SimConfig, classes: ClassTable) -> World:
        """The world the `[sim]` section describes; the same config always gives the same world."""
        raise NotImplementedError
