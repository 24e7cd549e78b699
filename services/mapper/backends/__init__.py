"""Mapping back-ends: one module per back-end, found by name in one lazy table.

    BACKENDS = Registry("mapper.backend", {"tsdf": "smana.services.mapper.backends.tsdf:Tsdf"})
    backend_class("tsdf")                                    # imports tsdf.py only now
    backend_class("my_pkg.my_map:MyBackend")                 # out of tree, by module:Class
    register("my-map", MyBackend)                            # or in-process

The table is a `smana.common.registry.Registry`: a back-end's module is imported only when it is
used, so that a missing optional package only matters to whoever picks that back-end (a one-line
hint says what to install). Every back-end subclasses `MapBackend` (`base.py`), which says what
it declares and implements, its parameters included: a back-end's typed section (`config_class`)
lives beside its code and is read from `[mapper.<config_key>]` (`config_sections`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from smana.common.registry import Registry

from .params import BUILT_IN

if TYPE_CHECKING:
    from .base import MapBackend

# name -> "module:Class", or, after register(), the class itself
BACKENDS = Registry(
    "mapper.backend",
    {
        "octree-max": "smana.services.mapper.backends.octree_max:OctreeMax",
        "octree-bayes": "smana.services.mapper.backends.octree_bayes:OctreeBayes",
        "tsdf": "smana.services.mapper.backends.tsdf:Tsdf",
    },
    # a subclass of MapBackend (base.py imports the block grid's kernels: checked when a target is
    # first used, so that loading a config, which reads the parameters below, needs no numba)
    check=lambda target: isinstance(target, type) and issubclass(target, _base()),
    kind="MapBackend class",
    # their parameters, in a module without numba: a config loads without the kernels
    params={
        name: f"smana.services.mapper.backends.params:{section.__name__}"
        for name, section in BUILT_IN.items()
    },
)

__all__ = [
    "BACKENDS",
    "MapBackend",
    "backend_class",
    "check_backend",
    "config_sections",
    "register",
]


def _base() -> type:
    from .base import MapBackend

    return MapBackend


def __getattr__(name: str):
    if name == "MapBackend":  # imported when asked for (module docstring of base.py)
        return _base()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def register(name: str, cls: type[MapBackend] | str) -> None:
    """Make a back-end known by `name` in this process (a class, or a "module:Class" spec)."""
    BACKENDS.register(name, cls)


def backend_class(name: str) -> type[MapBackend]:
    """The class of back-end `name` (a registered name or a `module:Class` spec). An unknown
    name, a module that cannot be imported or a class that is not a back-end is a one-line
    `RegistryError` (a `ConfigError`, a `ValueError`) naming `mapper.backend`."""
    return BACKENDS.get(name)


def check_backend(name: str) -> None:
    """Fail at once, in one line, when `mapper.backend` names no back-end (`smana mapper` and
    `smana up` call this before they start anything)."""
    backend_class(name)


def config_sections(backend: str = "") -> dict[str, type]:
    """{config_key: section class} of every back-end (and of `backend`, when it is a
    module:Class spec): what `[mapper.<config_key>]` may hold (common/config/mapper.py)."""
    return BACKENDS.sections((backend,) if ":" in backend else ())
