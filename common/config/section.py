"""The one typed-config mechanism: a `Section` is a dataclass whose fields carry their own limits,
and one generic validator checks every field from its type and limits.

    @dataclass
    class FollowerConfig(Section, section="explorer.follower"):
        lookahead_m: float = param(0.4, gt=0)
        mode: Literal["a", "b"] = "a"

A section is validated whenever it is made, from a TOML table (`build`) or in Python
(`FollowerConfig(lookahead_m=0)`), and the error is one line naming the dotted key:
`explorer.follower.lookahead_m: expected a number > 0, got 0`. Checks that relate two fields live
in the section's `validate()`. Cores receive their section as it is: no copies, no renaming.

A section whose variants (back-ends, worlds) declare their own parameters beside their code is
decorated `@with_variants("package.module:config_sections", "backend")`: that function (in the
variants' registry, common/registry.py; imported only when a variant's section is needed)
returns {config_key: Section class}, and each variant's section is read from and written to
`[<section>.<config_key>]`, reached as an attribute (`config.mapper.tsdf`) and passed by keyword
(`SimConfig(garden=GardenConfig(size_m=8))`). Left out, it is that class's defaults.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import math
import numbers
import types
import typing
from dataclasses import field
from typing import Any, ClassVar, Literal

VARIANTS = "variants"  # the field of a section decorated with `with_variants`


class ConfigError(ValueError):
    """A config file, key or value that cannot be used. The message names the key."""


def param(default: Any = dataclasses.MISSING, *, gt=None, ge=None, lt=None, le=None, **kw):
    """A field with limits on its value (numbers, or the items of a list of numbers)."""
    limits = {k: v for k, v in (("gt", gt), ("ge", ge), ("lt", lt), ("le", le)) if v is not None}
    if isinstance(default, list | dict):
        value = default
        kw["default_factory"] = lambda: type(value)(value)
        default = dataclasses.MISSING
    return field(default=default, metadata=limits, **kw)


def table(cls, **values):
    """A sub-section field: `follower: FollowerConfig = table(FollowerConfig)`."""
    return field(default_factory=lambda: cls(**values))


class Section:
    """Base of every config section: validation on construction (see the module docstring)."""

    section: ClassVar[str] = ""

    def __init_subclass__(cls, section: str = "", **kw):
        super().__init_subclass__(**kw)
        cls.section = section

    def __post_init__(self) -> None:
        where = f"{self.section}." if self.section else ""
        hints = type_hints(type(self))
        for f in dataclasses.fields(self):
            if not f.init:
                continue
            if f.metadata.get(VARIANTS):
                self._check_variants(where)
                continue
            hint = hints[f.name]
            value = getattr(self, f.name)
            if dataclasses.is_dataclass(hint):
                if not isinstance(value, hint):
                    raise ConfigError(f"{where}{f.name}: expected a [{where}{f.name}] table")
                continue
            object.__setattr__(self, f.name, check_value(where + f.name, value, hint, f.metadata))
        self.validate()

    def validate(self) -> None:
        """Checks between fields; override in a section that has some."""

    # -- variants' own sections (`with_variants`) ------------------------------------------

    @classmethod
    def variant_classes(cls, selected: str = "") -> dict[str, type]:
        """{config_key: Section class} of this section's variants (and of `selected`, a variant
        named by module:Class); {} for a section without variants."""
        spec = getattr(cls, "_variants_spec", "")
        if not spec:
            return {}
        module, _, attr = spec.partition(":")
        return getattr(importlib.import_module(module), attr)(selected)

    def selected_variant(self) -> str:
        return str(getattr(self, type(self)._variant_field, "") or "")

    def variant(self, key: str):
        """The `[<section>.<key>]` sub-section: as given, else its class's defaults (kept)."""
        tables = self.__dict__[VARIANTS]
        if key not in tables:
            classes = self.variant_classes(self.selected_variant())
            if key not in classes:
                raise KeyError(key)
            tables[key] = classes[key]()
        return tables[key]

    def _check_variants(self, where: str) -> None:
        tables = self.__dict__[VARIANTS] = dict(self.__dict__[VARIANTS])  # never shared
        if not tables:
            return
        classes = self.variant_classes(self.selected_variant())
        for key, value in tables.items():
            if key not in classes:
                known = ", ".join(sorted(classes))
                raise ConfigError(f"unknown section {where}{key} (variants' sections: {known})")
            if not isinstance(value, classes[key]):
                raise ConfigError(f"{where}{key}: expected a [{where}{key}] table")

    def __getattr__(self, name: str):
        # only reached when normal look-up fails: a variant's section, e.g. config.mapper.tsdf
        tables = self.__dict__.get(VARIANTS) if not name.startswith("_") else None
        if tables is None:
            raise AttributeError(name)
        try:
            return self.variant(name)
        except KeyError:
            raise AttributeError(
                f"{type(self).__name__} has no field or variant section {name!r}"
            ) from None


