"""Mapping back-ends: one module per back-end, found by name in one lazy table.

    BACKENDS = {"octree-max": "octree_max:OctreeMax", ...}   # name -> "module:Class"
    backend_class("tsdf")                                    # imports tsdf.py only now
    backend_class("my_pkg.my_map:MyBackend")                 # out of tree, by module:Class
    register("my-map", MyBackend)                            # or in-process

A back-end's module is imported only when it is used, so that a missing optional package only
matters to whoever picks that back-end (a one-line hint says what to install). Every back-end
subclasses `MapBackend` (`base.py`), which says what it declares and implements.
"""

from __future__ import annotations

import importlib

from smana.common.config import ConfigError

from .base import MapBackend

# name -> "module:Class" (a module of this package) or, after register(), the class itself
BACKENDS: dict[str, str | type[MapBackend]] = {
    "octree-max": "octree_max:OctreeMax",
    "octree-bayes": "octree_bayes:OctreeBayes",
    "tsdf": "tsdf:Tsdf",
}

__all__ = ["BACKENDS", "MapBackend", "backend_class", "check_backend", "register"]


def register(name: str, cls: type[MapBackend] | str) -> None:
    """Make a back-end known by `name` in this process (a class, or a "module:Class" spec)."""
    if not isinstance(cls, str) and not (isinstance(cls, type) and issubclass(cls, MapBackend)):
        raise TypeError(f"a back-end must be a MapBackend subclass, got {cls!r}")
    BACKENDS[name] = cls


def backend_class(name: str) -> type[MapBackend]:
    """The class of back-end `name` (a registered name or a `module:Class` spec). An unknown
    name, a module that cannot be imported or a class that is not a back-end is a one-line
    `ConfigError` (a `ValueError`) naming `mapper.backend`."""
    entry = BACKENDS.get(name)
    if entry is None and ":" not in name:
        known = ", ".join(repr(n) for n in BACKENDS)
        raise ConfigError(
            f"mapper.backend: expected one of [{known}] or a module:Class spec, got {name!r}"
        )
    if entry is None or isinstance(entry, str):
        spec = entry or name
        module, _, attr = spec.partition(":")
        path = f"{__name__}.{module}" if entry is not None else module
        try:
            mod = importlib.import_module(path)
        except ModuleNotFoundError as exc:
            missing = exc.name or path
            hint = "" if missing == path else f" (pip install {missing.split('.')[0]})"
            raise ConfigError(f"mapper.backend {name!r}: cannot import {missing!r}{hint}") from None
        entry = getattr(mod, attr, None)
        if not (isinstance(entry, type) and issubclass(entry, MapBackend)):
            raise ConfigError(f"mapper.backend {name!r}: {spec} is not a MapBackend class")
    return entry


def check_backend(name: str) -> None:
    """Fail at once, in one line, when `mapper.backend` names no back-end (`smana mapper` and
    `smana up` call this before they start anything)."""
    backend_class(name)
