"""`smana recorder`'s Zenoh wiring: subscribes to what a run sends and feeds `RunRecorder`; writes
`recorder.json` when it stops."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import msgpack

from smana.common import keys
from smana.common.classes import ClassTable
from smana.common.config import SmanaConfig
from smana.common.messages import GraphPatch, MapDelta, Pose
from smana.common.service import Service
from smana.services.recorder.recorder import (
    FLEET_DIR,
    RRD_NAME,
    SUMMARY_NAME,
    TRAJECTORY_FILES,
    RunRecorder,
)


class RecorderService(Service):
    """Records everything it is sent until the stack stops: what is still queued when the stop
    comes is recorded too (`drain_on_stop`), and `smana up` stops it after every service it
    records (`Supervisor.shutdown`). Poses are recorded as they come, without the explorer's
    plausibility gates: the record is the evidence of what was on the wire (a spoofed or jumping
    pose included), and a gate tuned for a ground robot (`general.max_speed_mps`) would refuse a
    replayed car's poses. The figures that matter come from trusted sources instead: a replay's
    distance from the poses the replay itself published (`replay_trajectory.csv`), and a secured
    deployment lets only the sensor roles publish poses (`deploy/acl.py`)."""

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
        "smana.services.recorder",
        "--config",
        str(config_path),
        "--robot",
        robot,
    ]
