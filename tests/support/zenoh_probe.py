"""A small zenoh client for the multi-host tests, run inside a network namespace.

    zenoh_probe.py open ENDPOINT [auth]           exit 0 when a router answered, 3 when not
    zenoh_probe.py sub ENDPOINT KEY OUT [auth]    write received payloads to OUT, one per line
    zenoh_probe.py pub ENDPOINT KEY PAYLOAD [auth]
    zenoh_probe.py get ENDPOINT KEY OUT [--json BODY] [auth]
    zenoh_probe.py serve ENDPOINT KEY PAYLOAD [auth]   reply PAYLOAD to every query on KEY

auth: --user U --credentials FILE, and for tls/ endpoints --tls-dir DIR --host NAME (the
folder of `smana deploy init-certs` and the host whose certificate to present).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import zenoh

from smana.common.config import ZenohConfig
from smana.common.zenoh_config import make_zenoh_config


def config(args) -> zenoh.Config:
    zc = ZenohConfig(
        mode="client",
        connect=[args.endpoint],
        user=args.user or "",
        credentials_file=args.credentials or "",
    )
    if args.tls_dir:
        d = args.tls_dir
        zc.tls_ca, zc.tls_cert, zc.tls_key = (
            f"{d}/ca.pem",
            f"{d}/{args.host}/host.pem",  # a host's folder of `smana deploy init-certs`
            f"{d}/{args.host}/host.key",
        )
    return make_zenoh_config(zc)


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("what", choices=["open", "sub", "pub", "get", "serve"])
    p.add_argument("endpoint")
    p.add_argument("rest", nargs="*")
    p.add_argument("--user")
    p.add_argument("--credentials")
    p.add_argument("--tls-dir")
    p.add_argument("--host", default="base")
    p.add_argument("--json")
    p.add_argument("--count", type=int, default=5)
    args = p.parse_args()
    try:
        session = zenoh.open(config(args))
    except zenoh.ZError as exc:
        print(f"no session: {exc}", file=sys.stderr)
        return 3
    with session:
        if not session.info.routers_zid():
            return 3
        if args.what == "open":
            return 0
        if args.what == "pub":
            key, payload = args.rest
            for _ in range(args.count):
                session.put(key, payload.encode())
                time.sleep(0.1)
            return 0
        if args.what == "get":
            key, out = args.rest
            kw = {}
            if args.json:
                kw = {"payload": args.json.encode(), "encoding": zenoh.Encoding.APPLICATION_JSON}
            replies = list(session.get(key, timeout=10.0, **kw))
            with open(out, "w") as f:
                for r in replies:
                    body = r.ok.payload.to_bytes() if r.ok else r.err.payload.to_bytes()
                    f.write(json.dumps({"ok": r.ok is not None, "body": body.decode()}) + "\n")
            return 0 if replies else 4
        stop = threading.Event()
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        if args.what == "serve":
            key, payload = args.rest
            q = session.declare_queryable(key, lambda query: query.reply(key, payload.encode()))
            print("serving", flush=True)
            stop.wait()
            q.undeclare()
            return 0
        key, out = args.rest
        with open(out, "a") as f:

            def on(sample):
                f.write(sample.payload.to_bytes().decode() + "\n")
                f.flush()

            sub = session.declare_subscriber(key, on)
            print("subscribed", flush=True)
            stop.wait()
            sub.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
