"""What the mapper answers: its figures (`mapper/stats`, the status details) and the queries
`mapper/snapshot`, `mapper/save` and `mapper/point` (the service module's docstring says what
each takes). Part of `service.MapperService`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smana.common import keys
from smana.common.messages import MapDelta
from smana.common.service import ReplyError, Request

MAX_QUERY_POINTS = 100_000
MAX_NAME_BYTES = 255  # NAME_MAX of Linux file systems


class MapperQueries:
    """The part of `MapperService` that answers queries. It uses the state the service sets
    (`map`, `save_path`, `journal`, the counters, `members`, `member_books`, ...)."""

    def stats(self) -> dict:
        t = np.array(self.times_ms) if self.times_ms else np.zeros(1)
        return {
            **self.map.stats(),
            "clouds": self.clouds,
            "last_cloud_seq": self.last_cloud_seq,
            "points_dropped_nonfinite": self.points_dropped,
            "labels_replaced": self.labels_replaced,
            "integrate_ms_median": float(np.median(t)),
            "integrate_ms_last": float(t[-1]),
            "save_path": str(self.save_path) if self.save_path else "",
            "last_save_s": self.last_save_s,
            "journal": (
                {"records": self.journal.records, "bytes": self.journal.bytes}
                if self.journal is not None
                else {}
            ),
            "takeover": self.takeover,
            **({"members": self._member_stats()} if self.fleet else {}),
        }

    def _member_stats(self) -> dict:
        layers = self.map.member_stats()
        return {m: {**layers[m], **self.member_books[m]} for m in self.members}

    def status_details(self) -> dict:
        s = self.stats()
        keep = (
            "backend",
            "voxels_observed",
            "voxels_occupied",
            "bytes_used",
            "clouds",
            "points_dropped_nonfinite",
            "labels_replaced",
            "integrate_ms_median",
        )
        out = {k: s[k] for k in keep}
        if self.fleet:  # plain values only: totals over the members
            out["member_deltas"] = sum(m["deltas_applied"] for m in s["members"].values())
            out["member_resyncs"] = sum(m["resyncs"] for m in s["members"].values())
        return out

    def on_snapshot(self, req: Request) -> MapDelta:
        body = req.body()
        box = body.get("box", req.params.get("box"))
        if box is not None:
            try:
                if isinstance(box, str):
                    box = [float(v) for v in box.split(",")]
                b = np.asarray(box, np.float64).reshape(2, 3)
            except (ValueError, TypeError):
                raise ReplyError(
                    "value", "box must be 6 numbers: xmin,ymin,zmin,xmax,ymax,zmax"
                ) from None
            box = (b[0], b[1])
        observed = body.get("observed", req.params.get("observed", False))
        if isinstance(observed, str):
            observed = observed.lower() in ("1", "true", "yes")
        try:
            rows = self.map.observed_voxels(box) if observed else self.map.occupied_voxels(box)
        except ValueError as exc:
            raise ReplyError("value", str(exc)) from None
        # Before the first cloud there is no cloud number (-1 in the stats); the message carries
        # numbers >= 0, and an empty snapshot of a fresh map is still a valid snapshot.
        cloud_seq = max(self.last_cloud_seq, 0)
        return self._message(rows, self.last_stamp_s, cloud_seq, self.delta_seq)

    def on_save(self, req: Request) -> dict:
        # It writes a file: only its exact key, never a wildcard that happened to match it
        if req.key != keys.query(self.robot, "mapper", "save"):
            raise ReplyError("selector", f"save: {req.key} is not the save key itself")
        if self.save_path is None:
            raise ReplyError("value", "no mapper.save_path and no run dir: nowhere to save")
        name = req.body().get("name")
        path = self.save_path
        if name:
            # only a plain .npz file name beside the configured path: a query never picks a
            # directory, nor another file of the run directory (config.toml, a report); and one
            # the file system takes, with its ".tmp" twin (no NUL, at most NAME_MAX bytes)
            plain = isinstance(name, str) and Path(name).name == name and not name.startswith(".")
            if not (
                plain
                and name.endswith(".npz")
                and name.isprintable()
                and len(f"{name}.tmp".encode()) <= MAX_NAME_BYTES
            ):
                raise ReplyError("value", f"name must be a plain file name.npz, got {name!r}")
            path = self.save_path.parent / name
        self._check_save_quota(path)
        try:
            return self.save(path)
        except OSError as exc:  # disk full, permissions: the query fails, the mapper goes on
            raise ReplyError("io", f"could not save to {path}: {exc.strerror or exc}") from None

    def _check_save_quota(self, path: Path) -> None:
        """Refuse a queried save that would leave more than `save_max_files` .npz files, or more
        than `save_max_mb` of them (counting the new one as large as the last save), beside
        `save_path`: whoever may ask cannot fill the disk."""
        mc = self.config.mapper
        others = [p for p in path.parent.glob("*.npz") if p.name != path.name and p.is_file()]
        used = sum(p.stat().st_size for p in others)
        size = path.stat().st_size if path.is_file() else self._last_save_bytes
        if len(others) + 1 > mc.save_max_files or (used + size) / 1e6 > mc.save_max_mb:
            raise ReplyError(
                "quota",
                f"save: {len(others)} map files, {used / 1e6:.0f} MB in {path.parent} "
                f"(mapper.save_max_files {mc.save_max_files}, save_max_mb {mc.save_max_mb:g})",
            )

    def on_point(self, req: Request) -> dict:
        pts = req.body().get("points")
        try:
            arr = np.asarray(pts, np.float64)
        except (ValueError, TypeError):
            raise ReplyError("value", "points must be a list of [x, y, z]") from None
        if arr.ndim == 1 and arr.shape == (3,):
            arr = arr[None]
        if arr.ndim != 2 or arr.shape[1] != 3 or not np.isfinite(arr).all():
            raise ReplyError("value", "points must be a list of finite [x, y, z]")
        if arr.shape[0] > MAX_QUERY_POINTS:
            raise ReplyError("value", f"at most {MAX_QUERY_POINTS} points per query")
        q = self.map.query(arr)
        return {
            "known": q.known.tolist(),
            "occupied": q.occupied.tolist(),
            "labels": q.labels.tolist(),
            "confidences": q.confidences.tolist(),
            "values": [None if np.isnan(v) else float(v) for v in q.values],
        }
