"""Dataset readers: one class per on-disk format, found by name or by looking at the path.

Reader modules are imported only when their format is used, so that a missing optional package
(`rosbags` for bags) only matters to whoever replays a bag.

Adding a reader: one module with a `DatasetReader` subclass, plus one line in `READERS` (in this
package), or `register("name", "package.module:Class")` from outside smana. A format may also be
given as the spec itself: `--set replay.format=my_pkg.my_reader:MyReader`.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
from pathlib import Path

from .base import DatasetError, DatasetInfo, DatasetReader, Scan, SkippedScan

# format name -> (module, class); a module starting with "." is one of this package's
READERS = {
    "semantickitti": (".semantickitti", "SemanticKittiReader"),
    "rellis3d": (".rellis3d", "Rellis3dReader"),
    "rosbag": (".rosbag", "RosbagReader"),
    "folder": (".folder", "FolderReader"),
}

__all__ = [
    "READERS",
    "DatasetError",
    "DatasetInfo",
    "DatasetReader",
    "Scan",
    "SkippedScan",
    "detect_format",
    "open_dataset",
    "reader_class",
    "register",
]


def _spec(spec: str) -> tuple[str, str]:
    module, sep, cls = spec.partition(":")
    if not (sep and module and cls):
        raise ValueError(f"reader {spec!r}: expected package.module:Class")
    return module, cls


def register(fmt: str, spec: str) -> None:
    """Add (or replace) the reader of format `fmt`, a `DatasetReader` subclass named as
    "package.module:Class": imported when a dataset of that format is opened."""
    READERS[fmt] = _spec(spec)


def reader_class(fmt: str) -> type[DatasetReader]:
    """The reader of a format name, or of a "package.module:Class" spec."""
    if fmt in READERS:
        module, name = READERS[fmt]
    elif ":" in fmt:
        module, name = _spec(fmt)
    else:
        raise ValueError(f"unknown dataset format {fmt!r} (known: {', '.join(READERS)})")
    try:
        mod = importlib.import_module(module, __name__)
    except ModuleNotFoundError as exc:
        absolute = importlib.util.resolve_name(module, __name__)
        if exc.name and (absolute == exc.name or absolute.startswith(exc.name + ".")):
            raise ValueError(f"dataset format {fmt!r}: no module {module!r}") from None
        raise  # the reader's own optional dependency: its message says what to install
    cls = getattr(mod, name, None)
    if not (isinstance(cls, type) and issubclass(cls, DatasetReader)):
        raise ValueError(f"dataset format {fmt!r}: {module}:{name} is not a DatasetReader")
    return cls


def detect_format(path: str | Path) -> str:
    """Guess the format from the layout; raises DatasetError when nothing fits."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "does not exist")
    if path.is_file():
        if path.suffix in (".bag", ".mcap"):
            return "rosbag"
        raise DatasetError(path, "a file must be a .bag or .mcap; other datasets are folders")
    if (path / "metadata.yaml").is_file():
        return "rosbag"
    children = [p for p in path.iterdir() if p.is_dir()]
    if (
        (path / "os1_cloud_node_kitti_bin").is_dir()
        or (path / "Rellis-3D").is_dir()
        or any((c / "os1_cloud_node_kitti_bin").is_dir() for c in children)
    ):
        return "rellis3d"
    if (path / "velodyne").is_dir() or (path / "sequences").is_dir():
        return "semantickitti"
    if any(path.glob("*.ply")) or any(path.glob("*.npz")):
        return "folder"
    raise DatasetError(path, f"cannot tell the dataset format; name one of {', '.join(READERS)}")


def open_dataset(path: str | Path, fmt: str | None = None, **options) -> DatasetReader:
    """Open a dataset with the reader for `fmt` (detected when None).

    Options left at None are dropped; an option the reader does not take is an error rather
    than silently ignored (a label field given for a SemanticKITTI folder means a mistake).
    """
    fmt = fmt or detect_format(path)
    cls = reader_class(fmt)
    given = {k: v for k, v in options.items() if v is not None}
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "path"}
    extra = sorted(set(given) - accepted)
    if extra:
        raise ValueError(f"option(s) {', '.join(extra)} do not apply to {fmt} datasets")
    return cls(path, **given)
