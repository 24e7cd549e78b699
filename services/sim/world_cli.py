"""`smana world ...`: look at a simulator world without running the simulator.

    smana world export  --seed 3 --out gt.ply          # labelled ground-truth cloud (PLY)
    smana world preview --seed 3 --out world.png       # top-down picture of the classes
    smana world info    --seed 3                       # object counts, free share (JSON)

Every subcommand takes either `--seed/--size` (procedural garden) or `--ply` (a world built from
a labelled cloud, as `smana sim --world ply:PATH` would build it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from smana.common.cli import ArgumentParser, int_in, output_file, positive_float

from .world import GardenWorld, WorldError


def _world_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=0, help="procedural garden seed (default 0)")
    p.add_argument(
        "--size", type=positive_float, default=12.0, help="side of the square world, metres"
    )
    p.add_argument(
        "--ground-resolution", type=positive_float, default=None, help="height field cell, m"
    )
    p.add_argument("--ply", type=Path, default=None, help="build the world from a labelled PLY")
    p.add_argument(
        "--voxel", type=positive_float, default=0.05, help="object voxel size for --ply, m"
    )
    p.add_argument("--classes", default="garden3drms", help="class table name or TOML path")


def build_world(args: argparse.Namespace) -> GardenWorld:
    from smana.common.classes import ClassTable

    classes = ClassTable.load(args.classes)
    if args.ply is not None:
        kw = {"ground_resolution_m": args.ground_resolution} if args.ground_resolution else {}
        return GardenWorld.from_ply(args.ply, classes, voxel_m=args.voxel, **kw)
    kw = {"ground_resolution_m": args.ground_resolution} if args.ground_resolution else {}
    return GardenWorld.generate(args.seed, size_m=args.size, classes=classes, **kw)


def cli(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="smana world", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="write the ground-truth labelled cloud as PLY")
    _world_args(exp)
    exp.add_argument("--out", type=Path, required=True)
    exp.add_argument("--spacing", type=positive_float, default=0.03, help="sample spacing, m")
    pre = sub.add_parser("preview", help="write a top-down PNG of the classes")
    _world_args(pre)
    pre.add_argument("--out", type=Path, required=True)
    pre.add_argument(
        "--pixels", type=int_in(16, 16384), default=768, help="approximate image width"
    )
    info = sub.add_parser("info", help="print a summary as JSON")
    _world_args(info)
    args = parser.parse_args(argv)
    if getattr(args, "out", None) is not None:
        output_file(args.out)  # before the world is built, not after

    try:
        world = build_world(args)
        if args.command == "export":
            n = world.export_ply(args.out, args.spacing)
            print(f"wrote {n} points to {args.out}")
        elif args.command == "preview":
            import cv2

            img = world.preview_image(args.pixels)
            try:
                written = cv2.imwrite(str(args.out), np.ascontiguousarray(img[..., ::-1]))
            except cv2.error:
                written = False
            if not written:
                raise OSError(f"could not write {args.out} (is the extension an image type?)")
            print(f"wrote {img.shape[1]}x{img.shape[0]} preview to {args.out}")
        else:
            print(json.dumps(world.summary(), indent=2))
    except (WorldError, OSError, ValueError) as exc:
        print(f"smana world: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    raise SystemExit(run_command("world", cli))
