"""What a message may hold: the base class every schema derives from, its field kinds (arrays
with a dtype, shape and group; scalars with a range), the bounds on values no robot can produce,
and the one error a decoder raises. The schemas themselves are in `messages.py`, their codec in
`codec.py`; code imports all three from `smana.common.messages`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

SCHEMA_VERSION = 1  # the version of a message type that never changed (Message.VERSION)
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024  # a 131k-point cloud is ~2.2 MB; 64 MB leaves room for maps

# Bounds on values no robot can produce: refused as `value` by the decoder, so no service ever
# computes with them. Coordinates: 1000 km from the world origin. Stamps: seconds (simulated,
# dataset or Unix time) up to the year 2286. Sequence numbers and every integer: int64.
COORD_LIMIT_M = 1.0e6
STAMP_LIMIT_S = 1.0e10
INT_LIMIT = 2**63 - 1
RESOLUTION_RANGE_M = (1.0e-3, 100.0)

ERROR_KINDS = (
    "oversize",  # payload larger than the limit
    "malformed",  # not msgpack/JSON, or not a map with a type tag
    "type",  # a message of another type than expected
    "version",  # schema version this build does not speak
    "missing_field",
    "unknown_field",
    "dtype",  # array of a dtype the schema does not allow
    "shape",  # array of the wrong rank or inner dimensions, or data of the wrong byte size
    "length",  # arrays that must have the same length do not
    "nonfinite",  # NaN or inf where a finite number is required
    "value",  # a scalar of the wrong type or outside its range
)


class MessageError(ValueError):
    """A payload that is not a valid message. `kind` is one of ERROR_KINDS."""

    def __init__(self, kind: str, message: str):
        assert kind in ERROR_KINDS, kind
        super().__init__(f"{kind}: {message}")
        self.kind = kind


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may hold. `shape` uses None for a free dimension; dimensions that share a
    `group` name must agree across the fields of one message (e.g. every per-point array has N)."""

    dtypes: tuple[str, ...]
    shape: tuple[int | None, ...]
    group: str | None = None
    finite: bool = True
    shapes: tuple[tuple[int | None, ...], ...] = ()  # alternatives to `shape` (e.g. 2 or 3 coords)
    limit: float | None = None  # largest magnitude a value may have (coordinates: COORD_LIMIT_M)

    def allowed_shapes(self) -> tuple[tuple[int | None, ...], ...]:
        return (self.shape, *self.shapes)


def array(dtypes, shape, group=None, finite=True, shapes=(), default=None, limit=None, since=1):
    """A dataclass field holding a numpy array with the given spec; `since`: the first version of
    its message that carries it."""
    spec = ArraySpec(
        tuple(np.dtype(d).str for d in dtypes), tuple(shape), group, finite, shapes, limit
    )
    meta = {"array": spec, "since": since}
    if default is None:

        def empty():
            return np.zeros(tuple(0 if s is None else s for s in shape), spec.dtypes[0])

        return field(default_factory=empty, metadata=meta)
    return field(default_factory=default, metadata=meta)


# -- the messages ---------------------------------------------------------------------------------

REGISTRY: dict[str, type[Message]] = {}


@dataclass
class Message:
    """Base of every message. Subclasses are registered by class name."""

    TYPE: ClassVar[str] = ""
    # The version this build writes for the type. It reads every version from 1 up to it: a
    # field declared `since` a later version than a message's must be absent from it, takes its
    # default, and `upgrade(version)` then makes the message what the newer form means.
    VERSION: ClassVar[int] = SCHEMA_VERSION
    # Fields a JSON query may leave out (they take their defaults). The msgpack wire form always
    # carries every field, so there a missing field is an error.
    JSON_OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        cls.TYPE = cls.__name__
        REGISTRY[cls.__name__] = cls

    def check(self) -> None:
        """Checks across fields, after each field passed its own (raise MessageError)."""

    def upgrade(self, version: int) -> None:
        """Fill the fields a message of an older `version` did not carry (they hold defaults)."""

    def wire_overrides(self) -> dict:
        """Fields sent with another value than they hold (what a local field says on the wire)."""
        return {}


def scalar(default, lo=None, hi=None):
    """A scalar field whose value must lie in [lo, hi] (either end may be open: None)."""
    return field(default=default, metadata={"range": (lo, hi)})
