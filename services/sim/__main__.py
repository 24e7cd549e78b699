"""`smana sim`: run the PyBullet simulator service.

    smana sim --world garden --seed 3 --noise medium --pose-noise 0.1,0.02
    smana sim --world ply:garden.ply --camera 320x320 --camera-rate 5 --lidar --rtf 2

Every flag is a shortcut for a `[sim]` config key (`--set sim.KEY=VALUE` reaches the others).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from smana.common.cli import UsageError, config_from_args, make_parser, run_command, setup_logging


def _pair(text: str, sep: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(sep))
    except ValueError:
        raise UsageError(f"{name} wants two numbers joined by {sep!r}, not {text!r}") from None
    return a, b


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana sim", __doc__.strip().splitlines()[0])
    g = p.add_argument_group("simulation")
    g.add_argument("--world", help="'garden' (procedural) or ply:PATH (a labelled cloud)")
    g.add_argument("--seed", type=int, help="world and noise seed")
    g.add_argument("--size", type=float, help="side of the procedural garden, m")
    g.add_argument(
        "--noise",
        choices=["off", "none", "low", "medium", "high"],
        help="label noise level (paper Table 2)",
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
    args = p.parse_args(argv)
    cfg = config_from_args(args)
    sc = cfg.sim
    changes: dict = {}
    if args.world:
        world = args.world
        if world != "garden":
            path = world[4:] if world.startswith("ply:") else world
            world = "ply:" + str(Path(path).resolve())  # the supervisor runs us elsewhere
        changes["world"] = world
    for flag, key in (
        ("seed", "seed"),
        ("size", "size_m"),
        ("noise", "noise"),
        ("camera_rate", "camera_rate_hz"),
        ("stride", "camera_stride"),
        ("lidar_rate", "lidar_rate_hz"),
        ("rtf", "real_time_factor"),
    ):
        if getattr(args, flag) is not None:
            changes[key] = getattr(args, flag)
    if args.pose_noise:
        changes["pose_noise_xy_m"], changes["pose_noise_yaw_rad"] = _pair(
            args.pose_noise, ",", "--pose-noise"
        )
    if args.camera:
        w, h = _pair(args.camera.lower(), "x", "--camera")
        changes["camera_width"], changes["camera_height"] = int(w), int(h)
    for flag, key, value in (
        ("no_camera", "camera_enabled", False),
        ("images", "publish_images", True),
        ("lidar", "lidar_enabled", True),
        ("lockstep", "lockstep", True),
    ):
        if getattr(args, flag):
            changes[key] = value
    sc = dataclasses.replace(sc, **changes)
    from smana.common.config import ConfigError, SimConfig, build

    try:  # the flags go through the same checks as the config file
        sc = build(SimConfig, {f.name: getattr(sc, f.name) for f in dataclasses.fields(sc)}, "sim.")
    except ConfigError as exc:
        print(f"smana sim: {exc}", file=sys.stderr)
        return 2
    cfg = dataclasses.replace(cfg, sim=sc)
    setup_logging(cfg.general.log_level, "sim")
    from smana.services.sim.service import main
    from smana.services.sim.world import WorldError

    try:
        return main(cfg)
    except (WorldError, ValueError) as exc:
        print(f"smana sim: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(run_command("sim", cli))
