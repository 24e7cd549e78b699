"""Where a fuzz input's choices come from and the wild values drawn from them, for every
generator of the lab (fuzz_messages.py, fuzz_maps.py, fuzz_ros2.py): `Draw`, a small source of
choices (`RandomDraw`, a seeded `random.Random`, drives `smana bench fuzz`; the test suite wraps
a hypothesis `data` object in the same interface), and the pools of values a field may receive
instead of its own (`WILD_SCALARS`, `WILD_STRINGS`, `DTYPES`, `SHAPES`, `WILD_MAPS`;
`wild_float`, `wild_scalar`, `wild_value`)."""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from smana.common.messages import (
    COORD_LIMIT_M,
    MAX_PAYLOAD_BYTES,
    STAMP_LIMIT_S,
)

# -- sources of choices ---------------------------------------------------------------------------


class Draw:
    """Where a generator's choices come from. Subclasses provide `integer`; the rest derive."""

    def integer(self, lo: int, hi: int) -> int:
        """An int in [lo, hi] (both included)."""
        raise NotImplementedError

    def choice(self, options: Sequence):
        return options[self.integer(0, len(options) - 1)]

    def boolean(self, p_true: float = 0.5) -> bool:
        return self.integer(0, 999) < int(p_true * 1000)

    def unit(self) -> float:
        """A float in [0, 1)."""
        return self.integer(0, 2**24 - 1) / 2**24

    def rng(self) -> np.random.Generator:
        """A numpy generator for bulk contents, seeded by one choice."""
        return np.random.default_rng(self.integer(0, 2**32 - 1))

    def blob(self, n: int) -> bytes:
        return self.rng().bytes(n) if n else b""


class RandomDraw(Draw):
    """Choices from a seeded `random.Random` (the bench)."""

    def __init__(self, seed_or_rng: int | random.Random = 0):
        self.r = (
            seed_or_rng if isinstance(seed_or_rng, random.Random) else random.Random(seed_or_rng)
        )

    def integer(self, lo: int, hi: int) -> int:
        return self.r.randint(lo, hi)


# -- value pools ----------------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")

# Scalars of every sort a field may receive instead of its own (all msgpack- and JSON-packable
# except where noted in `_packable`).
WILD_SCALARS: tuple[Any, ...] = (
    0,
    1,
    -1,
    0.0,
    -0.0,
    0.5,
    1e-300,
    5e-324,
    1e300,
    -1e300,
    NAN,
    INF,
    -INF,
    2**31 - 1,
    2**31,
    2**53 + 1,
    2**63 - 1,
    2**63,
    2**64 - 1,
    -(2**63),
    -(2**63) - 1,
    True,
    False,
    None,
    "",
    "1",
    "1.0",
    "nan",
    "inf",
    "world",
    "0x10",
    " 1 ",
    "\u00e9\u6f22",
    b"",
    b"\x00\xff",
    [],
    [1, 2, 3],
    [NAN],
    {},
    {"a": 1},
    {"a": NAN},
    {"a": {"b": INF}},
    {"a": [NAN]},
    {1: 2.0},
    {"1": "x"},
    {"1": "nan"},
    {"2": 1e300},
)

WILD_STRINGS: tuple[str, ...] = (
    "",
    " ",
    "world ",
    "World",
    "odom",
    "map",
    "\x00",
    "world\x00",
    "../../etc/passwd",
    "*",
    "**",
    "$*",
    "a/b",
    "\u202e",
    "\U0001f916" * 10,
    "x" * 10_000,
)

