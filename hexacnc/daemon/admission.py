"""Admission to the daemon's socket: who gets a connection, which ops it may send, when it is closed.

A mixin of :class:`hexacnc.daemon.server.SocketServer` (it uses the server's connection table,
``_register``, ``_send`` and ``_flush``); the policies live in :mod:`.access` (peer credentials,
roles) and :mod:`.tcpauth` (token, pre-auth limits, per-address back-off).  Every refusal is
logged with who (peer uid/pid or address), which op and why, at most 20 lines a second (the rest
are counted in the next line).
"""
from __future__ import annotations

import logging
import socket
import time
from typing import Any

from ..errors import HexacncError
from . import access as A
from . import protocol as P
from . import tcpauth, tlsio

log = logging.getLogger("hexacnc.daemon.server")


def tcp_secret(cfg: Any, override: str | None = None) -> str:
    """The TCP token (``override``, ``[daemon] token_file`` or legacy ``tcp_token``); raises
    HexacncError for a weak token or a file that lets others read it (the config file, for the
    legacy key)."""
    dcfg = cfg.daemon
    if override is None and getattr(dcfg, "tcp_token", "") and not getattr(dcfg, "token_file", ""):
        leak = tcpauth.config_file_leaks(getattr(cfg, "path", None))
        if leak:
            raise HexacncError(leak)
    return tcpauth.resolve_token(dcfg, override)


def preflight(cfg: Any, socket_path: str | None = None) -> str:
    """What the socket server would refuse, checked before ``hexacnc run`` boots the drives: the
    socket's directory (created 0700 at a default place), the TCP token, the TLS files, the
    [daemon] groups.  Returns the socket path."""
    from . import sockpath
    dcfg = cfg.daemon
    path = sockpath.server_socket_path(dcfg, socket_path)
    sockpath.prepare_server_dir(path)
    A.AccessPolicy.from_config(dcfg)
    if dcfg.tcp_port:
        tcp_secret(cfg)
        if getattr(dcfg, "tls_cert", ""):
            tlsio.server_context(dcfg.tls_cert, dcfg.tls_key)
    return path


