"""The Rerun recorder: a Zenoh subscriber that logs what flows through a run into a `.rrd` file.

    python -m smana.deploy.recording --config run/config.toml --run-dir run   # (smana up runs it)
    smana view --spawn                                                         # live, in a viewer

Over the `sim_time` timeline (the stamps the messages carry) it logs:
- `world/robot` (Transform3D from `robot/pose`) and `world/trajectory` (and `world/trajectory_truth`
  from `robot/pose_truth` when the simulator publishes it);
- `camera/rgb` and `camera/semantic` (downscaled images; the class colours come from an
  AnnotationContext built from the class table, so the viewer names each class);
- `world/map/<block>`: the semantic voxel map rebuilt from `mapper/delta`, in 2 m blocks so that
  only blocks that changed are logged again;
- `world/graph/{nodes,obstacles,safety_zone}` from `navgraph/patch`;
- `world/explorer/{frontier,path,goal}` and `metrics/*` from `explorer/state`.

Into the run directory it writes every pose as it comes (`trajectory_pose.csv`,
`trajectory_truth.csv`: what the report measures a simulated run on) and, when it stops,
`recorder.json`: what it recorded and the books of what it received.

A fleet (`fleet.robots` set, the recorder started as `--robot <fleet.name>`) is one recording:
each member's pose, trajectories, explorer frontier, path and goal under `world/robots/<member>/`
in the member's own colour (`metrics/<member>/*`), the fleet's merged map (`smana/<fleet>/mapper/
delta`) and shared graph (`smana/<fleet>/navgraph/patch`) once, each member's trajectory files in
`robots/<member>/`, and `recorder.json` counting per member (`members`).

`RunRecorder` is the part without Zenoh (fed decoded messages, used in tests); `rerun` is imported
lazily and a missing SDK gives a one-line hint and a recorder that does nothing.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path

import msgpack
import numpy as np

from smana.common import keys
from smana.common.classes import MEMBER_COLOURS, ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import GraphPatch, MapDelta, Pose
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.common.service import Service

log = logging.getLogger("smana.recorder")

RRD_NAME = "recording.rrd"
SUMMARY_NAME = "recorder.json"
APP_ID = "smana"
TRAJECTORY_FILES = {"pose": "trajectory_pose.csv", "pose_truth": "trajectory_truth.csv"}
TRAJECTORY_HEADER = "t_s,x_m,y_m,z_m,yaw_rad"
FLEET_DIR = "robots"  # a fleet member's trajectories: RUN_DIR/robots/<member>/


def import_rerun():
    """The rerun module, or None with a one-line hint."""
    try:
        import rerun as rr
    except ImportError:
        print(
            "smana: rerun-sdk is not installed (pip install rerun-sdk): no recording",
            file=sys.stderr,
        )
        return None
    return rr


# -- the map, rebuilt from deltas --------------------------------------------------------------


class VoxelStore:
    """The occupied voxels of the map, kept from MapDelta messages (a voxel at most once).

    `apply` only queues a delta (cost proportional to the delta): merging into the store, newest
    state per voxel, waits for the next read (`blocks`, `keys`, ...). Merging on every delta cost
    the whole store each time: the recorder fell behind the mapper, poses queued behind deltas."""

    MERGE_ROWS = 2_000_000  # queued rows past which a delta merges at once (bounds the memory)

    def __init__(self, block_m: float = 2.0):
        self.block_m = block_m
        self._keys = np.zeros(0, np.int64)
        self._centres = np.zeros((0, 3), np.float32)
        self._labels = np.zeros(0, np.uint16)
        self._queued: list[tuple[np.ndarray, ...]] = []  # (keys, centres, labels, occupied)
        self._queued_rows = 0
        self.dirty_blocks: set[tuple[int, int]] = set()
        self.resolution_m = 0.0

    @staticmethod
    def _keys_of(centres: np.ndarray, res: float) -> np.ndarray:
        q = np.floor(centres / res).astype(np.int64) + (1 << 20)
        return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]

    def _blocks(self, centres: np.ndarray) -> np.ndarray:
        return np.floor(centres[:, :2] / self.block_m).astype(np.int64)

    @staticmethod
    def _block_codes(blocks: np.ndarray) -> np.ndarray:
        """One int64 per block (x in the high half, y in the low half): sortable, and fast to
        make unique where a row-wise unique of (x, y) pairs is not."""
        return (blocks[:, 0] << 32) + blocks[:, 1]

    def apply(self, delta: MapDelta) -> None:
        if delta.resolution_m != self.resolution_m and (len(self._keys) or self._queued):
            self.__init__(self.block_m)  # the map was restarted at another resolution
        self.resolution_m = delta.resolution_m
        c = np.asarray(delta.centres, np.float32)
        if len(c) == 0:
            return
        labels = np.asarray(delta.labels, np.uint16)
        occupied = np.asarray(delta.occupied).astype(bool)
        self._queued.append((self._keys_of(c, delta.resolution_m), c, labels, occupied))
        self._queued_rows += len(c)
        b = self._blocks(c)
        _, first = np.unique(self._block_codes(b), return_index=True)
        self.dirty_blocks.update(map(tuple, b[first].tolist()))
        if self._queued_rows > self.MERGE_ROWS:
            self._merge()

    def _merge(self) -> None:
        if not self._queued:
            return
        # newest wins: stack the store then the deltas in order, keep each key's last row
        q = self._queued
        all_k = np.concatenate([self._keys, *(d[0] for d in q)])
        all_c = np.concatenate([self._centres, *(d[1] for d in q)])
        all_l = np.concatenate([self._labels, *(d[2] for d in q)])
        all_o = np.concatenate([np.ones(len(self._keys), bool), *(d[3] for d in q)])
        self._queued, self._queued_rows = [], 0
        rev = np.arange(len(all_k))[::-1]
        _, first = np.unique(all_k[rev], return_index=True)
        keep = rev[first]
        keep = keep[all_o[keep]]
        self._keys, self._centres, self._labels = all_k[keep], all_c[keep], all_l[keep]

    @property
    def keys(self) -> np.ndarray:
        self._merge()
        return self._keys

    @property
    def centres(self) -> np.ndarray:
        self._merge()
        return self._centres

    @property
    def labels(self) -> np.ndarray:
        self._merge()
        return self._labels

    def blocks(self, wanted) -> list[tuple[tuple[int, int], np.ndarray, np.ndarray]]:
        """(block, centres, labels) of each block in `wanted`: one sort of the store for all of
        them (a mask per block cost the whole store per block)."""
        self._merge()
        code = self._block_codes(self._blocks(self._centres))
        order = np.argsort(code, kind="stable")
        code = code[order]
        out = []
        for b in sorted(wanted):
            k = (int(b[0]) << 32) + int(b[1])
            lo, hi = np.searchsorted(code, k, "left"), np.searchsorted(code, k, "right")
            sel = order[lo:hi]
            out.append((b, self._centres[sel], self._labels[sel]))
        return out

    def block(self, b: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        _, c, lab = self.blocks([b])[0]
        return c, lab


# -- the recorder core ---------------------------------------------------------------------------


class TrajectoryCsv:
    """A trajectory file (TRAJECTORY_HEADER columns) written row by row as poses come, flushed
    each time, so that a recorder killed while stopping keeps every pose it had handled. Each
    recorder process starts the file anew, as it does its .rrd."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._file = None

    def write(self, row: tuple[float, ...]) -> None:
        if self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "w")  # noqa: SIM115 - kept open across rows
            self._file.write(TRAJECTORY_HEADER + "\n")
        self._file.write(",".join(f"{v:.4f}" for v in row) + "\n")
        self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def decode_image(payload: bytes) -> tuple[float, np.ndarray]:
    """(stamp, image array) from a raw image map: {"stamp_s", "data", "shape", "dtype"} or
    {"stamp_s", "width", "height", "channels"|"encoding", "data"}."""
    m = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    if not isinstance(m, dict) or "data" not in m:
        raise ValueError("image payload is not a map with data")
    data = m["data"]
    if isinstance(data, dict):  # an array in the message codec's wire form
        m = {**m, **{k: data[k] for k in ("shape", "dtype") if k in data}}
        data = data["data"]
    if "shape" in m:
        shape = tuple(int(s) for s in m["shape"])
        dtype = np.dtype(m.get("dtype", "u1"))
    else:
        h, w = int(m["height"]), int(m["width"])
        enc = str(m.get("encoding", ""))
        ch = int(m.get("channels", 3 if enc.startswith(("rgb", "bgr")) else 1))
        # ROS-style encodings: rgb8, mono8, 16UC1, 32FC1
        if "32F" in enc:
            dtype = np.dtype("<f4")
        elif "16" in enc:
            dtype = np.dtype("<u2")
        else:
            dtype = np.dtype(m.get("dtype", "u1"))
        shape = (h, w, ch) if ch > 1 else (h, w)
    img = np.frombuffer(data, dtype)
    if img.size != int(np.prod(shape)):
        raise ValueError(f"image data holds {img.size} values, shape {shape} needs more")
    return float(m.get("stamp_s", m.get("stamp", 0.0))), img.reshape(shape)


