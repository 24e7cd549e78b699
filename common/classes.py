"""The class table: which semantic labels exist, which are traversable and at what cost.

The table is data (a TOML file), not code, because every dataset numbers its classes differently
(3DRMS garden, RELLIS-3D, SemanticKITTI). Services look classes up through dense lookup arrays
indexed by label id, so that hot loops never touch a Python dict.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

# "forbidden": flat and geometrically traversable, but never to be entered (water): not an obstacle
# (no safety zone round it, the robot may pass beside it) and not traversable (cost +inf).
KINDS = ("unknown", "traversable", "obstacle", "ignored", "forbidden")
UNKNOWN_ID = 0
MAX_CLASS_ID = 65535  # labels travel as uint8 or uint16


class ClassTableError(ValueError):
    """A class table file is malformed."""


# One colour per fleet member (r1, r2, ...; RGB uint8), for its body, path and goal in the
# recording and its trajectory in the report's figures: saturated, apart from the class colours'
# greens and browns.
MEMBER_COLOURS = (
    (255, 230, 0),
    (25, 115, 255),
    (255, 50, 150),
    (0, 240, 240),
    (150, 50, 255),
    (255, 128, 0),
)


@dataclass(frozen=True)
class SemanticClass:
    id: int
    name: str
    kind: str
    cost: float | None = None
    colour: tuple[int, int, int] = (255, 255, 255)
    # Ids of a dataset's own numbering that this class stands for (RELLIS-3D, SemanticKITTI):
    # lets a replayed dataset keep its label files while the stack sees compact table ids.
    maps_from: tuple[int, ...] = ()

    @property
    def traversable(self) -> bool:
        return self.kind == "traversable"

    @property
    def obstacle(self) -> bool:
        return self.kind == "obstacle"

    @property
    def forbidden(self) -> bool:
        return self.kind == "forbidden"


class ClassTable:
    """Classes by id, plus dense per-id lookup arrays for vectorised code.

    `size` is one more than the largest id; every array below has that length:
    - `valid_lut[id]`: the id is in the table;
    - `cost_lut[id]`: traversability cost T(l), +inf where the class is not traversable;
    - `obstacle_lut[id]`, `traversable_lut[id]`, `ignored_lut[id]`, `forbidden_lut[id]`:
      booleans;
    - `colour_lut[id]`: RGB uint8 (unknown ids are magenta so they stand out).
    """

    def __init__(self, name: str, classes: list[SemanticClass]):
        if not classes:
            raise ClassTableError(f"class table {name!r} has no classes")
        ids = [c.id for c in classes]
        if len(set(ids)) != len(ids):
            raise ClassTableError(f"class table {name!r} has duplicate ids")
        if UNKNOWN_ID not in ids:
            raise ClassTableError(f"class table {name!r} must define id {UNKNOWN_ID} (unknown)")
        self.name = name
        self.classes = {c.id: c for c in sorted(classes, key=lambda c: c.id)}
        self.size = max(ids) + 1
        self.valid_lut = np.zeros(self.size, bool)
        self.cost_lut = np.full(self.size, np.inf, np.float64)
        self.obstacle_lut = np.zeros(self.size, bool)
        self.traversable_lut = np.zeros(self.size, bool)
        self.ignored_lut = np.zeros(self.size, bool)
        self.forbidden_lut = np.zeros(self.size, bool)
        self.colour_lut = np.tile(np.array([255, 0, 255], np.uint8), (self.size, 1))
        for c in classes:
            self.valid_lut[c.id] = True
            self.obstacle_lut[c.id] = c.obstacle
            self.traversable_lut[c.id] = c.traversable
            self.ignored_lut[c.id] = c.kind == "ignored"
            self.forbidden_lut[c.id] = c.forbidden
            self.colour_lut[c.id] = c.colour
            if c.traversable:
                self.cost_lut[c.id] = c.cost
        self._dataset_lut = _dataset_lut(name, classes)

    @property
    def maps_dataset_ids(self) -> bool:
        """True when the table translates a dataset's numbering (some class has `maps_from`)."""
        return self._dataset_lut is not None

    def map_dataset_labels(self, raw: np.ndarray) -> tuple[np.ndarray, int]:
        """Dataset label ids -> table ids (uint16) through `maps_from`.

        Ids that no class claims become unknown; returns (labels, how many were unclaimed). A
        table without any `maps_from` takes dataset ids as its own ids (then this is `sanitise`).
        """
        raw = np.asarray(raw)
        if raw.dtype.kind not in "iu":
            raise ValueError(f"labels must be integers, got {raw.dtype}")
        if self._dataset_lut is None:
            labels, n_bad = self.sanitise(raw)
            return labels.astype(np.uint16, copy=False), n_bad
        lut = self._dataset_lut
        inside = (raw >= 0) & (raw < lut.size)
        out = np.zeros(raw.shape, np.int32)
        out[inside] = lut[raw[inside]]
        unclaimed = out < 0
        unclaimed |= ~inside
        out[unclaimed] = UNKNOWN_ID
        return out.astype(np.uint16), int(unclaimed.sum())

    # -- loading -------------------------------------------------------------------------------

    @classmethod
    def load(cls, name_or_path: str | Path) -> ClassTable:
        """Load a bundled table by name (`garden3drms`, ...) or a TOML file by path."""
        path = Path(name_or_path)
        if path.suffix == ".toml" or path.exists():
            if not path.is_file():
                raise ClassTableError(f"class table file not found: {path}")
            text = path.read_text()
            origin = str(path)
        else:
            res = resources.files("smana.common").joinpath("classes", f"{name_or_path}.toml")
            if not res.is_file():
                known = ", ".join(bundled_tables())
                raise ClassTableError(f"no bundled class table {name_or_path!r} (known: {known})")
            text = res.read_text()
            origin = f"bundled:{name_or_path}"
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ClassTableError(f"{origin}: {exc}") from exc
        return cls.from_dict(data, origin)

    @classmethod
    def from_dict(cls, data: dict, origin: str = "<dict>") -> ClassTable:
        entries = data.get("class")
        if not isinstance(entries, list):
            raise ClassTableError(f"{origin}: expected [[class]] entries")
        classes = []
        for i, e in enumerate(entries):
            where = f"{origin}: class #{i}"
            unknown_keys = set(e) - {"id", "name", "kind", "cost", "colour", "maps_from"}
            if unknown_keys:
                raise ClassTableError(f"{where}: unknown keys {sorted(unknown_keys)}")
            try:
                cid, cname, kind = int(e["id"]), str(e["name"]), str(e["kind"])
            except KeyError as exc:
                raise ClassTableError(f"{where}: missing {exc.args[0]!r}") from None
            if not 0 <= cid <= MAX_CLASS_ID:
                raise ClassTableError(f"{where}: id {cid} outside 0..{MAX_CLASS_ID}")
            if kind not in KINDS:
                raise ClassTableError(f"{where}: kind {kind!r} not one of {KINDS}")
            cost = e.get("cost")
            if kind == "traversable":
                if cost is None or not float(cost) >= 0:
                    raise ClassTableError(f"{where}: traversable class needs a cost >= 0")
                cost = float(cost)
            colour = tuple(int(v) for v in e.get("colour", (255, 255, 255)))
            if len(colour) != 3 or not all(0 <= v <= 255 for v in colour):
                raise ClassTableError(f"{where}: colour must be three integers 0..255")
            maps_from = e.get("maps_from", [])
            if not isinstance(maps_from, list) or not all(
                isinstance(v, int) and 0 <= v <= MAX_CLASS_ID for v in maps_from
            ):
                raise ClassTableError(f"{where}: maps_from must be a list of ids 0..{MAX_CLASS_ID}")
            classes.append(SemanticClass(cid, cname, kind, cost, colour, tuple(maps_from)))
        return cls(str(data.get("name", origin)), classes)

    # -- queries -------------------------------------------------------------------------------

    def __contains__(self, class_id: int) -> bool:
        return 0 <= class_id < self.size and bool(self.valid_lut[class_id])

    def __getitem__(self, class_id: int) -> SemanticClass:
        return self.classes[class_id]

    def by_name(self, name: str) -> SemanticClass:
        for c in self.classes.values():
            if c.name == name:
                return c
        raise KeyError(name)

    @property
    def ids(self) -> np.ndarray:
        return np.array(sorted(self.classes), np.int64)

    def costs(self, overrides: dict[int, float] | None = None) -> np.ndarray:
        """`cost_lut` with some classes' costs replaced (a per-request override)."""
        lut = self.cost_lut.copy()
        for cid, cost in (overrides or {}).items():
            if cid not in self or not self.classes[cid].traversable:
                raise ValueError(f"class {cid} is not a traversable class of {self.name}")
            if not cost >= 0:
                raise ValueError(f"cost for class {cid} must be >= 0, got {cost}")
            lut[cid] = cost
        return lut

    def cost_overrides(self, items: list[str]) -> dict[int, float]:
        """Traversability-cost overrides written as text (`explorer.class_costs`, `smana plan
        --cost`): ["grass=4", "2=1.5"] -> {1: 4.0, 2: 1.5}. A class by name or id, a cost >= 0
        (inf makes the class impassable); anything else is a ValueError naming the item."""
        out: dict[int, float] = {}
        for item in items:
            name, sep, value = item.partition("=")
            name = name.strip()
            try:
                if not sep:
                    raise ValueError
                cost = float(value)
            except ValueError:
                raise ValueError(f"{item!r} must look like CLASS=COST (a name or an id)") from None
            try:
                cid = int(name) if name.isdigit() else self.by_name(name).id
            except KeyError:
                raise ValueError(f"no class {name!r} in {self.name}") from None
            self.costs({cid: cost})  # an obstacle class, or a cost below 0 (or NaN): refused
            out[cid] = cost
        return out

    def sanitise(self, labels: np.ndarray) -> tuple[np.ndarray, int]:
        """Map ids outside the table to unknown; returns (labels, how many were replaced)."""
        labels = np.asarray(labels)
        inside = labels < self.size
        bad = ~inside
        bad[inside] = ~self.valid_lut[labels[inside]]
        n_bad = int(bad.sum())
        if n_bad:
            labels = labels.copy()
            labels[bad] = UNKNOWN_ID
        return labels, n_bad


def _dataset_lut(name: str, classes: list[SemanticClass]) -> np.ndarray | None:
    """Dense dataset id -> table id array (-1 where no class claims the id), or None if unused."""
    claimed = {v: c.id for c in classes for v in c.maps_from}
    if not claimed:
        return None
    if sum(len(c.maps_from) for c in classes) != len(claimed):
        raise ClassTableError(f"class table {name!r}: a dataset id is in two classes' maps_from")
    lut = np.full(max(claimed) + 1, -1, np.int32)
    for raw_id, cid in claimed.items():
        lut[raw_id] = cid
    return lut


def bundled_tables() -> list[str]:
    folder = resources.files("smana.common").joinpath("classes")
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))