class Admission:
    """Admission, authentication, refusals and time-outs of the socket server's connections."""

    def _init_admission(self, cfg: Any, tcp_token: str | None) -> None:
        dcfg = cfg.daemon
        self.tcp_token = ""
        self._token_digest = b""
        if self.tcp_port:
            self.tcp_token = tcp_secret(cfg, tcp_token)     # refuses weak tokens, leaky files
            self._token_digest = tcpauth.secret_digest(self.tcp_token)
        self.policy = A.AccessPolicy.from_config(dcfg)
        self.idle_timeout_s = float(getattr(dcfg, "idle_timeout_s", 600.0))
        self.max_unauthenticated = int(getattr(dcfg, "max_unauthenticated", 16))
        self._limiter = tcpauth.FailureLimiter()
        self._log_gate = tcpauth.LogThrottle()
        self._tls_ctx = None
        if self.tcp_port and getattr(dcfg, "tls_cert", ""):
            self._tls_ctx = tlsio.server_context(dcfg.tls_cert, dcfg.tls_key)
        self.tcp_host = str(getattr(dcfg, "tcp_host", "127.0.0.1") or "127.0.0.1")
        self._preauth: dict = {}              # TCP connections before hello, oldest first
        self._idle_checked = 0.0

    def _expire_connections(self) -> None:
        """Close TCP connections not authenticated within ``auth_timeout_s`` and connections idle
        for ``[daemon] idle_timeout_s`` (a running wait, subscription or motion op keeps one open)."""
        now = time.monotonic()
        for conn in list(self._preauth.values()):
            if not conn.closing and now - conn.created > self.auth_timeout_s:
                self.stats["preauth_closed"] += 1
                self._refuse_conn(conn, "hello", f"no 'hello' with 'token' within {self.auth_timeout_s:g} s")
        if now - getattr(self, "_idle_checked", 0.0) < 0.25:
            return
        self._idle_checked = now
        limit = self.idle_timeout_s
        for conn in list(self._conns.values()):
            if (conn.authenticated and not conn.closing and not conn.subs and not conn.waits
                    and not conn.motion_pending and now - conn.last_active > limit):
                self.stats["idle_closed"] += 1
                log.info("%s: idle for %.0f s ([daemon] idle_timeout_s %g); closing", conn.label(),
                         now - conn.last_active, limit)
                self._send(conn, P.error_reply(None, P.REFUSED, f"idle for more than {limit:g} s "
                                                                f"([daemon] idle_timeout_s); closing"))
                conn.closing = True
                self._flush(conn)

    # -- admission and refusals (policy in hexacnc.daemon.access / tcpauth) ----
    def _log_refusal(self, who: str, op: str, why: str) -> None:
        ok, hidden = self._log_gate.allow()
        if ok:
            A.log_refusal(who, op, why + (f" (and {hidden} similar refusals not logged)" if hidden else ""))

    def _refuse_socket(self, s: socket.socket, who: str, op: str, why: str, plain: bool = True,
                       **extra: Any) -> None:
        """Refuse a connection before it is registered: the reason sent (best effort; not to a
        TLS client, which expects a handshake), logged first (a client that reads the refusal finds it in the
        log), closed."""
        self.stats["refused"] += 1
        self._log_refusal(who, op, why)
        try:
            if plain:
                s.send(P.encode(P.error_reply(None, P.UNAUTHORIZED, why, **extra)))
        except OSError:
            pass
        s.close()

    def _refuse_conn(self, conn: Any, op: str, why: str, req_id: int | None = None,
                     code: str = P.UNAUTHORIZED, **extra: Any) -> None:
        """Refuse ``op`` of a registered connection and close it once the reply is out."""
        self._log_refusal(conn.who, op, why)
        self._preauth.pop(conn.num, None)
        self._send(conn, P.error_reply(req_id, code, why, **extra))
        conn.closing = True
        self._flush(conn)
        if not conn.authenticated:        # never lingers: the reply is best effort
            self._drop(conn, why)

    def _slots_used(self) -> int:
        return len(self._conns) - len(self._preauth)

    def _admit_unix(self, s: socket.socket) -> None:
        try:
            peer = A.unix_peer(s)
        except OSError as exc:
            log.warning("refused a unix client: no peer credentials (%s)", exc)
            s.close()
            return
        role, why = self.policy.role_for(peer)
        if role is None:
            self.stats["refused_peer"] += 1
            self._refuse_socket(s, peer.describe(), "connect", why)
            return
        if self._slots_used() >= self.max_clients:
            self._refuse_busy(s, "unix")
            return
        conn = self._register(s, "unix", f"uid {peer.uid} pid {peer.pid}")
        conn.role = role
        conn.who = peer.describe()

    def _admit_tcp(self, s: socket.socket, peer: str) -> None:
        addr = peer.rsplit(":", 1)[0]
        wait = self._limiter.retry_after(addr)
        if wait > 0:
            self.stats["auth_throttled"] += 1
            self._refuse_socket(s, f"tcp {peer}", "connect", f"too many failed authentications from {addr}: "
                                f"retry in {wait:.1f} s", plain=self._tls_ctx is None, retry_after_s=round(wait, 3))
            return
        if len(self._preauth) >= self.max_unauthenticated:
            oldest = next(iter(self._preauth.values()))
            self.stats["preauth_closed"] += 1
            self._refuse_conn(oldest, "hello", f"{self.max_unauthenticated} connections are waiting to "
                                               f"authenticate ([daemon] max_unauthenticated): the oldest is closed")
        try:
            s = tlsio.wrap_server(s, self._tls_ctx)
        except (OSError, ValueError) as exc:
            s.close()
            self._log_refusal(f"tcp {peer}", "connect", f"TLS set-up failed: {exc}")
            return
        conn = self._register(s, "tcp", peer)
        conn.who = f"tcp {peer}"
        self._preauth[conn.num] = conn

    def _refuse_busy(self, s: socket.socket, kind: str) -> None:
        self.stats["refused"] += 1
        try:
            s.send(P.encode(P.error_reply(None, P.BUSY, f"too many clients (max {self.max_clients})")))
        except OSError:
            pass
        s.close()
        log.warning("refused a %s client: %d clients connected", kind, self.max_clients)

    def _authenticate(self, conn: Any, req: P.Request) -> bool:
        """First message of a TCP client: ``hello`` with the token (rate-limited per address)."""
        wait = self._limiter.retry_after(conn.addr)
        if wait > 0:
            self.stats["auth_throttled"] += 1
            self._refuse_conn(conn, req.op, f"too many failed authentications from {conn.addr}: retry in "
                                            f"{wait:.1f} s", req.id, retry_after_s=round(wait, 3))
            return False
        token = req.fields.get("token")
        if req.op != "hello" or token is None:
            self.stats["errors"] += 1
            self._refuse_conn(conn, req.op, "TCP clients must first send 'hello' with the right 'token'", req.id)
            return False
        if not tcpauth.token_matches(token, self._token_digest):
            self.stats["auth_failed"] += 1
            delay = self._limiter.failed(conn.addr)
            self._refuse_conn(conn, "hello", f"wrong token; next attempt from {conn.addr} in {delay:.1f} s",
                              req.id)
            return False
        self._limiter.succeeded(conn.addr)
        self._preauth.pop(conn.num, None)
        if self._slots_used() > self.max_clients:
            self.stats["refused"] += 1
            self._refuse_conn(conn, "hello", f"too many clients (max {self.max_clients})", req.id, P.BUSY)
            return False
        conn.authenticated = True
        conn.role = self.policy.tcp_role
        log.info("%s authenticated (role %s)", conn.label(), conn.role)
        return True

