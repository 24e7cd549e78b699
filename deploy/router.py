"""A zenoh router in a Python process: the embedded default needs no zenohd.

`smana up` runs one inside the supervisor; `smana router` runs one alone (for tests, or as the
meeting point of a multi-host deployment)."""

from __future__ import annotations

import dataclasses
import json
import logging
import threading

from smana.common.config import ZenohConfig
from smana.common.service import on_stop_signals
from smana.common.zenoh_config import make_zenoh_config, open_session

log = logging.getLogger("smana.router")

# How `smana up` (and `smana router` without --listen) choose another port for the router.
ROUTER_LISTEN_HINT = "--set 'deploy.router_listen=[\"{}\"]'"


def router_config(listen: list[str], base: ZenohConfig | None = None, connect: list[str] = ()):
    """A router-mode zenoh config listening on `listen` and linking to the routers in `connect`.
    From `base` (the [zenoh] section) it keeps the config file, scouting choice and security:
    TLS files, the credentials (it logs in to other routers as user `router` and accepts every
    user of the file) and the access-control policy."""
    zc = base or ZenohConfig()
    conf = make_zenoh_config(
        dataclasses.replace(
            zc,
            mode="router",
            connect=list(connect),
            listen=list(listen),
            user="router" if zc.credentials_file else "",
        )
    )
    # A router relays everything; it keeps no storage, so no plugin is needed.
    conf.insert_json5("plugins_loading/enabled", json.dumps(False))
    return conf


def open_router(listen: list[str], base: ZenohConfig | None = None, connect: list[str] = (),
                listen_hint: str = ROUTER_LISTEN_HINT):  # fmt: skip
    """The router's session; a `SessionError` (one line) when it cannot open, e.g. a port in use.
    `listen_hint` tells the user how to choose another endpoint ({} is a suggested one)."""
    import zenoh

    zenoh.try_init_log_from_env()  # RUST_LOG=debug shows zenoh's own view of links and auth
    return open_session(router_config(listen, base, connect), listen_hint)


def cli(argv: list[str] | None = None) -> int:
    from smana.common.cli import config_from_args, make_parser
    from smana.deploy.supervisor import profile_path

    p = make_parser("smana router", __doc__)
    p.add_argument(
        "--profile",
        default="local",
        help="take the router's endpoints and security from this deployment profile",
    )
    args = p.parse_args(argv)
    cfg = config_from_args(args, layers=[profile_path(args.profile, p)])
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s router: %(message)s")
    # --listen/--connect name the router's own endpoints; otherwise the [deploy] section does.
    listen = args.listen or cfg.deploy.router_listen
    connect = args.connect or cfg.deploy.router_connect
    stop = threading.Event()
    on_stop_signals(lambda _sig: stop.set())
    hint = "--listen {}" if args.listen else ROUTER_LISTEN_HINT
    with open_router(listen, cfg.zenoh, connect, hint) as session:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
        if connect:
            log.info("linking to %s", ", ".join(connect))
        stop.wait()
    log.info("router stopped")
    return 0


if __name__ == "__main__":
    from smana.common.cli import run_command

    raise SystemExit(run_command("router", cli))
