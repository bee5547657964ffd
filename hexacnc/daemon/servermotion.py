"""Motion ops of the socket server (:class:`hexacnc.daemon.server.SocketServer`): control of the
machine (one controlling connection), motion ops run in order on one worker thread (stop, pause,
resume and reset on their own so they never wait behind a program being planned), temperatures.

A mixin: it uses the server's pools, condition and result queue and :class:`.serverio.ConnectionIO`.
"""
from __future__ import annotations

import logging
from typing import Any, Callable

from ..errors import HexacncError
from . import protocol as P
from .serverio import _Conn

log = logging.getLogger("hexacnc.daemon.server")

#: motion ops queued but not done, per client
_MAX_MOTION_PENDING = 64


class MotionOps:
    """``program``, ``pause``/``resume``/``stop``/``reset``, ``temperatures``, ``release``."""

    _stop_epoch = 0     #: stops received (socket thread), see :meth:`_unless_stopped`

    def _take_control(self, conn: _Conn, req: P.Request) -> bool:
        if self._controller is None:
            self._controller = conn
            log.info("%s now controls motion", conn.label())
            return True
        if self._controller is conn:
            return True
        self.stats["errors"] += 1
        self._send(conn, P.error_reply(req.id, P.NOT_CONTROLLER,
                                       f"op {req.op!r}: {self._controller.label()} controls the machine; "
                                       f"this connection may only observe until it disconnects or "
                                       f"takes control ('take'; hexacnc ... --take)"))
        return False

    def _submit_motion(self, conn: _Conn, req: P.Request, call: Callable[[], Any],
                       reply: Callable[[Any], dict]) -> None:
        if conn.motion_pending >= _MAX_MOTION_PENDING:
            self._send(conn, P.error_reply(req.id, P.BUSY, f"more than {_MAX_MOTION_PENDING} motion ops "
                                                           f"of this client are still being executed"))
            return
        conn.motion_pending += 1

        def job() -> None:
            out: dict
            try:
                result = call()
                out = reply(result)
            except Exception as exc:
                if not isinstance(exc, HexacncError):
                    log.exception("Daemon call for op %s failed", req.op)
                out = P.error_from_exception(exc, req.id, self._state_or_none(), req.op)
            finally:
                with self._motion_cv:
                    self._motion_done += 1
                    self._motion_cv.notify_all()
            self._results.put((conn, out, "motion-done"))
            self._wake()
        with self._motion_cv:
            self._motion_submitted += 1
        # disable too: machine off never waits behind a motion op (e.g. a running CiA 402 home)
        # and override: a feed change acts within REWIND_LEAD_S, not after a program being planned
        control = req.op in ("stop", "pause", "resume", "reset", "disable", "override") \
            and getattr(self, "_control_pool", None)
        (self._control_pool if control else self._motion_pool).submit(job)

    def _op_program(self, conn: _Conn, req: P.Request) -> None:
        if not self._take_control(conn, req):
            return
        text, name = req.fields["text"], req.fields["name"]

        def reply(result: Any) -> dict:
            info = P.plain(result) if isinstance(result, dict) else {"blocks": result}
            info.setdefault("name", name)
            return P.ok_reply(req.id, **info)
        load = self._program_loader()
        self._submit_motion(conn, req, self._unless_stopped(lambda stops: load(text, name, stops), name), reply)

    def _program_loader(self) -> Callable[[Any, str, Any], Any]:
        """``load(text or chunks, name, stops)``: the operator's (persistent state) or the daemon's
        ``load_program``; one that takes no ``stops`` (a test double) gets the text joined."""
        import inspect

        from .progtext import joined
        load = self.operator.load_program if getattr(self, "operator", None) is not None else self.daemon.load_program
        try:
            takes = "stops" in inspect.signature(load).parameters
        except (TypeError, ValueError):
            takes = False
        if takes:
            return lambda text, name, stops: load(text, name, stops=stops)
        return lambda text, name, stops: load(joined(text), name)

    def _unless_stopped(self, load: Callable[[], Any], name: str) -> Callable[[], Any]:
        """``load(stops)`` for the motion worker, unless a ``stop`` arrived after the program (stop runs on
        its own worker and can overtake it): refused if the stop came before planning began, and
        stopped again if it came while planning began.  ``stops``: the daemon's count of stops taken
        before this check, so that a stop that comes while the program is still being prepared (a large
        text scanned, its planning children started) aborts it as soon as it is planned or queued."""
        epoch = self._stop_epoch

        def call() -> Any:
            stops = getattr(self.daemon, "_stops", None)
            if self._stop_epoch != epoch:
                raise HexacncError(f"{name}: stopped before it was interpreted and planned")
            result = load(stops)
            if self._stop_epoch != epoch:
                self.daemon.stop()
                raise HexacncError(f"{name}: stopped while it was being interpreted and planned")
            return result
        return call

    def _simple_motion(self, conn: _Conn, req: P.Request) -> None:
        if not self._take_control(conn, req):
            return
        fn = getattr(self.daemon, req.op)

        def reply(result: Any) -> dict:
            extra = P.plain(result) if isinstance(result, dict) else {}
            return P.ok_reply(req.id, **extra)
        self._submit_motion(conn, req, fn, reply)

    def _op_stop(self, conn: _Conn, req: P.Request) -> None:
        if self._controller in (None, conn):
            self._stop_epoch += 1           # on arrival: programs received before it never start
        self._simple_motion(conn, req)

    _op_pause = _op_resume = _op_reset = _simple_motion

    def _op_temperatures(self, conn: _Conn, req: P.Request) -> None:
        """A probe reading for the thermal observer (controller or sensor role; validated as a whole, applied or not at all)."""
        push = getattr(self.daemon, "push_temperatures", None)
        if push is None:
            self._send(conn, P.error_reply(req.id, P.REFUSED, "this daemon takes no temperatures"))
            return
        try:
            info = push(dict(req.fields))
        except HexacncError as exc:
            code = getattr(exc, "code", None)
            field = getattr(exc, "field", None)
            self.stats["errors"] += 1
            self._send(conn, P.error_reply(req.id, code if code in P.ERROR_CODES else P.REFUSED, str(exc),
                                           **({"field": field} if field else {})))
            return
        self._send(conn, P.ok_reply(req.id, **P.plain(info or {})))

    def _op_release(self, conn: _Conn, req: P.Request) -> None:
        was = self._controller is conn
        if was:
            self._controller = None
            log.info("%s released control", conn.label())
        self._send(conn, P.ok_reply(req.id, released=was))
