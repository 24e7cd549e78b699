"""A zenoh router in a Python process: the embedded default needs no zenohd.

`smana up` runs one inside the supervisor; `smana router` runs one alone (for tests, or as the
meeting point of a multi-host deployment)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import signal
import threading

from smana.common.config import ZenohConfig
from smana.common.zenoh_config import make_zenoh_config

log = logging.getLogger("smana.router")


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


def open_router(listen: list[str], base: ZenohConfig | None = None, connect: list[str] = ()):
    import zenoh

    return zenoh.open(router_config(listen, base, connect))


def cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="smana router", description=__doc__)
    p.add_argument(
        "--listen", "-l", action="append", metavar="ENDPOINT",
        help="endpoint to listen on (default tcp/127.0.0.1:7447; repeatable)",
    )  # fmt: skip
    p.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config (TLS, ACL, ...)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s router: %(message)s")
    listen = args.listen or ["tcp/127.0.0.1:7447"]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    base = ZenohConfig(config_file=args.zenoh_config or "")
    with open_router(listen, base) as session:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
        stop.wait()
    log.info("router stopped")
    return 0


if __name__ == "__main__":
    raise SystemExit(cli())