# dtype strings for an array's "dtype": other kinds, other byte orders, aliases (some of them are
# valid spellings of an allowed dtype: the codec must accept those), nonsense.
DTYPES: tuple[Any, ...] = (
    "<f4",
    ">f4",
    "=f4",
    "|f4",
    "f4",
    "float32",
    "single",
    "<f8",
    ">f8",
    "f8",
    "d",
    "<f2",
    "<i4",
    ">i4",
    "i4",
    "<i8",
    "<u2",
    ">u2",
    "u2",
    "|u1",
    "u1",
    "uint8",
    "|b1",
    "?",
    "|i1",
    "<c8",
    "<c16",
    "|O",
    "O",
    "object",
    "<U4",
    "|S4",
    "|V4",
    "V12",
    "<M8[s]",
    "<m8[ns]",
    "",
    "xyz",
    "f",
    "<f3",
    "<f4 ",
    "f4,f4",
    "(3,)f4",
    "<f16",
    5,
    4.0,
    None,
    True,
    [],
    {},
    [["a", "<f4"]],
    [["x", "<f4"], ["y", "<f4"], ["z", "<f4"]],
    {"names": ["a"], "formats": []},
    b"<f4",
    "\u00e9",
)

# Shapes for an array's "shape", some as functions of the true row count n.
SHAPES: tuple[Callable[[int], Any], ...] = (
    lambda n: [2**32, 2**32],
    lambda n: [2**32, 2**32, 0],
    lambda n: [2**63, 0],
    lambda n: [2**64 - 1],
    lambda n: [2**63 - 1, 3],
    lambda n: [-1, 3],
    lambda n: [-(2**63)],
    lambda n: [n, -3],
    lambda n: [0],
    lambda n: [0, 3],
    lambda n: [],
    lambda n: [n, 3, 1],
    lambda n: [n + 1, 3],
    lambda n: [max(n - 1, 0), 3],
    lambda n: [n, 2],
    lambda n: [n, 4],
    lambda n: [n],
    lambda n: [3 * n],
    lambda n: [1, n, 3],
    lambda n: [str(n), 3],
    lambda n: [float(n), 3.0],
    lambda n: [True, 3],
    lambda n: None,
    lambda n: str(n),
    lambda n: {},
    lambda n: [[n], [3]],
    lambda n: [MAX_PAYLOAD_BYTES + 1, 0],
    lambda n: [0, 2**40],
    lambda n: [2**31, 2**31, 0],
    lambda n: (n, 3),
)


# Maps for map-typed fields (class costs, status details): ids and costs as strings, bools,
# negative and fractional ids, NaN hidden in a string, nested NaN, values of the wrong type.
WILD_MAPS: tuple[dict, ...] = (
    {"1": "nan"},
    {"1": "inf"},
    {"2": "-1e999"},
    {True: 1.0},
    {1: True},
    {-5: 1.0},
    {1.5: 2.0},
    {"x": 1},
    {1: None},
    {1: [1]},
    {1: {"a": NAN}},
    {1: NAN},
    {1: -INF},
    {2**64 - 1: 1.0},
    {"1": " 2 "},
    {"0x1": 1.0},
    {INF: 1.0},
    {NAN: 1.0},
    {b"1": 1.0},
    {"": 0},
    {"1": 1e300},
    {str(i): float(i) for i in range(300)},
)


def wild_float(d: Draw) -> float:
    return d.choice(
        (
            NAN,
            INF,
            -INF,
            1e300,
            -1e300,
            3.5e38,
            -3.5e38,
            1e-45,
            -0.0,
            0.0,
            1e6,
            -1e6,
            1e6 + 1.0,
            COORD_LIMIT_M * 1.0000001,
            STAMP_LIMIT_S + 1.0,
        )
    )


def wild_scalar(d: Draw) -> Any:
    return d.choice(WILD_SCALARS)


def wild_value(d: Draw, depth: int = 0) -> Any:
    """A random msgpack-packable value: scalars, strings, bytes, lists and maps, nested."""
    k = d.integer(0, 9 if depth < 3 else 5)
    if k <= 3:
        return wild_scalar(d)
    if k == 4:
        return d.choice(WILD_STRINGS)
    if k == 5:
        return d.blob(d.choice((0, 1, 7, 300)))
    if k <= 7:
        return [wild_value(d, depth + 1) for _ in range(d.integer(0, 4))]
    return {
        d.choice(("a", "box", "name", "x", "y", "points", "_type", 1)): wild_value(d, depth + 1)
        for _ in range(d.integer(0, 4))
    }
