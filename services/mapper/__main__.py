"""`smana mapper`: online semantic 3D mapping (octree-max, octree-bayes, tsdf, ...) over zenoh.

Integrates the robot's semantic clouds, publishes a MapDelta per cloud, answers stats, snapshot,
save and point queries, autosaves, and resumes from a map file with --load.
"""

from __future__ import annotations

import sys

from smana.common.cli import ServiceCommand, doc_summary, run_command

# e.g. an unreadable --load file: said in one line, no traceback
COMMAND = ServiceCommand(
    "mapper", doc_summary(__doc__), "smana.services.mapper.service:main", (OSError, ValueError)
)


def cli(argv: list[str] | None = None) -> int:
    p = COMMAND.parser()
    p.add_argument("--load", metavar="FILE", help='resume from a saved map ("auto": save_path)')
    p.add_argument("--save", metavar="FILE", help="where to autosave the map (mapper.save_path)")
    args = p.parse_args(argv)
    flags = {"mapper.load": args.load, "mapper.save_path": args.save}
    cfg = COMMAND.config(args, [f"{key}={value}" for key, value in flags.items() if value])
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
    return COMMAND.run(cfg)


if __name__ == "__main__":
    sys.exit(run_command("mapper", cli))
