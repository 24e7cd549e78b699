"""`smana world ...`: look at a simulator world without running the simulator.

    smana world export  --seed 3 --out gt.ply          # labelled ground-truth cloud (PLY)
    smana world preview --seed 3 --out world.png       # top-down picture of the classes
    smana world info    --seed 3                       # object counts, free share (JSON)
    smana world preview --world ply:garden.ply --out world.png

Every subcommand takes `--world` as `sim.world` does (resolved by the registry in
services/sim/worlds: `garden`, the default, with `--seed/--size`; `ply:PATH`, or `--ply PATH`,
with `--voxel`; an out-of-tree `module:Class`), and builds the world `smana sim` would build.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from smana.common.cli import ArgumentParser, int_in, output_file, positive_float

from .worlds import World, WorldError, build_world


def _world_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--world", default=None, help="a sim.world value: garden (default), ply:PATH, module:Class"
    )
    p.add_argument("--seed", type=int, default=0, help="world seed (default 0)")
    p.add_argument(
        "--size", type=positive_float, default=None, help="side of the procedural garden, m"
    )
    p.add_argument(
        "--ground-resolution", type=positive_float, default=None, help="height field cell, m"
    )
    p.add_argument("--ply", type=Path, default=None, help="the same as --world ply:PATH")
    p.add_argument(
        "--voxel", type=positive_float, default=None, help="object voxel size for a PLY, m"
    )
    p.add_argument("--classes", default="garden3drms", help="class table name or TOML path")


def world_from_args(args: argparse.Namespace) -> World:
    """The world the flags describe, built through the registry as `smana sim` would build it."""
    from smana.common.classes import ClassTable
    from smana.common.config.sim import GardenConfig, PlyConfig, SimConfig

    garden, ply = {}, {}
    if args.size is not None:
        garden["size_m"] = args.size
    if args.ground_resolution is not None:
        garden["ground_resolution_m"] = ply["ground_resolution_m"] = args.ground_resolution
    if args.voxel is not None:
        ply["voxel_m"] = args.voxel
    world = args.world or (f"ply:{args.ply}" if args.ply is not None else "garden")
    config = SimConfig(
        world=world, seed=args.seed, garden=GardenConfig(**garden), ply=PlyConfig(**ply)
    )
    return build_world(config, ClassTable.load(args.classes))


def write_preview(world: World, out: Path, pixels: int, seed: int | None = None) -> Path:
    """The world from above in metres, hill-shaded, its classes in a legend (lab/plots.py draws
    every smana figure; imported here, lazily, so the other subcommands never load matplotlib)."""
    from smana.lab import plots

    from .worlds.preview import shaded_classes

    top = world.top_class()
    lo, hi = (
        top.origin_xy,
        np.asarray(top.origin_xy) + np.asarray(top.data.shape) * top.resolution_m,
    )
    title = f"world preview (hill-shaded): {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m" + (
        f", seed {seed}" if seed is not None else ""
    )
    fig = plots.world_map(
        world.classes, top.data, top.origin_xy, top.resolution_m, title, shaded_classes(world)
    )
    width_in = fig.get_size_inches()[0]
    return plots.save(fig, out, dpi=max(20, round(pixels / width_in)))


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
        world = world_from_args(args)
        if args.command == "export":
            n = world.export_ply(args.out, args.spacing)
            print(f"wrote {n} points to {args.out}")
        elif args.command == "preview":
            write_preview(world, args.out, args.pixels, args.seed)
            print(f"wrote a {args.pixels} px wide preview (axes in metres) to {args.out}")
        else:
            print(json.dumps(world.summary(), indent=2))
    except (WorldError, OSError, ValueError) as exc:
        print(f"smana world: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    raise SystemExit(run_command("world", cli))
