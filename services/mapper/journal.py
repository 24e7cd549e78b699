"""The mapper's journal: an append-only log of the map since its last autosave (no zenoh).

Why a journal of voxel *states*, not the delta stream: a `MapDelta` carries what consumers need
(centre, fused label and confidence, occupied, one value), not the back-end's state. The octrees
keep their top-k label distribution, the TSDF its weights and per-class log-probabilities; a map
rebuilt from deltas looks the same until the next cloud, then fuses it differently, and saves a
different file. So after every integration the mapper appends, for each voxel the cloud changed,
every column the back-end holds (`SemanticMap.voxel_state`), plus the service's counters. A
record sets absolute states, so replaying one twice changes nothing: a crash between an autosave
and the journal's rotation loses nothing and doubles nothing.

A process that takes over (the hot spare, or a plain restart) opens the journal, loads the
autosave, and applies every whole record (`JournalReader`); a record cut short by `kill -9` in the
middle of its write (or one whose checksum fails) ends the replay and is counted (`torn_bytes`),
then cut off so that the new mapper appends after the last whole record. A hot spare follows the
file while it stands by (`JournalReader.poll`), so the take-over only reads the last few records.

Records are written with `os.write` and no fsync: a process killed with -9 loses nothing the kernel
has accepted; a power cut may lose the page cache's last seconds (the autosave is fsynced).

File layout: records of `<4s magic><u32 length><u32 crc32>` followed by a msgpack map. The first
record is the header `{"kind": "header", "backend", "resolution_m", "fields", "service"}`, the rest
`{"kind": "voxels", "keys": N x 3 int32, "cols": {name: rows}, "service": {counters}}`.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

MAGIC = b"SMJ1"
_FRAME = struct.Struct("<4sII")
MAX_RECORD_BYTES = 1 << 31  # a length beyond this is garbage, not a record


def journal_path(save_path: Path) -> Path:
    """The journal that goes with an autosave: `map.npz` -> `map.journal`."""
    return save_path.with_suffix(".journal")


def _array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def _unarray(d: dict) -> np.ndarray:
    return np.frombuffer(d["data"], np.dtype(d["dtype"])).reshape(d["shape"])


def frame(payload: dict) -> bytes:
    body = msgpack.packb(payload, use_bin_type=True)
    return _FRAME.pack(MAGIC, len(body), zlib.crc32(body)) + body


def _header(m, service: dict) -> dict:
    return {
        "kind": "header",
        "backend": m.backend,
        "resolution_m": m.resolution_m,
        "fields": sorted(m.column_names()),
        "service": service,
    }


class JournalWriter:
    """Appends records to a journal file (opened at `offset`: what follows is cut off)."""

    def __init__(self, path: Path, m, service: dict, offset: int | None = None):
        self.path = Path(path)
        self.map = m
        self.records = 0
        self.bytes = 0
        if offset is None:
            self._fd = None
            self.rotate(service)
        else:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT)
            os.ftruncate(self._fd, offset)
            os.lseek(self._fd, offset, os.SEEK_SET)
            self.bytes = offset

    def append(self, keys: np.ndarray, service: dict) -> int:
        """One integration: the full state of the voxels at `keys` (the delta's), and the
        service's counters after it. Returns the bytes written."""
        cols = self.map.voxel_state(keys)
        rec = frame(
            {
                "kind": "voxels",
                "keys": _array(np.asarray(keys, np.int32)),
                "cols": {k: _array(v) for k, v in cols.items()},
                "service": service,
            }
        )
        os.write(self._fd, rec)
        self.records += 1
        self.bytes += len(rec)
        return len(rec)

    def rotate(self, service: dict) -> None:
        """After an autosave: a new journal holding only its header (the map file holds the
        rest). Written beside and renamed over, so a reader sees the old file or the new one."""
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.parent.mkdir(parents=True, exist_ok=True)  # a run directory not made yet
        head = frame(_header(self.map, service))
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.write(fd, head)
        os.replace(tmp, self.path)
        if self._fd is not None:
            os.close(self._fd)
        self._fd = fd
        self.records = 0
        self.bytes = len(head)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


@dataclass
class ReplayBooks:
    """What a reader applied: records and voxels, the bytes of a torn last record, the service
    counters of the last record (or header) read, and the journal files it went through."""

    records: int = 0
    voxels: int = 0
    torn_bytes: int = 0
    skipped: str = ""  # why a journal was ignored (another back-end or resolution)
    service: dict = field(default_factory=dict)
    files: int = 0


class JournalReader:
    """Follows a journal into a map: `poll()` applies every whole record written since the last
    call, and moves on to the new file after a rotation (the old one is read to its end first:
    the writer finished it before the rename). Open it before loading the autosave: then a
    rotation in between leaves it on the old file, whose records the map file already holds or
    that come after it (replaying them is harmless)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.books = ReplayBooks()
        self.map = None
        self._buf = b""
        self._fd = None
        self._ino = None
        self.offset = 0  # end of the last whole record in the current file
        self._header_ok = False
        self._open()

    def _open(self) -> bool:
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return False
        if self._fd is not None:
            os.close(self._fd)
        self._fd, self._ino = fd, os.fstat(fd).st_ino
        self._buf, self.offset, self._header_ok = b"", 0, False
        self.books.files += 1
        return True

    @property
    def exists(self) -> bool:
        return self._fd is not None

    def attach(self, m) -> None:
        """The map the records go into (loaded after the reader opened the file)."""
        self.map = m

    def poll(self) -> int:
        """Apply what is new; returns the voxel records applied (then `recount()` the map)."""
        if self._fd is None and not self._open():
            return 0
        n0 = self.books.records
        self._read()
        try:
            ino = os.stat(self.path).st_ino
        except FileNotFoundError:
            return self.books.records - n0
        if ino != self._ino:  # rotated: the old file is complete, the new one starts fresh
            self._read()
            self._open()
            self._read()
        return self.books.records - n0

    def finish(self) -> int:
        """At take-over (the writer is gone): whatever is left after the last whole record is a
        record cut short (counted in `torn_bytes`). Returns the offset to append at."""
        self.poll()
        self.books.torn_bytes = len(self._buf)
        return self.offset

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _read(self) -> None:
        chunks = [self._buf]
        while chunk := os.read(self._fd, 1 << 20):
            chunks.append(chunk)
        buf = b"".join(chunks)
        view, at = memoryview(buf), 0  # records are read in place, the rest kept once
        while len(buf) - at >= _FRAME.size:
            magic, length, crc = _FRAME.unpack_from(buf, at)
            if magic != MAGIC or length > MAX_RECORD_BYTES:
                break  # garbage: nothing after it is read (finish() counts it torn)
            end = at + _FRAME.size + length
            if len(buf) < end:
                break  # still being written, or cut short
            body = view[at + _FRAME.size : end]
            if zlib.crc32(body) != crc:
                break
            self._apply(msgpack.unpackb(body, raw=False))
            self.offset += end - at
            at = end
        view.release()
        self._buf = buf[at:]

    def _apply(self, rec: dict) -> None:
        m = self.map
        if rec.get("kind") == "header":
            fits = (
                rec["backend"] == m.backend
                and rec["resolution_m"] == m.resolution_m
                and rec["fields"] == sorted(m.column_names())
            )
            self._header_ok = fits
            if not fits:
                self.books.skipped = (
                    f"journal {self.path} is for {rec['backend']} at {rec['resolution_m']} m, the "
                    f"map is {m.backend} at {m.resolution_m} m"
                )
            self.books.service = rec.get("service") or self.books.service
            return
        if not self._header_ok:
            return
        keys = _unarray(rec["keys"])
        m.set_voxel_state(keys, {k: _unarray(v) for k, v in rec["cols"].items()})
        self.books.records += 1
        self.books.voxels += int(keys.shape[0])
        self.books.service = rec["service"]
