"""One registry helper: a table of named variants (back-ends, worlds, readers, commands, ...),
each a class or a lazy `"package.module:Class"` imported only when it is first used.

    BACKENDS = Registry("mapper.backend", {"tsdf": "smana.services.mapper.backends.tsdf:Tsdf"},
                        base=MapBackend)
    BACKENDS.register("my-map", MyMap)                   # a class, or "my_pkg.my_map:MyMap"
    BACKENDS.get("tsdf")                                 # imports tsdf.py now; returns Tsdf
    BACKENDS.get("my_pkg.my_map:MyMap")                  # an unregistered module:Class spec
    BACKENDS.names()                                     # ["tsdf", "my-map"], in order
    "tsdf" in BACKENDS; list(BACKENDS); BACKENDS.unregister("my-map")
    BACKENDS.copy()                                      # an independent table (tests restore)
    BACKENDS.sections()                                  # {config_key: config_class} (below)

    COMMANDS = Registry("command", {"up": "smana.deploy.supervisor:cli"}, check=callable,
                        kind="command", specs=False)      # any attribute: here a function

`base` (a class the targets subclass) or `check` (a predicate) says what an entry must be;
`specs=False` refuses unregistered module:Class names; `hints` maps a missing top-level package
to its install line.

Every failure is one `RegistryError`, a `ConfigError` (so a `ValueError`), whose message starts
with the config key the name came from (`what`) and never spans two lines: an unknown name lists
the known ones; a module that is not there says so; a module whose own dependency is missing
names it with an install hint (`hints`, by top-level package; default `pip install <package>`);
an attribute that is not what the registry holds (`base`, or the `check` predicate) says what it
is not. The CLIs print that line and exit 2. A family with an error of its own passes a subclass
(`error=WorldError`), so that its callers' `except` keeps working.

A variant may declare its own typed parameters beside its code: class attributes `config_key`
(its sub-section's name) and `config_class` (a config `Section`). `sections()` collects them over
the table, so that the config loader attaches each under `[<section>.<config_key>]`
(common/config/section.py, `variants=`); an out-of-tree variant registered at run time, or named
by its module:Class spec, is configured the same way.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from typing import Any

from smana.common.config.section import ConfigError

__all__ = ["Registry", "RegistryError", "load_spec"]


class RegistryError(ConfigError):
    """A name or `module:Class` spec that names nothing usable (one line, naming the key)."""


def load_spec(
    spec: str, what: str = "spec", hints: dict[str, str] | None = None, kind: str = ""
) -> Any:
    """The attribute a `"package.module:Attr"` spec names, imported now; RegistryError in one
    line (starting `what: 'spec': `) when the module or the attribute is not there."""
    where = f"{what}: {spec!r}"
    module, sep, attr = spec.partition(":")
    if not (sep and module and attr and all(p.isidentifier() for p in module.split("."))):
        raise RegistryError(f"{where}: expected package.module:Class")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = exc.name or module
        if module == missing or module.startswith(missing + "."):
            raise RegistryError(
                f"{where}: cannot import {module!r}: no module {missing!r} "
                "(is its folder on PYTHONPATH?)"
            ) from None
        top = missing.split(".")[0]
        hint = (hints or {}).get(top, f"pip install {top}")
        raise RegistryError(
            f"{where}: cannot import {module!r}: it needs {missing!r}, which is not installed "
            f"({hint})"
        ) from None
    try:
        return getattr(mod, attr)
    except AttributeError:
        kind = kind or "attribute"
        raise RegistryError(
            f"{where}: {module} has no {kind} {attr!r} ({spec} is not a {kind})"
        ) from None


class Registry:
    """Named variants, lazily imported (module docstring)."""

    def __init__(
        self,
        what: str,
        entries: dict[str, Any] | None = None,
        *,
        base: type | None = None,
        check: Callable[[Any], bool] | None = None,
        kind: str = "",
        hints: dict[str, str] | None = None,
        specs: bool = True,
        error: type[RegistryError] | None = None,
        params: dict[str, str] | None = None,
    ):
        self.what = what  # the config key or command the names come from: "mapper.backend"
        self.base = base
        self.kind = kind or (f"{base.__name__} class" if base is not None else "usable entry")
        self._check = check
        self.hints = dict(hints or {})
        self.specs = specs  # whether an unregistered "module:Class" is accepted by get()
        self.error = error or RegistryError  # a subclass, for a family that has its own
        self._entries: dict[str, Any] = {}
        self._loaded: dict[str, Any] = {}
        # name -> "module:Section" of a registered variant's parameters, when they live in a
        # lighter module than the variant (`sections()` then imports that module only)
        self._params: dict[str, str] = {}
        for name, target in (entries or {}).items():
            self.register(name, target)
        self._params = dict(params or {})

    # -- the table ---------------------------------------------------------------------------

    def register(self, name: str, target: Any) -> None:
        """Make `name` known in this process: a class (checked now) or a "module:Class" spec
        (checked when first used). Registering a name again replaces it."""
        if not isinstance(name, str) or not name or "\n" in name:
            raise self.error(f"{self.what}: a name must be a non-empty string, got {name!r}")
        if isinstance(target, str):
            module, sep, attr = target.partition(":")
            if not (sep and module and attr):
                raise self.error(
                    f"{self.what}: {name!r}: expected package.module:Class, got {target!r}"
                )
        elif not self._accepts(target):
            raise self.error(f"{self.what}: {name!r}: {target!r} is not a {self.kind}")
        self._entries[name] = target
        self._loaded.pop(name, None)
        self._params.pop(name, None)  # a new target declares its own parameters

    def unregister(self, name: str) -> None:
        self._params.pop(name, None)
        self._entries.pop(name, None)
        self._loaded.pop(name, None)

    def names(self) -> list[str]:
        return list(self._entries)

    def entry(self, name: str) -> Any:
        """What `name` was registered with (a class or its spec), without importing anything."""
        return self._entries[name]

    def copy(self) -> Registry:
        new = Registry(self.what, base=self.base, check=self._check, kind=self.kind)
        new.hints = self.hints
        new.specs, new.error = self.specs, self.error
        new._entries, new._loaded = dict(self._entries), dict(self._loaded)
        new._params = dict(self._params)
        return new

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._entries))

    def __len__(self) -> int:
        return len(self._entries)

    def __delitem__(self, name: str) -> None:
        if name not in self._entries:
            raise KeyError(name)
        self.unregister(name)

    def __repr__(self) -> str:
        return f"Registry({self.what!r}, {self.names()!r})"

    # -- look-up -----------------------------------------------------------------------------

    def get(self, name: str) -> Any:
        """The class `name` stands for (a registered name, or a module:Class spec when `specs`),
        imported now if it was not yet. RegistryError in one line otherwise."""
        if name in self._loaded:
            return self._loaded[name]
        if name in self._entries:
            target = self._entries[name]
            if isinstance(target, str):
                target = self._load(target, name)
                self._loaded[name] = target
            return target
        if self.specs and ":" in name:
            return self._load(name, name)
        raise self.error(f"{self.what}: {self.unknown_text()}, got {name!r}")

    def unknown_text(self) -> str:
        """ "expected one of [...]" (and "or a module:Class spec"): the start of the unknown-name
        message, for a registry user that words its own."""
        known = ", ".join(repr(n) for n in self._entries)
        return f"expected one of [{known}]" + (" or a module:Class spec" if self.specs else "")

    def sections(self, also: tuple[str, ...] = ()) -> dict[str, type]:
        """{config_key: config_class} of every registered variant that declares parameters, and
        of the specs in `also` (the variant a config names by module:Class). A variant whose
        module cannot be imported is left out here: it fails in one line when it is used."""
        out: dict[str, type] = {}
        for name in [*self._entries, *also]:
            if name in self._params:
                section = load_spec(self._params[name], self.what, self.hints, "section")
                out.setdefault(section.section.rpartition(".")[2], section)
                continue
            try:
                cls = self.get(name)
            except RegistryError:
                continue
            key, section = getattr(cls, "config_key", None), getattr(cls, "config_class", None)
            if key and section is not None:
                out.setdefault(key, section)
        return out

    def _load(self, spec: str, name: str) -> Any:
        what = f"{self.what}: {name!r}" if name != spec else self.what
        try:
            target = load_spec(spec, what, self.hints, self.kind)
        except RegistryError as exc:
            raise self.error(str(exc)) from None
        if not self._accepts(target):
            raise self.error(f"{what}: {spec!r}: {spec} is not a {self.kind}")
        return target

    def _accepts(self, target: Any) -> bool:
        if self._check is not None:
            return bool(self._check(target))
        if self.base is not None:
            return isinstance(target, type) and issubclass(target, self.base)
        return True
