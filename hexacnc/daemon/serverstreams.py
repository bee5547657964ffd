"""Status, ``wait`` and ``subscribe`` of the socket server (:class:`hexacnc.daemon.server.SocketServer`):
``hello``/``status`` answered inline, ``wait`` on its own threads in short slices, subscription streams
served from the selector loop at their rate (a client that does not read loses samples), and the
results of worker threads delivered by the selector thread.

A mixin: it uses the server's connection table, result queue and :class:`.serverio.ConnectionIO`.
"""
from __future__ import annotations

import logging
import platform
import queue
import time

import msgpack

from .. import __version__
from ..errors import HexacncError
from . import protocol as P
from .serverio import _Conn

log = logging.getLogger("hexacnc.daemon.server")

#: subscription samples are skipped while a client has this much unsent
_STREAM_BACKLOG_BYTES = 256 * 1024
#: slice of Daemon.wait between checks for a closed client / server
_WAIT_SLICE_S = 0.2
#: outstanding "wait" requests per client
_MAX_WAITS_PER_CLIENT = 4
#: subscriptions per client
_MAX_SUBS_PER_CLIENT = 8
#: state values after which "wait" returns
_WAIT_DONE_STATES = ("idle", "fault")


class StatusStreams:
    """``hello``, ``status``, ``wait``, ``subscribe``/``unsubscribe`` and result delivery."""

    def _state_or_none(self) -> str | None:
        try:
            return str(self.daemon.status().get("state"))
        except Exception:
            return None

    def _status(self) -> dict:
        """The daemon's status as plain types; read at most once per loop pass (a copy each time)."""
        st = self._pass_status
        if st is None:
            st = self.daemon.status()
            if self.operator is not None:
                st = self.operator.status(st)
            ctl = self._controller
            st["controller"] = None if ctl is None else ctl.label()
            st = self._pass_status = P.plain(st)
        return dict(st)

    def _op_hello(self, conn: _Conn, req: P.Request) -> None:
        conn.client_name = str(req.fields.get("client", ""))[:64]
        try:
            info = P.plain(self.daemon.hello() or {})
        except Exception as exc:
            log.warning("Daemon.hello failed: %s", exc)
            info = {}
        versions = dict(info.get("versions") or {}) if isinstance(info.get("versions"), dict) else {}
        versions.update({"hexacnc": __version__, "protocol": P.PROTOCOL_VERSION,
                         "python": platform.python_version(), "msgpack": ".".join(map(str, msgpack.version))})
        info.update({
            "protocol": P.PROTOCOL_VERSION,
            "version": __version__,
            "versions": versions,
            "machine": info.get("machine") or self.machine_name,
            "role": "controller" if self._controller is conn else "observer",
            "access": conn.role,
            "controller_present": self._controller is not None,
            "status_rate_hz": self.status_rate_hz,
            "max_message_bytes": self.max_message_bytes,
            "ops": sorted(P.OPS),
        })
        self._send(conn, P.ok_reply(req.id, **info))

    def _op_status(self, conn: _Conn, req: P.Request) -> None:
        st = self._status()
        st["role"] = "controller" if self._controller is conn else "observer"
        st["access"] = conn.role
        self._send(conn, P.ok_reply(req.id, **st))

    def _op_wait(self, conn: _Conn, req: P.Request) -> None:
        if conn.waits >= _MAX_WAITS_PER_CLIENT:
            self._send(conn, P.error_reply(req.id, P.BUSY,
                                           f"at most {_MAX_WAITS_PER_CLIENT} outstanding 'wait' per client"))
            return
        conn.waits += 1
        timeout_s = req.fields["timeout_s"]
        daemon = self.daemon
        stop = self._stop

        with self._motion_cv:
            after = self._motion_submitted

        def job() -> None:
            deadline = time.monotonic() + timeout_s
            out: dict | None = None
            try:
                with self._motion_cv:           # motion ops received before this wait come first
                    while self._motion_done < after and not stop.is_set() and conn.alive:
                        self._motion_cv.wait(min(_WAIT_SLICE_S, max(0.0, deadline - time.monotonic())) or 0.01)
                        if time.monotonic() >= deadline:
                            break
                while True:
                    left = deadline - time.monotonic()
                    st = daemon.wait(max(0.0, min(_WAIT_SLICE_S, left)))
                    state = st.get("state") if isinstance(st, dict) else None
                    if state in _WAIT_DONE_STATES:
                        out = P.ok_reply(req.id, timed_out=False, **P.plain(st))
                        break
                    if time.monotonic() >= deadline:
                        out = P.ok_reply(req.id, timed_out=True, **P.plain(st))
                        break
                    if not conn.alive or stop.is_set():
                        return
            except Exception as exc:
                if not isinstance(exc, HexacncError):
                    log.exception("Daemon.wait failed")
                out = P.error_from_exception(exc, req.id)
            finally:
                self._results.put((conn, out, "wait-done"))
                self._wake()
        self._wait_pool.submit(job)

    def _op_subscribe(self, conn: _Conn, req: P.Request) -> None:
        if len(conn.subs) >= _MAX_SUBS_PER_CLIENT:
            self._send(conn, P.error_reply(req.id, P.BUSY,
                                           f"at most {_MAX_SUBS_PER_CLIENT} subscriptions per client"))
            return
        rate = float(req.fields.get("rate_hz", self.status_rate_hz))
        period = 1.0 / rate
        st = self._status()
        conn.subs[req.id] = [period, time.monotonic() + period, 0, 0]
        self._send(conn, P.ok_reply(req.id, sub=req.id, rate_hz=rate, **st))

    def _op_unsubscribe(self, conn: _Conn, req: P.Request) -> None:
        sub = req.fields.get("sub")
        if sub is None:
            cancelled = sorted(conn.subs)
            conn.subs.clear()
        else:
            cancelled = [sub] if conn.subs.pop(sub, None) is not None else []
        self._send(conn, P.ok_reply(req.id, cancelled=cancelled))

    # -- output ---------------------------------------------------------------
    def _deliver_results(self) -> None:
        while True:
            try:
                item = self._results.get_nowait()
            except queue.Empty:
                return
            conn, out = item[0], item[1]
            if item[2] == "wait-done":
                conn.waits -= 1
            elif item[2] == "motion-done":
                conn.motion_pending -= 1
            conn.last_active = time.monotonic()       # idle time counts from the end of a wait/op
            if out is not None and conn.alive and not conn.closing:
                self._send(conn, out)

    def _next_stream_due(self) -> float:
        due = time.monotonic() + 0.5
        for c in self._conns.values():
            for s in c.subs.values():
                if s[1] < due:
                    due = s[1]
        return due

    def _serve_streams(self) -> None:
        now = time.monotonic()
        st: dict | None = None
        err: dict | None = None
        for conn in list(self._conns.values()):
            if not conn.alive or conn.closing or not conn.subs:
                continue
            for sid, s in conn.subs.items():
                if s[1] > now:
                    continue
                s[1] += s[0]
                if s[1] <= now:
                    s[1] = now + s[0]
                if len(conn.out) > _STREAM_BACKLOG_BYTES:
                    s[3] += 1
                    self.stats["stream_dropped"] += 1
                    continue
                if st is None and err is None:
                    try:
                        st = self._status()
                    except Exception as exc:
                        err = P.error_from_exception(exc, None)["error"]
                s[2] += 1
                if st is not None:
                    msg = {"id": sid, "ok": True, "stream": "status", "seq": s[2], "dropped": s[3]}
                    msg.update(st)
                else:
                    msg = {"id": sid, "ok": False, "stream": "status", "seq": s[2], "error": err}
                self.stats["stream_sent"] += 1
                self._send(conn, msg)
                if not conn.alive:
                    break