class Track:
    """One robot's poses in the recording: where its entities live (`prefix`), its colour, its
    trajectories (in memory, and in files when a folder is given)."""

    def __init__(self, prefix: str, colour, folder: Path | None):
        self.prefix = prefix
        self.colour = list(colour)
        self.rows: dict[str, list[tuple[float, ...]]] = {"pose": [], "pose_truth": []}
        self.files = (
            {}
            if folder is None
            else {k: TrajectoryCsv(Path(folder) / n) for k, n in TRAJECTORY_FILES.items()}
        )
        self.counts: dict[str, int] = {}


class RunRecorder:
    """Logs decoded smana messages into a Rerun recording stream (file and/or live viewer).

    A single robot's entities are `world/robot`, `world/trajectory`, `world/explorer/...`; with
    `members` (a fleet) each member's are under `world/robots/<member>/` in its own colour (its
    poses and explorer state are passed with `robot=`), its trajectory files under
    `trajectory_dir/robots/<member>/`, and the map and graph are the fleet's, once."""

    def __init__(
        self,
        classes: ClassTable,
        rrd_path: Path | None = None,
        spawn: bool = False,
        connect: str | None = None,
        graph_resolution_m: float = 0.2,
        graph_bounds=((-50.0, -50.0), (50.0, 50.0)),
        image_scale: float = 0.25,
        image_period_s: float = 1.0,
        map_period_s: float = 2.0,
        graph_period_s: float = 2.0,
        trajectory_period_s: float = 1.0,
        trajectory_dir: Path | None = None,
        members: list[str] | tuple[str, ...] = (),
    ):
        self.rr = rr = import_rerun()
        self.classes = classes
        self.image_scale = image_scale
        self.periods = {
            "image": image_period_s,
            "map": map_period_s,
            "graph": graph_period_s,
            "trajectory": trajectory_period_s,
        }
        self._last: dict[str, float] = {}
        self.voxels = VoxelStore()
        self.grid = NavGrid.from_bounds(*graph_bounds, graph_resolution_m)
        self._graph_version = -1
        # (t, x, y, z, yaw) of every pose, as published and true, per robot (None: the single
        # robot); with `trajectory_dir`, also written to TRAJECTORY_FILES there as they come
        self.members = list(members)
        folder = None if trajectory_dir is None else Path(trajectory_dir)
        self.tracks: dict[str | None, Track] = {None: Track("world", [255, 200, 0], folder)}
        for k, r in enumerate(self.members):
            self.tracks[r] = Track(
                f"world/{FLEET_DIR}/{r}",
                MEMBER_COLOURS[k % len(MEMBER_COLOURS)],
                None if folder is None else folder / FLEET_DIR / r,
            )
        self.counts: dict[str, int] = {}
        self.t = 0.0
        self.rec = None
        if rr is None:
            return
        self.rec = rr.RecordingStream(APP_ID)
        sinks = []
        if rrd_path is not None:
            Path(rrd_path).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(rrd_path)))
        if spawn:
            # start a viewer (it listens on the default gRPC port) and stream to it
            rr.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        if connect:
            sinks.append(rr.GrpcSink(connect))
        if sinks:
            self.rec.set_sinks(*sinks)
        self._static()

    def _static(self) -> None:
        rr = self.rr
        infos = [
            rr.AnnotationInfo(id=c.id, label=c.name, color=tuple(int(v) for v in c.colour))
            for c in self.classes.classes.values()
        ]
        ctx = rr.AnnotationContext(infos)
        self.rec.log("world", ctx, static=True)
        self.rec.log("camera", ctx, static=True)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for r, track in self.tracks.items():
            if r is None and self.members:
                continue  # a fleet's recording has its members' bodies only
            self.rec.log(
                f"{track.prefix}/robot/body",
                rr.Boxes3D(
                    half_sizes=[[0.28, 0.2, 0.1]],
                    colors=[[240, 190, 30] if r is None else track.colour],
                    labels=None if r is None else [r],
                ),
                static=True,
            )

    @property
    def trajectory(self) -> list[tuple[float, ...]]:
        """The single robot's published poses (a member's: `tracks[member].rows`)."""
        return self.tracks[None].rows["pose"]

    @property
    def trajectory_truth(self) -> list[tuple[float, ...]]:
        return self.tracks[None].rows["pose_truth"]

    # -- helpers --------------------------------------------------------------------------------

    def _time(self, stamp_s: float) -> None:
        if math.isfinite(stamp_s) and stamp_s > 0:
            self.t = stamp_s
        self.rec.set_time("sim_time", duration=self.t)

    def _due(self, what: str, t: float) -> bool:
        last = self._last.get(what)
        if last is None or t - last >= self.periods[what.split(":")[0]] or t < last:
            self._last[what] = t
            return True
        return False

    def _count(self, what: str) -> None:
        self.counts[what] = self.counts.get(what, 0) + 1

    # -- inputs ---------------------------------------------------------------------------------

    def on_pose(self, pose: Pose, truth: bool = False, robot: str | None = None) -> None:
        # The row first: the trajectory files are what the report measures, the viewer's
        # picture comes second.
        kind = "pose_truth" if truth else "pose"
        track = self.tracks[robot]
        p = np.asarray(pose.position, float)
        row = (float(pose.stamp_s), float(p[0]), float(p[1]), float(p[2]), float(pose.yaw))
        track.rows[kind].append(row)
        if kind in track.files:
            track.files[kind].write(row)
        self._count(kind)
        track.counts[kind] = track.counts.get(kind, 0) + 1
        if self.rec is None:
            return
        rr = self.rr
        self._time(pose.stamp_s)
        if not truth:
            q = np.asarray(pose.orientation_xyzw, float)
            self.rec.log(f"{track.prefix}/robot", rr.Transform3D(translation=p, quaternion=q))
        if self._due(f"trajectory:{robot}", time.monotonic()):
            self._log_trajectories(track)

    def _log_trajectories(self, track: Track) -> None:
        rr = self.rr
        for path, rows, colour, radius in (
            (f"{track.prefix}/trajectory", track.rows["pose"], track.colour, 0.03),
            (f"{track.prefix}/trajectory_truth", track.rows["pose_truth"], [255] * 3, 0.015),
        ):
            if len(rows) >= 2:
                xyz = np.array(rows)[:, 1:4]
                self.rec.log(path, rr.LineStrips3D([xyz], colors=[colour], radii=radius))

    def on_image(self, kind: str, payload: bytes) -> None:
        self._count(f"image/{kind}")
        if self.rec is None:
            return
        stamp, img = decode_image(payload)
        if not self._due("image:" + kind, stamp if stamp > 0 else time.monotonic()):
            return
        import cv2

        rr = self.rr
        self._time(stamp)
        s = self.image_scale
        if kind == "semantic":
            small = img[:: max(1, round(1 / s)), :: max(1, round(1 / s))]
            if small.ndim == 3:
                small = small[..., 0]
            self.rec.log("camera/semantic", rr.SegmentationImage(np.ascontiguousarray(small)))
        elif kind == "rgb":
            small = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self.rec.log("camera/rgb", rr.Image(small))
        elif kind == "depth":
            small = img[:: max(1, round(1 / s)), :: max(1, round(1 / s))]
            self.rec.log(
                "camera/depth",
                rr.DepthImage(
                    np.ascontiguousarray(small), meter=1.0 if small.dtype.kind == "f" else 1000.0
                ),
            )

    def on_delta(self, delta: MapDelta) -> None:
        self._count("delta")
        self.voxels.apply(delta)
        if self.rec is None:
            return
        self._time(delta.stamp_s)
        if self._due("map", self.t):
            self.flush_map()

    def flush_map(self) -> None:
        if self.rec is None:
            return
        rr = self.rr
        r = max(self.voxels.resolution_m / 2, 0.01)
        for b, c, lab in self.voxels.blocks(self.voxels.dirty_blocks):
            path = f"world/map/b{b[0]}_{b[1]}".replace("-", "m")
            if len(c):
                self.rec.log(path, rr.Points3D(c, class_ids=lab, radii=r))
            else:
                self.rec.log(path, rr.Clear(recursive=False))
        self.voxels.dirty_blocks.clear()

    def on_patch(self, patch: GraphPatch) -> None:
        self._count("patch")
        if self.grid.geometry_mismatch(patch.resolution_m, patch.origin_xy):
            # follow the graph the navgraph actually builds
            self.grid = NavGrid(patch.origin_xy, self.grid.shape, patch.resolution_m)
        self.grid.apply_patch(patch.cells, patch.labels, patch.heights, patch.flags)
        if self.rec is None:
            return
        self._time(patch.stamp_s)
        if self._due("graph", self.t):
            self.flush_graph()

    def flush_graph(self) -> None:
        if self.rec is None or self.grid.version == self._graph_version:
            return
        self._graph_version = self.grid.version
        rr = self.rr
        cells, labels, heights, flags = self.grid.export()
        xy = self.grid.cell_centre(cells[:, 0], cells[:, 1])
        z = np.where(np.isfinite(heights), heights, 0.0)
        pts = np.column_stack([xy, z + 0.02]).astype(np.float32)
        known = (flags & FLAG_KNOWN) != 0
        obst = known & ((flags & FLAG_OBSTACLE) != 0)
        safety = known & ~obst & ((flags & FLAG_SAFETY_ZONE) != 0)
        free = known & ~obst & ~safety
        r = self.grid.resolution_m * 0.35
        self.rec.log("world/graph/nodes", rr.Points3D(pts[free], class_ids=labels[free], radii=r))
        self.rec.log(
            "world/graph/obstacles", rr.Points3D(pts[obst], class_ids=labels[obst], radii=r * 1.3)
        )
        self.rec.log(
            "world/graph/safety_zone", rr.Points3D(pts[safety], colors=[255, 140, 0], radii=r)
        )

    def on_explorer_state(self, st: dict, robot: str | None = None) -> None:
        self._count("explorer_state")
        track = self.tracks[robot]
        track.counts["explorer_state"] = track.counts.get("explorer_state", 0) + 1
        if self.rec is None:
            return
        rr = self.rr
        ex = f"{track.prefix}/explorer"
        colour = [255, 0, 200] if robot is None else track.colour
        metrics = "metrics" if robot is None else f"metrics/{robot}"
        self._time(float(st.get("t_s") or 0.0))
        cand = np.asarray(st.get("candidates") or [], float).reshape(-1, 2)
        gains = np.asarray(st.get("candidate_gains_m2") or [], float)
        if len(cand) and len(gains) == len(cand):
            g = gains / max(gains.max(), 1e-6)
            colours = np.column_stack([255 * g, 80 + 100 * (1 - g), 255 * (1 - g)]).astype(np.uint8)
            pts = np.column_stack([cand, np.full(len(cand), 0.1)])
            self.rec.log(f"{ex}/frontier", rr.Points3D(pts, colors=colours, radii=0.06))
        else:
            self.rec.log(f"{ex}/frontier", rr.Clear(recursive=False))
        path = np.asarray(st.get("path") or [], float).reshape(-1, 2)
        if len(path) >= 2:
            p3 = np.column_stack([path, np.full(len(path), 0.12)])
            self.rec.log(f"{ex}/path", rr.LineStrips3D([p3], colors=[colour], radii=0.025))
        else:
            self.rec.log(f"{ex}/path", rr.Clear(recursive=False))
        goal = st.get("goal")
        if goal:
            gx, gy = goal["xy"]
            yaw = float(goal.get("yaw", 0.0))
            self.rec.log(
                f"{ex}/goal",
                rr.Arrows3D(
                    origins=[[gx, gy, 0.15]],
                    vectors=[[0.5 * math.cos(yaw), 0.5 * math.sin(yaw), 0]],
                    colors=[colour],
                ),
            )
        else:
            self.rec.log(f"{ex}/goal", rr.Clear(recursive=False))
        for name in ("explored_m2", "distance_m", "frontier_size"):
            if st.get(name) is not None:
                self.rec.log(f"{metrics}/{name}", rr.Scalars(float(st[name])))

    def save_trajectories(self, folder: Path) -> None:
        """trajectory_pose.csv / trajectory_truth.csv (t_s, x_m, y_m, z_m, yaw_rad) for the report:
        the true trajectory is what collisions and travelled labels are measured on; a fleet
        member's in `folder/robots/<member>/`. (A recorder given `trajectory_dir` has written them
        there already, row by row.)"""
        for r, track in self.tracks.items():
            out = Path(folder) if r is None else Path(folder) / FLEET_DIR / r
            for kind, rows in track.rows.items():
                if not rows:
                    continue
                out.mkdir(parents=True, exist_ok=True)
                np.savetxt(
                    out / TRAJECTORY_FILES[kind],
                    np.array(rows),
                    delimiter=",",
                    fmt="%.4f",
                    header=TRAJECTORY_HEADER,
                    comments="",
                )

    def close(self) -> None:
        for track in self.tracks.values():
            for f in track.files.values():
                f.close()
        if self.rec is None:
            return
        self.flush_map()
        self.flush_graph()
        for track in self.tracks.values():
            self._log_trajectories(track)
        self.rec.flush()
        self.rec.disconnect()
        self.rec = None