def variant_tables():
    """The field that holds a section's variants' sections (`with_variants`)."""
    return field(default_factory=dict, repr=False, compare=False, metadata={VARIANTS: True})


def with_variants(spec: str, selector: str):
    """Class decorator (outside `@dataclass`) of a section whose variants bring their own
    sub-sections (module docstring): `spec` is the "module:function" that lists them, `selector`
    the field naming the variant in use. The class declares `variants: dict = variant_tables()`.
    """

    def wrap(cls):
        cls._variants_spec, cls._variant_field = spec, selector
        names = {f.name for f in dataclasses.fields(cls) if f.init}
        init = cls.__init__

        @functools.wraps(init)
        def __init__(self, *args, **kwargs):
            given = {k: kwargs.pop(k) for k in list(kwargs) if k not in names}
            if given:
                kwargs[VARIANTS] = {**kwargs.get(VARIANTS, {}), **given}
            init(self, *args, **kwargs)

        def __eq__(self, other):
            if type(other) is not type(self):
                return NotImplemented
            plain = all(
                getattr(self, f.name) == getattr(other, f.name)
                for f in dataclasses.fields(cls)
                if not f.metadata.get(VARIANTS)
            )
            keys = set(self.__dict__[VARIANTS]) | set(other.__dict__[VARIANTS])
            return plain and all(self.variant(k) == other.variant(k) for k in keys)

        cls.__init__, cls.__eq__ = __init__, __eq__
        cls.__hash__ = None  # compared by value, as @dataclass makes every other section
        return cls

    return wrap


_HINTS: dict[type, dict[str, Any]] = {}


