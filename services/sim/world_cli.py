"""`smana world ...`: look at a simulator world without running the simulator.

    smana world preview --out world.png                # the world `smana up` explores
    smana world export  --out gt.ply                   # its labelled ground-truth cloud (PLY)
    smana world info                                   # object counts, free shares (JSON)
    smana world preview --seed 0 --out world.png       # another garden
    smana world preview --world ply:garden.ply --out world.png

The world is the one the config describes, exactly as `smana up` and `smana sim` build it: the
defaults (`sim.seed` 3, the `[sim.garden]` knobs), then `--config FILE` and `--set sim.KEY=VALUE`,
then the flags here (`--seed`, `--size`, ... override the config). `--world` takes what `sim.world`
takes (resolved by the registry in services/sim/worlds: `garden`, the default; `ply:PATH`, or
`--ply PATH`, with `--voxel`; an out-of-tree `module:Class`)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from smana.common.cli import (
    ArgumentParser,
    add_config_args,
    config_file_from_args,
    doc_summary,
    int_in,
    non_negative_int,
    output_file,
    positive_float,
)

from .worlds import World, WorldError, build_world


def _world_args(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument(
        "--world", default=None, help="a sim.world value: garden (default), ply:PATH, module:Class"
    )
    p.add_argument(
        "--seed", type=non_negative_int, default=None, help="world seed (default: sim.seed, 3)"
    )
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
    p.add_argument(
        "--classes",
        default=None,
        help="class table name or TOML path (default: general.class_table)",
    )


def sim_config_from_args(args: argparse.Namespace):
    """(`[sim]` section, class table name) the flags describe: the config's, with the flags on
    top. The same config with no flags gives the world `smana up` explores."""
    if args.world is not None or args.ply is not None:  # before loading: its [sim.<key>] is known
        world = args.world or f"ply:{args.ply}"
        args.overrides = [*(args.overrides or []), f"sim.world={json.dumps(world)}"]
    cfg = config_file_from_args(args)
    sim = cfg.sim
    garden, ply = {}, {}
    if args.size is not None:
        garden["size_m"] = args.size
    if args.ground_resolution is not None:
        garden["ground_resolution_m"] = ply["ground_resolution_m"] = args.ground_resolution
    if args.voxel is not None:
        ply["voxel_m"] = args.voxel
    changes: dict = {
        "garden": dataclasses.replace(sim.garden, **garden),
        "ply": dataclasses.replace(sim.ply, **ply),
    }
    if args.world is not None or args.ply is not None:
        changes["world"] = args.world or f"ply:{args.ply}"
    if args.seed is not None:
        changes["seed"] = args.seed
    return dataclasses.replace(sim, **changes), args.classes or cfg.general.class_table


def world_from_args(args: argparse.Namespace) -> World:
    """The world the flags describe, built through the registry as `smana sim` would build it."""
    from smana.common.classes import ClassTable

    sim, classes = sim_config_from_args(args)
    return build_world(sim, ClassTable.load(classes))


def write_preview(world: World, out: Path, pixels: int, seed: int | None = None) -> Path:
    """The world from above in metres, hill-shaded, its classes in a legend (common/plotting.py
    draws the product's figures; imported here, lazily, so the other subcommands never load
    matplotlib)."""
    from smana.common import plotting

    from .worlds.preview import shaded_classes

    top = world.top_class()
    lo, hi = (
        top.origin_xy,
        np.asarray(top.origin_xy) + np.asarray(top.data.shape) * top.resolution_m,
    )
    title = f"world preview (hill-shaded): {hi[0] - lo[0]:.1f} x {hi[1] - lo[1]:.1f} m" + (
        f", seed {seed}" if seed is not None else ""
    )
    fig = plotting.world_map(
        world.classes, top.data, top.origin_xy, top.resolution_m, title, shaded_classes(world)
    )
    width_in = fig.get_size_inches()[0]
    return plotting.save(fig, out, dpi=max(20, round(pixels / width_in)))


def cli(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="smana world", description=doc_summary(__doc__))
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
            radius_m = config_file_from_args(args).navgraph.robot_radius_m
            print(json.dumps(world.summary(radius_m), indent=2))
    except BrokenPipeError:
        raise  # the reader went away (`| head`): run_command ends it quietly
    except (WorldError, OSError, ValueError) as exc:
        print(f"smana world: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    raise SystemExit(run_command("world", cli))
