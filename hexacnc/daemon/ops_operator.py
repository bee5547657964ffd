"""Socket ops of operator control (see docs/protocol.md), served by :class:`.server.SocketServer`.

Each handler is ``handler(server, conn, req)``; :data:`OPERATOR_OPS` maps op names to them.
Ops that move or change the machine need control (``server._take_control``) and run in order on
the motion worker; ``jog`` confirmations and stops, ``take`` and the read-only forms of
``offsets`` / ``tools`` are answered at once on the selector thread.
"""
from __future__ import annotations

import logging
from typing import Any

from . import protocol as P
from .operator import Operator

log = logging.getLogger("hexacnc.daemon.ops")


def attach_operator(daemon: Any, cfg: Any) -> Operator | None:
    """The daemon's :class:`Operator`, created on first use (None for a daemon without shared state)."""
    op = getattr(daemon, "operator", None)
    if op is None and hasattr(daemon, "sh") and hasattr(daemon, "lock"):
        op = Operator(daemon, cfg)
        daemon.operator = op
    return op


def _op(server) -> Operator:
    op = getattr(server, "operator", None)
    if op is None:
        raise P.RequestError(P.REFUSED, "this daemon has no operator functions")
    return op


def _motion(server, conn, req, call) -> None:
    if not server._take_control(conn, req):
        return

    def reply(result: Any) -> dict:
        return P.ok_reply(req.id, **(P.plain(result) if isinstance(result, dict) else {}))
    server._submit_motion(conn, req, call, reply)


def _inline(server, conn, req, call) -> None:
    try:
        out = call()
    except Exception as exc:
        server.stats["errors"] += 1
        server._send(conn, P.error_from_exception(exc, req.id, server._state_or_none(), req.op))
        return
    server._send(conn, P.ok_reply(req.id, **P.plain(out or {})))


def op_override(server, conn, req) -> None:
    f = req.fields
    if not any(k in f for k in ("feed", "rapid", "optional_stop", "block_delete")):
        op = _op(server)
        server._send(conn, P.ok_reply(req.id, feed=op.feed, rapid=op.rapid, max_feed_override=op.max_feed,
                                      optional_stop=op.optional_stop, block_delete=op.block_delete))
        return
    op = _op(server)
    _motion(server, conn, req, lambda: op.set_override(f.get("feed"), f.get("rapid"), f.get("optional_stop"),
                                                       f.get("block_delete")))


def op_enable(server, conn, req) -> None:
    _motion(server, conn, req, _op(server).enable)


def op_disable(server, conn, req) -> None:
    _motion(server, conn, req, _op(server).disable)


def op_home(server, conn, req) -> None:
    _motion(server, conn, req, _op(server).home)


def op_mdi(server, conn, req) -> None:
    op = _op(server)
    text = req.fields["text"]
    _motion(server, conn, req, lambda: op.mdi(text))


def op_pivot(server, conn, req) -> None:
    op = _op(server)
    pv = req.fields.get("pivot_mm")
    if "pivot_mm" not in req.fields:
        server._send(conn, P.ok_reply(req.id, **op.set_pivot(op.pivot_mm)))
        return
    if not server._take_control(conn, req):
        return
    _inline(server, conn, req, lambda: op.set_pivot(list(pv) or None))


def op_jog(server, conn, req) -> None:
    op = _op(server)
    f = req.fields
    action = f.get("action", "start")
    if not server._take_control(conn, req):
        return
    if action == "confirm":
        _inline(server, conn, req, op.jog_confirm)
    elif action == "stop":
        _inline(server, conn, req, op.jog_stop)
    else:
        if "axis" not in f:
            server._send(conn, P.error_reply(req.id, P.MISSING_FIELD, "op 'jog' needs field 'axis'", field="axis"))
            return
        _motion(server, conn, req, lambda: op.jog(f["axis"], f.get("frame", "base"), f.get("distance"),
                                                  f.get("direction"), float(f.get("speed", 1.0))))


def op_offsets(server, conn, req) -> None:
    op = _op(server)
    f = req.fields
    if "system" not in f and "select" not in f:
        _inline(server, conn, req, op.offsets)
        return
    values = f.get("values") or {}
    if not isinstance(values, dict):
        server._send(conn, P.error_reply(req.id, P.BAD_TYPE, "op 'offsets': values must be a map axis -> number"))
        return
    _motion(server, conn, req, lambda: op.offsets(f.get("system"), values, f.get("select")))


def op_tools(server, conn, req) -> None:
    op = _op(server)
    f = req.fields
    if "tool" not in f:
        _inline(server, conn, req, op.tools)
        return
    extra = {k: f[k] for k in ("pocket", "z_mm", "diameter_mm", "comment") if k in f}
    _motion(server, conn, req, lambda: op.tools(f["tool"], bool(f.get("delete", False)), **extra))


def op_take(server, conn, req) -> None:
    prev = server._controller
    server._controller = conn
    if prev is not None and prev is not conn:
        log.warning("%s took control from %s", conn.label(), prev.label())
        server._send(prev, {"id": None, "ok": True, "event": "control_taken", "by": conn.label(),
                            "message": f"control of the machine was taken by {conn.label()}"})
    elif prev is None:
        log.info("%s now controls motion", conn.label())
    server._send(conn, P.ok_reply(req.id, controller=conn.label(),
                                  previous=None if prev is None or prev is conn else prev.label()))


OPERATOR_OPS = {
    "override": op_override, "enable": op_enable, "disable": op_disable, "home": op_home, "mdi": op_mdi,
    "jog": op_jog, "pivot": op_pivot, "offsets": op_offsets, "tools": op_tools, "take": op_take,
}

__all__ = ["OPERATOR_OPS", "attach_operator"]
