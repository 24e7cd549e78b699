"""Dataset readers: one class per on-disk format, found by name or by looking at the path.

Reader modules are imported only when their format is used, so that a missing optional package
(`rosbags` for bags) only matters to whoever replays a bag.

Adding a reader: one module with a `DatasetReader` subclass, plus one line in `READERS` (a
`smana.common.registry.Registry`, in this package), or `register("name", "package.module:Class")`
(or the class) from outside smana. A format may also be
given as the spec itself: `--set replay.format=my_pkg.my_reader:MyReader`.
"""

from __future__ import annotations

import inspect
from pathlib import Path

from smana.common.registry import Registry

from .base import DatasetError, DatasetInfo, DatasetReader, Scan, SkippedScan

# format name -> "module:Class", imported when a dataset of that format is opened
READERS = Registry(
    "replay.format",
    {
        "semantickitti": "smana.services.replay.readers.semantickitti:SemanticKittiReader",
        "rellis3d": "smana.services.replay.readers.rellis3d:Rellis3dReader",
        "rosbag": "smana.services.replay.readers.rosbag:RosbagReader",
        "folder": "smana.services.replay.readers.folder:FolderReader",
    },
    base=DatasetReader,
    hints={"rosbags": "pip install 'smana[replay]'"},
)

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


def register(fmt: str, reader: str | type[DatasetReader]) -> None:
    """Add (or replace) the reader of format `fmt`: a `DatasetReader` subclass, or its
    "package.module:Class" (imported when a dataset of that format is opened)."""
    READERS.register(fmt, reader)


def reader_class(fmt: str) -> type[DatasetReader]:
    """The reader of a format name, or of a "package.module:Class" spec; a one-line
    `RegistryError` (a `ValueError`) naming the known formats, or what to install."""
    return READERS.get(fmt)


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