# -- the Zenoh service -------------------------------------------------------------------------


class RecorderService(Service):
    """Records everything it is sent until the stack stops: what is still queued when the stop
    comes is recorded too (`drain_on_stop`), and `smana up` stops it after every service it
    records (`Supervisor.shutdown`). Poses are recorded as they come, without the explorer's
    plausibility gates: the record is the evidence of what was on the wire (a spoofed or jumping
    pose included), and a gate tuned for a ground robot (`general.max_speed_mps`) would refuse a
    replayed car's poses. The figures that matter come from trusted sources instead: a replay's
    distance from the poses the replay itself published (`replay_trajectory.csv`), and a secured
    deployment lets only the sensor roles publish poses (`deploy/security.py`)."""

    name = "recorder"
    tick_period_s = 1.0
    drain_on_stop = True

    def __init__(self, config: SmanaConfig, rrd_path: Path | None, spawn=False, connect=None):
        super().__init__(config)
        nav = config.navgraph
        self.run_dir = Path(config.general.run_dir) if config.general.run_dir else None
        # started as the fleet (`--robot <fleet.name>`): one recording of every member
        fleet = config.fleet
        self.members = list(fleet.robots) if fleet.enabled and self.robot == fleet.name else []
        self.core = RunRecorder(
            ClassTable.load(config.general.class_table),
            rrd_path,
            spawn,
            connect,
            graph_resolution_m=nav.resolution_m,
            graph_bounds=(tuple(nav.bounds_min_xy), tuple(nav.bounds_max_xy)),
            trajectory_dir=self.run_dir,
            members=self.members,
        )
        self.rrd_path = rrd_path

    def setup(self) -> None:
        r = self.robot
        c = self.core
        if self.members:
            self._setup_fleet()
            return
        self.subscribe(keys.pose(r), c.on_pose, Pose)
        self.subscribe(keys.pose_truth(r), lambda p: c.on_pose(p, truth=True), Pose)
        self.subscribe(keys.map_delta(r), c.on_delta, MapDelta)
        self.subscribe(keys.graph_patch(r), c.on_patch, GraphPatch)
        self.subscribe(keys.explorer_state(r), self._on_state)
        for kind in ("rgb", "semantic"):
            self.subscribe_latest(keys.image(r, kind), lambda b, k=kind: c.on_image(k, b))

    def _setup_fleet(self) -> None:
        """Every member's poses and explorer state, the fleet's merged map and shared graph.
        (No camera images: N members' would outweigh the rest of the recording.)"""
        c = self.core
        for m in self.members:
            self.subscribe(keys.pose(m), lambda p, m=m: c.on_pose(p, robot=m), Pose)
            self.subscribe(keys.pose_truth(m), lambda p, m=m: c.on_pose(p, True, m), Pose)
            self.subscribe(keys.explorer_state(m), lambda b, m=m: self._on_state(b, m))
        self.subscribe(keys.map_delta(self.robot), c.on_delta, MapDelta)
        self.subscribe(keys.graph_patch(self.robot), c.on_patch, GraphPatch)

    def _on_state(self, payload: bytes, robot: str | None = None) -> None:
        st = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        if not isinstance(st, dict):
            raise ValueError("explorer state is not a map")
        self.core.on_explorer_state(st, robot)

    def tick(self) -> None:
        # a quiet stack still gets its map and graph logged
        if self.core.rec is not None and self.core.voxels.dirty_blocks:
            self.core.flush_map()

    def on_stop(self) -> None:
        # The trajectories are on disk already (row by row); the books are final (the queue was
        # drained before on_stop): say what was recorded before the slow part, closing the .rrd.
        summary = self.summary()
        self.log.info(
            "recorded %s; %d messages in: %d accepted, dropped %s, rejected %s",
            _recorded_line(summary["recorded"]),
            summary["msgs_in"],
            summary["accepted"],
            summary["dropped"] or 0,
            summary["rejected"] or 0,
        )
        if self.run_dir is not None:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            (self.run_dir / SUMMARY_NAME).write_text(json.dumps(summary, indent=1))
        self.core.close()

    def recorded(self) -> dict[str, int]:
        """How many of each stream the recording holds (poses, deltas, patches always named)."""
        return {"pose": 0, "pose_truth": 0, "delta": 0, "patch": 0, **self.core.counts}

    def summary(self) -> dict:
        """What `recorder.json` holds: what was recorded, and the books of what was received."""
        st = self.status()
        out = {
            "recorded": self.recorded(),
            "msgs_in": st.msgs_in,
            "accepted": st.accepted,
            "dropped": st.dropped,
            "rejected": st.rejected,
            "pending": st.pending,
            "rrd": str(self.rrd_path or ""),
            "trajectories": {k: v for k, v in TRAJECTORY_FILES.items() if self.core.counts.get(k)},
        }
        if self.members:
            # per member: what was recorded of it, and where its trajectories are
            tracks = self.core.tracks
            out["members"] = {
                m: {"pose": 0, "pose_truth": 0, "explorer_state": 0, **tracks[m].counts}
                for m in self.members
            }
            out["trajectories"] = {
                m: {
                    k: f"{FLEET_DIR}/{m}/{v}"
                    for k, v in TRAJECTORY_FILES.items()
                    if tracks[m].counts.get(k)
                }
                for m in self.members
            }
        return out

    def status_details(self) -> dict:
        recorded = self.recorded()
        out = {
            "recorded": recorded,
            "progress": _recorded_line(recorded),
            "rrd": str(self.rrd_path or ""),
        }
        if self.members:
            out["members"] = {m: dict(self.core.tracks[m].counts) for m in self.members}
        return out


