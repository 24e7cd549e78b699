"""What a `smana.common.service.Service` tells about itself: its `ServiceStatus`, published
every `general.status_period_s` and answered as a query; while it starts (or compiles its kernels)
a heartbeat thread publishes it and the zenoh callback answers it, since the main loop is busy.
"""

from __future__ import annotations

import os
import time

from smana.common import keys
from smana.common.messages import MessageError, ServiceStatus, decode
from smana.common.service_queries import query_form, reply_bytes, reply_encoding


class Liveliness:
    """The part of `Service` that builds, publishes and answers its status."""

    def status(self) -> ServiceStatus:
        self._status_seq += 1
        starting = self.state == "starting"
        with self.books.lock:
            # Computed between messages, or while answering a status query: then the one
            # message in flight is that query, which counts itself accepted.
            b = self.books
            queued = self._pending_locked() - b.in_flight
            books = (
                b.received,
                b.accepted + b.in_flight,
                dict(b.dropped),
                dict(b.rejected),
                queued,
            )
        if starting or self.kernels != "ready":  # no service state read: maybe off the loop
            details = {"startup_step": self.startup_step}
        else:
            details = self.status_details()
        if self.ready_s is not None:
            details = {**details, "ready_s": round(self.ready_s, 3)}
            details["ready_cpu_s"] = round(self.ready_cpu_s, 3)
        if self.prepare_in_background:
            details["kernels"] = self.kernels
            if self.kernels_s is not None:
                details["kernels_s"] = round(self.kernels_s, 3)
        return ServiceStatus(
            stamp_s=time.time(),
            seq=self._status_seq,
            robot=self.robot,
            service=self.name,
            pid=os.getpid(),
            uptime_s=time.monotonic() - self._t0,
            state=self.state,
            msgs_in=books[0],
            msgs_out=self.msgs_out,
            accepted=books[1],
            dropped=books[2],
            rejected=books[3],
            pending=books[4],
            events=dict(self.events),
            details=details,
        )

    def _heartbeat(self) -> None:
        """While starting, and while the kernels compile: a status every period, from this
        thread (the main one is busy, or may wait for a kernel)."""
        period = self.config.general.status_period_s
        while True:
            with self._status_lock:
                if (self.state != "starting" and self.kernels == "ready") or self.stopping:
                    return
                msg = self.status()
            try:
                self._status_pub.put(msg)
            except Exception:  # the session is closing
                return
            self._ready.wait(period)
            if self.state != "starting" and self.kernels != "ready":
                self._ready.clear()  # now live: wait for the next period, or the kernels

    def _on_status_query(self, query) -> None:
        """Status queries: answered right here while starting (the main loop is not running yet;
        the starting status reads no service state), from the main loop afterwards."""
        with self._status_lock:
            starting = self.state == "starting" or self.kernels != "ready"
            msg = self.status() if starting else None
        key = keys.status(self.robot, self.name)
        if msg is None:
            self._push(("query", lambda req: self.status(), key, query))
            return
        with self.books.lock:
            self.books.received += 1
            self.books.accepted += 1
        try:
            as_json = query_form(query)[1]
            query.reply(key, reply_bytes(msg, as_json), encoding=reply_encoding(as_json))
        except Exception:  # the querier left: nothing to answer
            pass

    def _publish_status(self) -> None:
        with self._status_lock:
            msg = self.status()
        self._status_pub.put(msg)


def kernels_loaded(sample) -> tuple[str, bool] | None:
    """From a status sample (a raw zenoh callback's): the service's name and whether its kernels
    are loaded (yes for a status that does not say: a service of another kind). A service is
    live before its kernels compile in the background (answering `warming_up`), so its alive
    token alone does not say it serves; a consumer that starts a clock on a producer's readiness
    (the explorer's budget, the replay's first scan) waits for this too. Every status says
    `kernels` from the session's opening, well before the alive token. None: no status."""
    try:
        st = decode(sample.payload.to_bytes(), ServiceStatus)
    except MessageError:
        return None
    return st.service, st.details.get("kernels", "ready") == "ready"
