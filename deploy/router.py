"""A zenoh router in a Python process: the embedded default needs no zenohd.

`smana up` runs one inside the supervisor; `smana router` runs one alone (for tests, or as the
meeting point of a multi-host deployment)."""

from __future__ import annotations

import dataclasses
import json
import logging
import threading

from smana.common.config import ConfigError, ZenohConfig
from smana.common.service import on_stop_signals
from smana.common.zenoh_config import make_zenoh_config, open_session, read_credentials
from smana.deploy.acl import router_user, uplink_policy

log = logging.getLogger("smana.router")

# How `smana up` (and `smana router` without --listen) choose another port for the router.
ROUTER_LISTEN_HINT = "--set 'deploy.router_listen=[\"{}\"]'"


def router_config(listen: list[str], base: ZenohConfig | None = None, connect: list[str] = ()):
    """A router-mode zenoh config listening on `listen` and linking to the routers in `connect`.
    From `base` (the [zenoh] section) it keeps the config file, scouting choice and security:
    TLS files, the credentials (it logs in to other routers as the file's router user, `router`
    or `<robot>.router`, and accepts every user of the file: the dictionary) and the
    access-control policy, which it extends to the
    routers it links to over TLS when it has no TLS listener (`_trust_uplinks`)."""
    zc = base or ZenohConfig()
    user = ""
    if zc.credentials_file:
        try:
            user = router_user(read_credentials(zc.credentials_file))
        except (OSError, ValueError) as exc:
            raise ConfigError(f"zenoh.credentials_file {zc.credentials_file}: {exc}") from None
    conf = make_zenoh_config(
        dataclasses.replace(
            zc, mode="router", connect=list(connect), listen=list(listen), user=user
        )
    )
    # A router relays everything; it keeps no storage, so no plugin is needed.
    conf.insert_json5("plugins_loading/enabled", json.dumps(False))
    _trust_uplinks(conf)
    return conf


def _endpoints(conf, key: str) -> list[str]:
    value = json.loads(conf.get_json(key))
    return value.get("router", []) if isinstance(value, dict) else value  # per mode, or one list


def _carries_certificate(endpoint: str) -> bool:
    return endpoint.split("/", 1)[0] in ("tls", "quic")


def _trust_uplinks(conf) -> None:
    """Let the routers this one links to over TLS relay through it (`security.uplink_policy`):
    they cannot log in on a link this router opened, so their certificate is all it knows of them.
    Only where this router listens on no TLS endpoint: there, no one else can present one."""
    if not any(_carries_certificate(e) for e in _endpoints(conf, "connect/endpoints")):
        return
    acl = json.loads(conf.get_json("access_control"))
    if not acl.get("enabled"):
        return
    if any(_carries_certificate(e) for e in _endpoints(conf, "listen/endpoints")):
        log.warning(
            "this router listens on TLS and also links out over TLS: the routers it links to get "
            "no relay rights here (any TLS client presents a host certificate, so a certificate "
            "alone cannot name a router); let them link to this one as user `router` instead"
        )
        return
    conf.insert_json5("access_control", json.dumps(uplink_policy(acl)))


def open_router(
    listen: list[str],
    base: ZenohConfig | None = None,
    connect: list[str] = (),
    listen_hint: str = ROUTER_LISTEN_HINT,
):
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
