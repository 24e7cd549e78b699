"""The run's map across restarts: built from `mapper.load` or new (`build_map`), its autosave
and the journal written between two autosaves, followed by a hot spare while it stands by and
replayed at a take-over after `kill -9` (the service module's docstring says what survives), and
the files it will not use kept aside, never overwritten. Part of `service.MapperService`."""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path

from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.services.mapper.fleet import FleetMap
from smana.services.mapper.journal import JournalReader, JournalWriter, has_records
from smana.services.mapper.semantic_map import SemanticMap


def resolve_save_path(config: SmanaConfig) -> Path | None:
    mc = config.mapper
    if mc.save_path:
        return Path(mc.save_path)
    if config.general.run_dir:
        return Path(config.general.run_dir) / "map.npz"
    return None


def _same_file(a, b: Path) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def _exists(path: Path) -> bool:
    return os.path.lexists(path)


def _not_regular(path: Path) -> bool:
    try:
        return not stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def build_map(config: SmanaConfig, table: ClassTable, log=None) -> SemanticMap | FleetMap:
    """The map the config asks for: loaded from `mapper.load`, or new (a `FleetMap` for
    `mapper.source = "fleet"`)."""
    mc = config.mapper
    load = mc.load
    if load == "auto":
        save = resolve_save_path(config)
        load = str(save) if save is not None and save.is_file() else ""
    if mc.source == "fleet":
        fleet = config.fleet
        if not load:
            return FleetMap(mc, fleet.robots, fleet, table)
        try:
            fm = FleetMap.load(load, mc, fleet.robots, fleet, table)
        except ValueError as exc:
            if mc.load != "auto":
                raise
            # the members' own maps hold everything: they fill an empty fleet map in at start
            if log:
                log.warning("%s; starting empty, the members' snapshots fill it in", exc)
            return FleetMap(mc, fleet.robots, fleet, table)
        if log:
            log.info("resumed fleet map from %s (%d voxels)", load, fm.stats()["voxels_observed"])
        return fm
    if load:
        m = SemanticMap.load(load, table, backend=mc.backend)
        if log and (m.backend, m.resolution_m) != (mc.backend, mc.resolution_m):
            log.warning(
                "map file %s is %s at %g m; config asked for %s at %g m: using the file",
                load,
                m.backend,
                m.resolution_m,
                mc.backend,
                mc.resolution_m,
            )
        if log:
            log.info("resumed map from %s (%d voxels)", load, m.stats()["voxels_observed"])
        return m
    return SemanticMap.from_config(mc, table)