def _recorded_line(recorded: dict[str, int]) -> str:
    parts = [f"{recorded['pose']} poses"]
    if recorded["pose_truth"]:
        parts.append(f"{recorded['pose_truth']} true poses")
    parts += [f"{recorded['delta']} deltas", f"{recorded['patch']} patches"]
    return ", ".join(parts)


def main(config: SmanaConfig, rrd_path: Path | None = None, spawn=False, connect=None) -> int:
    if rrd_path is None and config.general.run_dir:
        rrd_path = Path(config.general.run_dir) / RRD_NAME
    return RecorderService(config, rrd_path, spawn, connect).run()


def recorder_argv(config_path: str | Path, robot: str) -> list[str]:
    """The command line `smana up` starts the recorder with (see deploy/supervisor.py)."""
    return [
        sys.executable,
        "-m",
        "smana.deploy.recording",
        "--config",
        str(config_path),
        "--robot",
        robot,
    ]


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import config_from_args, make_parser, setup_logging

    p = make_parser("smana recorder", "Record a running smana stack into a Rerun .rrd file.")
    p.add_argument("--rrd", type=Path, help=f"output file (default RUN_DIR/{RRD_NAME})")
    p.add_argument("--spawn", action="store_true", help="also stream to a newly spawned viewer")
    p.add_argument("--viewer-url", metavar="URL", help="also stream to a running viewer (gRPC)")
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    setup_logging(cfg.general.log_level, "recorder")
    return main(cfg, args.rrd, args.spawn, args.viewer_url)


if __name__ == "__main__":
    from smana.common.cli import run_command

    sys.exit(run_command("recorder", cli))
