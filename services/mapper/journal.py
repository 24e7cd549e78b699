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
autosave, and applies every whole record (`JournalReader`). Nothing in the file is trusted: a
record is applied only when its checksum holds and its content fits the map (`check_record`, the
map loader's checks); damage costs the damaged record only (the reader goes on at the next magic
and counts what it skipped: `damaged_bytes`, `bad_records`); a record cut short by `kill -9` in
the middle of its write is counted (`torn_bytes`) and cut off, so that the new mapper appends
after the last whole record and the journal keeps what was replayed. A hot spare follows the file
while it stands by (`JournalReader.poll`), so the take-over only reads the last few records.

Records are written with `os.write` and no fsync: a process killed with -9 loses nothing the kernel
has accepted; a power cut may lose the page cache's last seconds (the autosave is fsynced).

File layout: records of `<4s magic><u32 length><u32 crc32>` followed by a msgpack map. The first
record is the header `{"kind": "header", "generation", "backend", "resolution_m", "fields",
"service"}` (`generation`: one more than the journal file before it), the rest
`{"kind": "voxels", "keys": N x 3 int32, "cols": {name: rows}, "service": {counters}}`.
"""

from __future__ import annotations

import math
import os
import stat
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from smana.services.mapper.block_grid import KEY_LIMIT
from smana.services.mapper.mapfile import check_values

MAGIC = b"SMJ1"
RECORD_FRAME = struct.Struct("<4sII")  # a record: magic, body length, CRC-32 of the body
MAX_RECORD_BYTES = 1 << 31  # a length beyond this is garbage, not a record


def journal_path(save_path: Path) -> Path:
    """The journal that goes with an autosave: `map.npz` -> `map.journal`."""
    return save_path.with_suffix(".journal")


def packed_array(a: np.ndarray) -> dict:
    """An array as a record holds it: its dtype, shape and raw bytes."""
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def frame(payload: dict) -> bytes:
    body = msgpack.packb(payload, use_bin_type=True)
    return RECORD_FRAME.pack(MAGIC, len(body), zlib.crc32(body)) + body


def _header(m, service: dict, generation: int) -> dict:
    return {
        "kind": "header",
        "generation": generation,
        "backend": m.backend,
        "resolution_m": m.resolution_m,
        "fields": sorted(m.column_names()),
        "service": service,
    }


class JournalWriter:
    """Appends records to a journal file (opened at `offset`: what follows is cut off)."""

    def __init__(
        self, path: Path, m, service: dict, offset: int | None = None, generation: int = 0
    ):
        self.path = Path(path)
        self.map = m
        self.records = 0
        self.bytes = 0
        # each new file's header numbers it one more than the last (a follower that sees a
        # number skipped missed a whole file between two polls: it reloads the autosave)
        self.generation = generation
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
        service's counters after it. Returns the bytes written; a ValueError (nothing written)
        when a column holds a value the reader would refuse."""
        cols = self.map.voxel_state(keys)
        for k, v in cols.items():  # what goes in must come back out: the reader's checks
            check_values(v, k)
        rec = frame(
            {
                "kind": "voxels",
                "keys": packed_array(np.asarray(keys, np.int32)),
                "cols": {k: packed_array(v) for k, v in cols.items()},
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
        if self._fd is not None:  # the first file of this writer keeps the number it was given
            self.generation += 1
        head = frame(_header(self.map, service, self.generation))
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
    """What a reader applied and what it skipped. Every byte of a journal ends in one of:
    a record applied (`records`), a record whose checksum holds but whose content was refused
    (`bad_records`: shapes, keys, columns, values, counters), bytes skipped up to the next good
    record (`damaged_bytes`: a bit flip, a record cut short mid-file) or the bytes after the last
    whole record at take-over (`torn_bytes`: the record the dead writer was writing)."""

    records: int = 0
    voxels: int = 0
    torn_bytes: int = 0
    damaged_bytes: int = 0
    bad_records: int = 0
    header_missing: int = 0  # files read whose header was damaged (their records still checked)
    skipped: str = ""  # why a journal was ignored (another map, not a regular file)
    first_problem: str = ""  # what the first refused record or damaged stretch was
    service: dict = field(default_factory=dict)
    files: int = 0

    @property
    def damaged(self) -> bool:
        """Something before the last good record was lost: the journal is no base to go on."""
        return bool(self.damaged_bytes or self.bad_records or self.header_missing)


class JournalReader:
    """Follows a journal into a map: `poll()` applies every whole record written since the last
    call, and moves on to the new file after a rotation (the old one is read to its end first:
    the writer finished it before the rename). Open it before loading the autosave: then a
    rotation in between leaves it on the old file, whose records the map file already holds or
    that come after it (replaying them is harmless).

    Nothing in a journal is trusted: a record is applied only when its checksum holds and its
    content fits the map (`check_record`: the keys, every column's dtype and shape, the values as
    the map loader checks them, plain counters). Damage costs the damaged record only: the
    reader looks for the next record's magic and goes on from there, counting what it skipped."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.books = ReplayBooks()
        self.map = None
        self._buf = b""
        self._fd = None
        self._ino = None
        self.offset = 0  # end of the last whole record in the current file
        self._header_ok: bool | None = None  # None: no header read (yet) in this file
        self.generation: int | None = None  # the current file's, from its header
        self._prev_generation: int | None = None
        # a rotation skipped between two polls (two autosaves, or an autosave and a clean stop,
        # within one): records of a whole file never applied; reopen and reload the autosave
        self.missed = False
        self._open()

    def _open(self) -> bool:
        try:
            st = os.stat(self.path)
        except OSError:
            return False
        if not stat.S_ISREG(st.st_mode):  # a FIFO would block the open, a device never end
            self.books.skipped = f"journal {self.path} is not a regular file"
            return False
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError:
            return False
        if self._fd is not None:
            os.close(self._fd)
        self._fd, self._ino = fd, os.fstat(fd).st_ino
        self._buf, self.offset, self._header_ok = b"", 0, None
        self._prev_generation, self.generation = self.generation, None
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
        if self._fd is None and (self.books.skipped or not self._open()):
            return 0
        n0 = self.books.records
        self._read()
        try:
            ino = os.stat(self.path).st_ino
        except FileNotFoundError:
            return self.books.records - n0
        if ino != self._ino:  # rotated: the old file is complete, the new one starts fresh
            self._read(final=True)
            if self._open():
                self._read()
        return self.books.records - n0

    def finish(self) -> int:
        """At take-over (the writer is gone): the file is complete. What follows the last whole
        record is a record cut short (`torn_bytes`); damage before it was skipped. Returns the
        offset to append at."""
        self.poll()
        if self._fd is not None:
            self._read(final=True, tail_is_torn=True)
        return self.offset

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _read(self, final: bool = False, tail_is_torn: bool = False) -> None:
        """Apply the whole records read so far. While the writer lives (`final` False) an
        incomplete last record is waited for; once the file is complete, what cannot be a
        record is skipped up to the next magic that starts a good one."""
        chunks = [self._buf]
        while chunk := os.read(self._fd, 1 << 20):
            chunks.append(chunk)
        buf = b"".join(chunks)
        view, at = memoryview(buf), 0  # records are read in place, the rest kept once
        while len(buf) - at >= (RECORD_FRAME.size if not final else 1):
            if len(buf) - at >= RECORD_FRAME.size:
                magic, length, crc = RECORD_FRAME.unpack_from(buf, at)
                end = at + RECORD_FRAME.size + length
                if magic == MAGIC and length <= MAX_RECORD_BYTES:
                    if end <= len(buf) and zlib.crc32(view[at + RECORD_FRAME.size : end]) == crc:
                        self._take(view[at + RECORD_FRAME.size : end])
                        self.offset += end - at
                        at = end
                        continue
                    if end > len(buf) and not final:
                        break  # still being written
            # damage at `at`: go on at the next magic (a flipped bit, a record cut short)
            nxt = buf.find(MAGIC, at + 1)
            if nxt < 0:
                if not final:
                    break  # the next record may not be written yet
                nxt = len(buf)
            if nxt == len(buf) and tail_is_torn:  # cut short by the kill: append before it
                self.books.torn_bytes += nxt - at
                at = nxt
                break
            self._problem(f"{nxt - at} damaged bytes at offset {self.offset}")
            self.books.damaged_bytes += nxt - at
            self.offset += nxt - at
            at = nxt
        view.release()
        self._buf = buf[at:]

    def _problem(self, what: str) -> None:
        if not self.books.first_problem:
            self.books.first_problem = what

    def _take(self, body) -> None:
        """One record whose checksum holds: applied when its content fits, else counted."""
        try:
            rec = msgpack.unpackb(body, raw=False, strict_map_key=True)
            if not isinstance(rec, dict):
                raise ValueError("not a map")
            if rec.get("kind") == "header":
                self._on_header(rec)
                return
            if self._header_ok is False:
                return  # a journal of another map: skipped whole (books.skipped says why)
            keys, cols, service = check_record(rec, self.map)
        except Exception as exc:  # noqa: BLE001 - any content error costs this record only
            self.books.bad_records += 1
            self._problem(f"record refused: {' '.join(str(exc).split())[:200]}")
            return
        if self._header_ok is None:  # its header was lost: the records are checked still
            self._header_ok = True
            self.books.header_missing += 1
            self._problem("journal header damaged")
        self.map.set_voxel_state(keys, cols)
        self.books.records += 1
        self.books.voxels += int(keys.shape[0])
        self.books.service = service

    def _on_header(self, rec: dict) -> None:
        m = self.map
        backend, res, fields = rec.get("backend"), rec.get("resolution_m"), rec.get("fields")
        fits = backend == m.backend and res == m.resolution_m and fields == sorted(m.column_names())
        self._header_ok = fits
        if not fits:
            self.books.skipped = (
                f"journal {self.path} is for {str(backend)[:40]} at {str(res)[:20]} m, the map "
                f"is {m.backend} at {m.resolution_m} m"
            )
            return
        gen = rec.get("generation")
        if type(gen) is int:
            self.generation = gen
            prev = self._prev_generation
            if prev is not None and gen != prev + 1:
                self.missed = True
        service = rec.get("service")
        if service:
            self.books.service = check_counters(service)


MAX_COUNTER = 2**63 - 1


def check_counters(c) -> dict:
    """A record's service counters: a map of names to integers (int64), finite numbers or
    maps of names to integers, nothing else (the service reads its figures from them)."""
    if not isinstance(c, dict) or len(c) > 64:
        raise ValueError("counters: not a map of at most 64 names")
    for k, v in c.items():
        if not isinstance(k, str):
            raise ValueError("counters: a name that is not text")
        vals = v.values() if isinstance(v, dict) else [v]
        if isinstance(v, dict) and (len(v) > 64 or not all(isinstance(n, str) for n in v)):
            raise ValueError(f"counters: {k[:40]}: not a map of at most 64 names")
        for x in vals:
            if isinstance(x, bool) or not isinstance(x, int | float):
                raise ValueError(f"counters: {k[:40]}: not a number")
            if isinstance(x, int) and abs(x) > MAX_COUNTER:
                raise ValueError(f"counters: {k[:40]}: beyond int64")
            if isinstance(x, float) and not math.isfinite(x):
                raise ValueError(f"counters: {k[:40]}: not finite")
    return c


def _unarray(d, dtype: np.dtype, shape: tuple) -> np.ndarray:
    """An array of a record, only as `dtype` and `shape` (-1: any length); nothing else."""
    if not isinstance(d, dict) or set(d) != {"dtype", "shape", "data"}:
        raise ValueError("an array without exactly dtype, shape and data")
    if d["dtype"] != dtype.str:
        raise ValueError(f"dtype {str(d['dtype'])[:20]}, expected {dtype.str}")
    got = d["shape"]
    if (
        not isinstance(got, list)
        or len(got) != len(shape)
        or not all(type(n) is int and n >= 0 for n in got)
        or any(w != -1 and n != w for n, w in zip(got, shape, strict=True))
    ):
        raise ValueError(f"shape {str(got)[:40]}, expected {shape}")
    data = d["data"]
    if not isinstance(data, bytes) or len(data) != math.prod(got) * dtype.itemsize:
        raise ValueError("data of the wrong size")
    return np.frombuffer(data, dtype).reshape(got)


def check_record(rec: dict, m) -> tuple[np.ndarray, dict, dict]:
    """A voxel record's keys, columns and counters, checked against map `m` the way the map
    loader checks a file (mapfile.py): exactly the back-end's columns, each of its dtype and of
    one row per key, values finite and in range, keys in the map's key range. A ValueError (one
    line) otherwise; nothing is applied."""
    if rec.get("kind") != "voxels" or set(rec) != {"kind", "keys", "cols", "service"}:
        raise ValueError("not a voxel record")
    keys = _unarray(rec["keys"], np.dtype(np.int32), (-1, 3))
    if keys.size and (keys.min() < -KEY_LIMIT or keys.max() >= KEY_LIMIT):
        raise ValueError(f"keys outside [-{KEY_LIMIT}, {KEY_LIMIT})")
    grid = m._core.grid
    raw = rec["cols"]
    if not isinstance(raw, dict) or set(raw) != set(grid.cols):
        raise ValueError(f"columns do not fit back-end {m.backend}")
    cols = {}
    for k, col in grid.cols.items():
        cols[k] = _unarray(raw[k], col.dtype, (keys.shape[0], *col.shape[1:]))
        check_values(cols[k], k)
    return keys, cols, check_counters(rec["service"])


def has_records(path: Path) -> bool:
    """Whether a journal holds more than its first record (the header): what a map that does not
    replay it would lose."""
    try:
        with open(path, "rb", opener=lambda p, f: os.open(p, f | os.O_NONBLOCK)) as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                return False
            head, size = fh.read(RECORD_FRAME.size), os.fstat(fh.fileno()).st_size
    except OSError:
        return False
    if len(head) < RECORD_FRAME.size:
        return False
    return size > RECORD_FRAME.size + RECORD_FRAME.unpack(head)[1]
