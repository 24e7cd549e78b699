"""The Rerun recorder: a Zenoh subscriber that logs what flows through a run into a `.rrd` file.

    python -m smana.services.recorder --config run/config.toml --run-dir run  # (smana up runs it)
    smana view --spawn                                                        # live, in a viewer

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

The package: `recorder.py` (`RunRecorder`, the part without Zenoh, fed decoded messages, used in
tests), `voxels.py` (the map rebuilt from deltas), `service.py` (the Zenoh wiring) and
`__main__.py`. `rerun` is imported lazily and a missing SDK gives a one-line hint and a recorder
that does nothing.
"""