class MapperTakeover:
    """The part of `MapperService` that loads, journals and takes over the run's map. It uses the
    state the service sets (`config`, `table`, `map`, `save_path`, `journal_path`, `journal`,
    the counters, `note`, `log`, ...)."""

    def standing_by(self) -> None:
        # A hot spare keeps its copy of the map current from the journal, so that a take-over
        # reads only the records written since the last poll.
        if not self._replays():
            return
        if self._reader is None:
            self._reader = self._open_journal(take_over=False)
            self.log.info("standing by: following %s", self.journal_path)
        else:
            self._reader.poll()
            if self._reader.missed:  # a whole journal went by between two polls: start over
                self._reader.close()
                self._reader = self._open_journal(take_over=False)
                self.log.info("standing by: a journal went by unread; reloaded the autosave")

    def _replays(self) -> bool:
        """Whether this start resumes the run's own map, its autosave and its journal:
        `mapper.load = "auto"`, or a `--load` of the autosave itself."""
        if self.journal_path is None:
            return False
        load = self.config.mapper.load
        return load == "auto" or (bool(load) and _same_file(load, self.save_path))

    def _open_journal(self, take_over: bool) -> JournalReader:
        # the journal first, then the autosave: a rotation in between leaves the reader on the
        # old journal, whose records the new autosave holds (replaying them changes nothing)
        reader = JournalReader(self.journal_path)
        reader.attach(self._load_autosave(take_over))
        return reader

    def _load_autosave(self, take_over: bool) -> SemanticMap:
        """The run's autosave (or a new map when there is none). A damaged one costs the file,
        not the service: one warning, the file kept aside (at a take-over), and the map starts
        from the journal alone (the last good state there is)."""
        try:
            return build_map(self.config, self.table, self.log)
        except (ValueError, OSError) as exc:
            why = " ".join(str(exc).split())
            kept = self._set_aside(self.save_path) if take_over else None
            self.note(
                "autosave_damaged",
                f"autosave cannot be used ({why}); "
                + (f"kept as {kept.name}; " if kept else "")
                + "the map starts from the journal alone",
            )
            return SemanticMap.from_config(self.config.mapper, self.table)

    def _set_aside(self, path: Path) -> Path | None:
        """Rename a file the mapper will not use (a damaged autosave, a journal of another
        map) beside itself, never over another: it is kept, not deleted."""
        for n in range(1, 1000):
            aside = path.with_name(f"{path.name}.unused-{n}")
            if not aside.exists():
                try:
                    os.rename(path, aside)
                except OSError as exc:
                    self.log.warning("could not keep %s aside: %s", path, exc)
                    return None
                return aside
        return None

    def warm_up(self) -> None:
        # The run's map: resumed from its autosave and its journal after a crash (`mapper.load`).
        self.startup_step = "loading the map"
        if not self._replays():
            self.map = build_map(self.config, self.table, self.log)
            # a journal this map does not continue (a fresh map, another file) holds voxels the
            # autosave may lack: kept aside, never overwritten
            if self.journal_path is not None and (
                has_records(self.journal_path) or _not_regular(self.journal_path)
            ):
                kept = self._set_aside(self.journal_path)
                self.note(
                    "journal_kept_aside",
                    f"journal {self.journal_path} is not this map's"
                    + (f": kept as {kept.name}" if kept else ""),
                )
            self._start_journal(None)
            return
        t0 = time.perf_counter()
        followed = self._reader is not None
        reader, self._reader = self._reader or self._open_journal(take_over=True), None
        self.startup_step = "replaying the map's journal"
        offset = reader.finish()
        if reader.missed:  # the spare slept through a whole journal: the autosave holds it
            reader.close()
            reader = self._open_journal(take_over=True)
            offset = reader.finish()
        exists = reader.exists  # (before close(), which forgets the file)
        self._generation = reader.generation
        reader.close()
        self.map = reader.map
        self.map.recount()
        b = reader.books
        self._restore(b.service)
        self.takeover = {
            "records_replayed": b.records,
            "voxels_replayed": b.voxels,
            "torn_bytes": b.torn_bytes,
            "damaged_bytes": b.damaged_bytes,
            "bad_records": b.bad_records,
            "journal_files": b.files,  # 2 and more: it followed the journal through autosaves
            "followed_in_standby": followed,
            "replay_ms": (time.perf_counter() - t0) * 1e3,
        }
        if b.records or b.torn_bytes:
            self.log.info(
                "replayed %d journal records (%d voxel states) over the autosave in %.0f ms%s; "
                "the map has %d occupied voxels",
                b.records,
                b.voxels,
                self.takeover["replay_ms"],
                f", {b.torn_bytes} bytes of a record cut short dropped" if b.torn_bytes else "",
                self.map.stats()["voxels_occupied"],
            )
        if b.records:
            self.dirty = True  # what was replayed is not in the autosave: the next save holds it
        if b.torn_bytes:
            self.note("journal_torn", f"{b.torn_bytes} bytes of a journal record cut short")
        if b.skipped:  # another map's journal, or not a file: kept aside, a new one started
            kept = self._set_aside(self.journal_path) if _exists(self.journal_path) else None
            self.note(
                "journal_kept_aside",
                f"{b.skipped}: not replayed" + (f", kept as {kept.name}" if kept else ""),
            )
            self._start_journal(None)
        elif b.damaged:
            # what was replayed is saved before the damaged journal gives way to a new one
            self.note(
                "journal_damaged",
                f"journal {self.journal_path}: {b.bad_records} records refused, "
                f"{b.damaged_bytes} damaged bytes skipped ({b.first_problem}); "
                f"{b.records} records replayed",
            )
            if self._save_quietly():
                self._start_journal(None)
            else:
                self._start_journal(offset)
        else:  # go on after the last whole record: the journal keeps what was replayed
            self._start_journal(offset if exists and offset > 0 else None)

    def _save_quietly(self) -> bool:
        if self.save_path is None:
            return False
        try:
            self.save(self.save_path)
        except OSError as exc:
            self.note("save_failed", f"saving {self.save_path}: {exc}")
            return False
        return True

    def _start_journal(self, offset: int | None) -> None:
        if self.journal_path is None:
            return
        # go on with the file's number, or number a new file one more than the one replayed
        gen = self._generation
        gen = (gen or 0) if offset is not None else (0 if gen is None else gen + 1)
        try:
            self.journal = JournalWriter(
                self.journal_path, self.map, self._counters(), offset, generation=gen
            )
        except OSError as exc:  # the map goes on; only a take-over would lose more
            self.note("journal_failed", f"journal {self.journal_path}: {exc}; mapping without")

    def _counters(self) -> dict:
        """The service's figures a journal record carries beside the voxels."""
        return {
            "clouds": self.clouds,
            "last_cloud_seq": self.last_cloud_seq,
            "last_stamp_s": self.last_stamp_s,
            "delta_seq": self.delta_seq,
            "input_seq": dict(self.input_seq),
            "points_dropped": self.points_dropped,
            "labels_replaced": self.labels_replaced,
            "integrations": self.map.n_integrations,
            "points": self.map.n_points,
        }

    def _restore(self, c: dict) -> None:
        if not c:
            return
        try:  # the reader checked they are numbers (journal.check_counters); now, which
            restored = {
                "clouds": int(c["clouds"]),
                "last_cloud_seq": int(c["last_cloud_seq"]),
                "last_stamp_s": float(c["last_stamp_s"]),
                "delta_seq": int(c["delta_seq"]),
                "input_seq": {str(k): int(v) for k, v in c["input_seq"].items()},
                "points_dropped": int(c["points_dropped"]),
                "labels_replaced": int(c["labels_replaced"]),
                "integrations": int(c["integrations"]),
                "points": int(c["points"]),
            }
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            self.note("journal_counters", f"journal counters unusable ({exc!r}); from zero")
            return
        for k in ("clouds", "last_cloud_seq", "last_stamp_s", "delta_seq", "input_seq"):
            setattr(self, k, restored[k])
        self.points_dropped = restored["points_dropped"]
        self.labels_replaced = restored["labels_replaced"]
        self.map.n_integrations = restored["integrations"]
        self.map.n_points = restored["points"]
