"""The recorder's core, without Zenoh: `RunRecorder` logs decoded poses, images, map deltas, graph
patches and explorer states into a Rerun recording and writes the trajectory files (see the
package's docstring for what goes where)."""

from __future__ import annotations

import logging
import math
import sys
import time
from pathlib import Path

import msgpack
import numpy as np

from smana.common.classes import MEMBER_COLOURS, ClassTable
from smana.common.messages import GraphPatch, MapDelta, Pose
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid
from smana.services.recorder.voxels import VoxelStore

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
            yaw = goal.get("yaw")
            if yaw is None:  # a goal with no heading (`smana goto X Y`): a point, no arrow
                self.rec.log(
                    f"{ex}/goal", rr.Points3D([[gx, gy, 0.15]], colors=[colour], radii=0.12)
                )
            else:
                yaw = float(yaw)
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