def type_hints(cls) -> dict[str, Any]:
    """A section class's resolved field annotations (cached: every validation reads them)."""
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def build(cls, data: dict, where: str = "", base=None):
    """Make a `cls` section from a TOML table, checking every key and value. Keys the table leaves
    out keep their value in `base` (a section's own default, e.g. `deploy.mapper.standby`)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where.rstrip('.') or 'config'}: expected a table, got {data!r}")
    hints = type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init and not f.metadata.get(VARIANTS)}
    unknown = set(data) - set(fields)
    if base is None:
        base = cls()
    kwargs = {}
    sections = ""  # a section with variants also names their sub-sections when a key is wrong
    if unknown and getattr(cls, "_variants_spec", ""):
        selector = cls._variant_field
        chosen = data.get(selector, getattr(base, selector))
        classes = cls.variant_classes(chosen if isinstance(chosen, str) else "")
        tables = {}
        for key in sorted(unknown & set(classes)):
            old = base.variant(key) if key in cls.variant_classes(base.selected_variant()) else None
            tables[key] = build(classes[key], data[key], f"{where}{key}.", old)
        unknown -= set(tables)
        kwargs[VARIANTS] = {**base.__dict__[VARIANTS], **tables}
        sections = f"; sub-sections: {', '.join(sorted(classes))}"
    if unknown:
        known = ", ".join(sorted(fields)) + sections
        name = ", ".join(f"{where}{k}" for k in sorted(unknown))
        raise ConfigError(f"unknown key {name} (known in [{where.rstrip('.') or 'top'}]: {known})")
    for name, value in data.items():
        if name not in fields:
            continue
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = build(hint, value, f"{where}{name}.", getattr(base, name))
        else:
            kwargs[name] = check_value(f"{where}{name}", value, hint, fields[name].metadata)
    return dataclasses.replace(base, **kwargs)


def check_value(key: str, v, hint, meta) -> Any:
    """`v` checked against a field's type and limits; returns it in the field's own type."""
    origin = typing.get_origin(hint)
    if origin is Literal:
        choices = typing.get_args(hint)
        if v not in choices:
            raise ConfigError(f"{key}: expected one of {list(choices)}, got {v!r}")
        return v
    if isinstance(hint, types.UnionType):  # X | None: None is spelt by leaving the key out
        if v is None:
            return None
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
        origin = typing.get_origin(hint)
    if origin is list:
        (item,) = typing.get_args(hint)
        if not isinstance(v, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {v!r}")
        return [check_value(f"{key}[{i}]", x, item, meta) for i, x in enumerate(v)]
    if hint is bool:
        if not isinstance(v, bool):
            raise ConfigError(f"{key}: expected true or false, got {v!r}")
        return v
    if hint in (int, float):
        ok = isinstance(v, numbers.Real) and not isinstance(v, bool)
        if not ok or (hint is int and v != int(v)):
            what = "an integer" if hint is int else "a number"
            raise ConfigError(f"{key}: expected {what}, got {v!r}")
        raw, v = v, hint(v)
        if not math.isfinite(v):  # 1e400 reads as inf: no parameter means infinity
            raise ConfigError(f"{key}: expected a finite number, got {raw!r}")
        for op, bound in meta.items():
            if op in _OPS and not _OPS[op][0](v, bound):
                raise ConfigError(f"{key}: expected a number {_OPS[op][1]} {bound:g}, got {raw!r}")
        return v
    if hint is str:
        if not isinstance(v, str):
            raise ConfigError(f"{key}: expected a string, got {v!r}")
        return v
    raise ConfigError(f"{key}: unsupported type {hint}")


_OPS = {
    "gt": (lambda v, b: v > b, ">"),
    "ge": (lambda v, b: v >= b, ">="),
    "lt": (lambda v, b: v < b, "<"),
    "le": (lambda v, b: v <= b, "<="),
}


def to_toml(obj) -> str:
    """Serialise a config (sections of scalars and lists, nested tables) as TOML."""
    lines: list[str] = []
    _emit(obj, "", lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def items(section) -> list[tuple[str, Any]]:
    """What a section holds, (name, value) in file order: its fields, then every variant's
    sub-section (`with_variants`: smana's and registered ones, given or defaults). What
    `to_toml` writes, and what a reader of a config walks."""
    out, tables = [], []
    for f in dataclasses.fields(section):
        if not f.init:
            continue
        if f.metadata.get(VARIANTS):
            keys = [*section.variant_classes(section.selected_variant())]
            keys += sorted(set(section.__dict__[VARIANTS]) - set(keys))
            tables += [(k, section.variant(k)) for k in keys]
        else:
            out.append((f.name, getattr(section, f.name)))
    return out + tables


def _emit(obj, prefix: str, lines: list[str]) -> None:
    scalars, tables = [], []
    for name, v in items(obj):
        (tables if dataclasses.is_dataclass(v) else scalars).append((name, v))
    if prefix and scalars:
        lines.append(f"\n[{prefix}]")
    for name, v in scalars:
        if v is not None:
            lines.append(f"{name} = {_toml_value(v)}")
    for name, v in tables:
        _emit(v, f"{prefix}.{name}" if prefix else name, lines)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {v!r} as TOML")
