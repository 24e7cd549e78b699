"""`smana mapper`: online semantic 3D mapping (octree-max, octree-bayes, tsdf, ...) over zenoh.

Integrates the robot's semantic clouds, publishes a MapDelta per cloud, answers stats, snapshot,
save and point queries, autosaves, and resumes from a map file with --load.
"""

from __future__ import annotations

import sys

from smana.common.cli import config_from_args, doc_summary, make_parser, run_command, setup_logging


def cli(argv: list[str] | None = None) -> int:
    p = make_parser("smana mapper", doc_summary(__doc__))
    p.add_argument("--load", metavar="FILE", help='resume from a saved map ("auto": save_path)')
    p.add_argument("--save", metavar="FILE", help="where to autosave the map (mapper.save_path)")
    args = p.parse_args(argv)
    if args.load:
        args.overrides.append(f"mapper.load={args.load}")
    if args.save:
        args.overrides.append(f"mapper.save_path={args.save}")
    cfg = config_from_args(args)
    from smana.services.mapper.backends import check_backend

    check_backend(cfg.mapper.backend)  # an unknown back-end stops here, in one line
    if cfg.mapper.source == "fleet":
        from smana.services.mapper.fleet import check_fleet_source

        check_fleet_source(cfg.mapper, cfg.fleet)  # so does a fleet map that cannot be merged
    from smana.services.mapper.semantic_map import SemanticMap

    try:
        # a map the library refuses (a range beyond the map's extent) stops here, in one line
        SemanticMap.from_config(cfg.mapper, cfg.general.class_table)
        if cfg.mapper.load and cfg.mapper.load != "auto":
            # so does a map file that cannot be used, before zenoh opens; the arrays' values are
            # checked as they are read, in the service (one line, exit 2)
            SemanticMap.check_file(cfg.mapper.load, cfg.general.class_table, cfg.mapper.backend)
    except ValueError as exc:
        print(f"smana mapper: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    setup_logging(cfg.general.log_level, "mapper")
    from smana.services.mapper.service import main

    try:
        return main(cfg)
    except (OSError, ValueError) as exc:  # e.g. an unreadable --load file: say so, no traceback
        print(f"smana mapper: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(run_command("mapper", cli))
