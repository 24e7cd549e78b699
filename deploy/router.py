"""A zenoh router in a Python process: the embedded default needs no zenohd.

`smana up` runs one inside the supervisor; `smana router` runs one alone (for tests, or as the
meeting point of a multi-host deployment)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading

from smana.common.config import ZenohConfig
from smana.common.zenoh_config import make_zenoh_config

log = logging.getLogger("smana.router")


def router_config(listen: list[str], base: ZenohConfig | None = None):
    """A router-mode zenoh config listening on `listen`, scouting and gossip off unless `base`
    (the [zenoh] section, for its config file and scouting choice) says otherwise."""
    zc = base or ZenohConfig()
    conf = make_zenoh_config(
        ZenohConfig(
            mode="router",
            connect=[],
            listen=list(listen),
            multicast_scouting=zc.multicast_scouting,
            gossip=zc.gossip,
            config_file=zc.config_file,
        )
    )
    # A router relays everything; it keeps no storage, so no plugin is needed.
    conf.insert_json5("plugins_loading/enabled", json.dumps(False))
    return conf


def open_router(listen: list[str], base: ZenohConfig | None = None):
    import zenoh

    return zenoh.open(router_config(listen, base))


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
