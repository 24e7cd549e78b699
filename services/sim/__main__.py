"""`smana sim`: run the PyBullet simulator service.

    smana sim --world garden --seed 3 --noise medium --pose-noise 0.1,0.02
    smana sim --world ply:garden.ply --camera 320x320 --camera-rate 5 --lidar --rtf 2
    smana sim --robots 3             # a fleet r1, r2, r3 in one world, under `fleet.name`

Every flag is a shortcut for a config key: `--set sim.KEY=VALUE` or `--set sim.camera.KEY=VALUE`
reaches the others. `--robots N` is `fleet.robots = ["r1", .., "rN"]`; the service then runs under
`fleet.name` unless `--robot` says otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from smana.common.cli import ServiceCommand, UsageError, doc_summary, run_command

# a world that cannot be built (a WorldError) or a value the simulator refuses: one line
COMMAND = ServiceCommand(
    "sim", doc_summary(__doc__), "smana.services.sim.service:main", (ValueError,)
)


def _pair(text: str, sep: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(sep))
    except ValueError:
        raise UsageError(f"{name} wants two numbers joined by {sep!r}, not {text!r}") from None
    return a, b


def _absolute_world(spec: str) -> str:
    """A PLY world's path made absolute (the supervisor runs us elsewhere); others as they are."""
    from smana.services.sim.worlds import world_source
    from smana.services.sim.worlds.cloud import PlyWorld

    try:
        source = world_source(spec)
    except ValueError:
        return spec  # the service reports it, in one line
    if isinstance(source, PlyWorld) and source.arg:
        return "ply:" + str(Path(source.arg).resolve())
    return spec


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string
    return repr(v)


def cli(argv: list[str] | None = None) -> int:
    p = COMMAND.parser()
    g = p.add_argument_group("simulation")
    g.add_argument(
        "--world", help="'garden' (procedural), ply:PATH (a labelled cloud) or module:Class"
    )
    g.add_argument("--seed", type=int, help="world and noise seed")
    g.add_argument("--size", type=float, help="side of the procedural garden, m")
    g.add_argument(
        "--noise",
        choices=["off", "none", "low", "medium", "high", "realistic"],
        help="label noise: a level of the paper's Table 2, or realistic (docs/tutorial.md)",
    )
    g.add_argument("--pose-noise", metavar="XY,YAW", help="std devs: metres, radians")
    g.add_argument("--camera", metavar="WxH", help="camera resolution, e.g. 320x320")
    g.add_argument("--camera-rate", type=float, metavar="HZ")
    g.add_argument("--stride", type=int, help="cloud from every n-th pixel row and column")
    g.add_argument("--no-camera", action="store_true", help="no camera clouds")
    g.add_argument("--images", action="store_true", help="also publish rgb/depth/semantic")
    g.add_argument("--lidar", action="store_true", help="publish LiDAR scans on robot/scan")
    g.add_argument("--lidar-rate", type=float, metavar="HZ")
    g.add_argument("--rtf", type=float, metavar="X", help="real-time factor")
    g.add_argument("--lockstep", action="store_true", help="wait for each cloud's MapDelta")
    g.add_argument(
        "--robots", type=int, metavar="N", help="a fleet r1 .. rN in one world (fleet.robots)"
    )
    args = p.parse_args(argv)
    # each flag is a `--set` override, applied after the user's: the same checks and messages
    sets: dict[str, object] = {}
    if args.world:
        sets["world"] = _absolute_world(args.world)
    for flag, key in (
        ("seed", "seed"),
        ("size", "garden.size_m"),
        ("noise", "noise"),
        ("camera_rate", "camera.rate_hz"),
        ("stride", "camera.stride"),
        ("lidar_rate", "lidar.rate_hz"),
        ("rtf", "real_time_factor"),
    ):
        if getattr(args, flag) is not None:
            sets[key] = getattr(args, flag)
    if args.pose_noise:
        sets["pose_noise_xy_m"], sets["pose_noise_yaw_rad"] = _pair(
            args.pose_noise, ",", "--pose-noise"
        )
    if args.camera:
        w, h = _pair(args.camera.lower(), "x", "--camera")
        sets["camera.width"], sets["camera.height"] = int(w), int(h)
    for flag, key, value in (
        ("no_camera", "camera.enabled", False),
        ("images", "camera.publish_images", True),
        ("lidar", "lidar.enabled", True),
        ("lockstep", "lockstep", True),
    ):
        if getattr(args, flag):
            sets[key] = value
    args.overrides = [*(args.overrides or []), *(f"sim.{k}={_toml(v)}" for k, v in sets.items())]
    if args.robots is not None:
        if args.robots < 1:
            raise UsageError(f"--robots wants a count >= 1, not {args.robots}")
        names = [f"r{i}" for i in range(1, args.robots + 1)]
        args.overrides.append(f"fleet.robots={json.dumps(names)}")
    cfg = COMMAND.config(args)
    if args.robots is not None and not args.robot:  # the fleet's sim speaks for no one member
        cfg = dataclasses.replace(
            cfg, general=dataclasses.replace(cfg.general, robot=cfg.fleet.name)
        )
    return COMMAND.run(cfg)


if __name__ == "__main__":
    sys.exit(run_command("sim", cli))
