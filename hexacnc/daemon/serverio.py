"""Connection I/O of the socket server (:class:`hexacnc.daemon.server.SocketServer`): the listening
sockets, accepting, reading and decoding (framing, batches of requests), sending, flushing, dropping.

A mixin: it uses the server's selector, connection table and stats; only the selector thread runs it.
"""
from __future__ import annotations

import logging
import os
import selectors
import socket
import stat
import threading
import time

from ..errors import HexacncError, ProtocolError
from . import protocol as P
from . import sockpath, tcpauth, tlsio

log = logging.getLogger("hexacnc.daemon.server")

#: bytes read per readiness event
_READ_CHUNK = 256 * 1024
#: a client whose unsent replies exceed this is dropped (it does not read)
_MAX_OUT_BYTES = 64 * 1024 * 1024
#: requests handled per client per loop pass (the rest waits for the next pass: fairness)
_MAX_BATCH = 64


class _Conn:
    """One client connection (touched only by the selector thread, except ``alive``)."""

    __slots__ = ("sock", "num", "kind", "peer", "dec", "out", "authenticated", "closing", "alive",
                 "subs", "waits", "motion_pending", "client_name", "registered_mask", "created", "backlog",
                 "role", "who", "last_active", "preauth_bytes", "addr")

    def __init__(self, sock: socket.socket, num: int, kind: str, peer: str, max_bytes: int):
        self.sock = sock
        self.num = num
        self.kind = kind                      # "unix" | "tcp"
        self.peer = peer
        self.dec = P.Decoder(max_bytes)
        self.out = bytearray()
        self.authenticated = kind == "unix"   # Unix socket: file permissions authenticate
        self.closing = False                  # close once ``out`` is flushed
        self.alive = True
        self.subs: dict[int, list] = {}       # sub id -> [period_s, next_due, seq, dropped]
        self.waits = 0
        self.motion_pending = 0
        self.client_name = ""
        self.created = time.monotonic()
        self.backlog = False                  # decoded data left for the next pass
        self.registered_mask = 0
        self.role: str | None = None          # access role (hexacnc.daemon.access); None before auth
        self.who = peer                       # peer uid/pid or address, for refusal logs
        self.last_active = self.created
        self.preauth_bytes = 0
        self.addr = peer.rsplit(":", 1)[0] if kind == "tcp" else ""

    def label(self) -> str:
        return f"client {self.num} ({self.kind} {self.peer}{', ' + self.client_name if self.client_name else ''})"


class ConnectionIO:
    """Binding, accepting, reading, decoding, sending and dropping client connections."""

    # -- binding ----------------------------------------------------------------
    def _bind_unix(self) -> None:
        path = self.socket_path
        sockpath.prepare_server_dir(path)        # refuses a directory others can write (or own)
        check_socket_path(path, remove_stale=True)
        # peer credentials decide who may do what; with groups configured anyone may connect (and
        # gets a role or a logged refusal), else only the owner's group can open the socket
        mode = 0o666 if self.policy.groups_configured else 0o660
        # bind under a temporary name, set 0660, then rename: no moment with wider permissions
        tmp = f"{path}.{os.getpid()}.{threading.get_ident() % 100000}.tmp"
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            if len(os.fsencode(tmp)) <= 107:
                s.bind(tmp)
                os.chmod(tmp, mode)
                os.replace(tmp, path)
            else:
                s.bind(path)
                os.chmod(path, mode)
            s.listen(64)
            s.setblocking(False)
        except OSError as exc:
            s.close()
            for p in (tmp,):
                try:
                    os.unlink(p)
                except OSError:
                    pass
            raise HexacncError(f"cannot listen on {path!r}: {exc.strerror or exc}") from exc
        self._unix = s
        self._unix_ino = os.lstat(path).st_ino
        self._sel.register(s, selectors.EVENT_READ, "listen-unix")

    def _bind_tcp(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((self.tcp_host, self.tcp_port))  # 127.0.0.1 unless TLS is on ([daemon] tcp_host)
            s.listen(64)
            s.setblocking(False)
        except OSError as exc:
            s.close()
            raise HexacncError(f"cannot listen on {self.tcp_host}:{self.tcp_port}: {exc.strerror or exc}") from exc
        self._tcp = s
        self.tcp_address = s.getsockname()[:2]
        self._sel.register(s, selectors.EVENT_READ, "listen-tcp")

    def _close_listeners(self) -> None:
        for s in (self._unix, self._tcp, self._wake_r, self._wake_w):
            if s is not None:
                try:
                    if self._sel is not None:
                        self._sel.unregister(s)
                except (KeyError, ValueError):
                    pass
                s.close()
        if self._unix is not None and self._unix_ino is not None:
            try:
                if os.lstat(self.socket_path).st_ino == self._unix_ino:
                    os.unlink(self.socket_path)
            except OSError:
                pass
        self._unix = self._tcp = self._wake_r = self._wake_w = None
        if self._sel is not None:
            self._sel.close()
            self._sel = None

    # -- reading ------------------------------------------------------------------
    def _wake(self) -> None:
        w = self._wake_w
        if w is not None:
            try:
                w.send(b"\0")
            except OSError:
                pass

    def _register(self, s: socket.socket, kind: str, peer: str) -> _Conn:
        conn = _Conn(s, self._next_num, kind, peer, self.max_message_bytes)
        self._next_num += 1
        self._conns[conn.num] = conn
        conn.registered_mask = selectors.EVENT_READ
        self._sel.register(s, selectors.EVENT_READ, conn)
        self.stats["accepted"] += 1
        log.debug("%s connected", conn.label())
        return conn

    def _accept(self, lsock: socket.socket, kind: str) -> None:
        # few TCP accepts per pass: a flood of new connections cannot push a fresh one out of the
        # pre-auth pool before the loop has read its hello
        for _ in range(16 if kind == "unix" else 4):
            try:
                s, addr = lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("accept failed: %s", exc)
                return
            s.setblocking(False)
            if kind == "tcp":
                self._admit_tcp(s, f"{addr[0]}:{addr[1]}")
            else:
                self._admit_unix(s)

    def _on_readable(self, conn: _Conn) -> None:
        want = _READ_CHUNK if conn.authenticated else tcpauth.PREAUTH_MAX_BYTES - conn.preauth_bytes
        if want <= 0:
            return
        try:
            data = tlsio.recv(conn.sock, want)      # plain or TLS; None: nothing there now
        except OSError as exc:
            if not conn.authenticated:            # e.g. a failed TLS handshake: a refusal, logged
                self._log_refusal(conn.who, "connect", f"receive failed: {exc}")
            self._drop(conn, f"receive failed: {exc}")
            return
        if data is None:
            return
        if not data:
            self._drop(conn, "disconnected")
            return
        if conn.closing:
            return                         # ignore anything after a fatal error
        conn.last_active = time.monotonic()
        if not conn.authenticated:
            conn.preauth_bytes += len(data)
        try:
            conn.dec.feed(data)
        except ProtocolError as exc:
            self._bad_stream(conn, exc)
            return
        self._process(conn)
        if (conn.alive and not conn.closing and not conn.authenticated
                and conn.preauth_bytes >= tcpauth.PREAUTH_MAX_BYTES):
            self.stats["preauth_closed"] += 1
            self._refuse_conn(conn, "hello", f"more than {tcpauth.PREAUTH_MAX_BYTES} bytes before "
                                             f"authentication", code=P.TOO_LARGE)

    def _process(self, conn: _Conn) -> None:
        """Handle up to _MAX_BATCH decoded requests; flag the connection if more are buffered."""
        conn.backlog = False
        n = 0
        try:
            for msg in conn.dec.messages():
                self._handle(conn, msg)
                n += 1
                if conn.closing or not conn.alive:
                    return
                if n >= _MAX_BATCH:
                    conn.backlog = True
                    return
        except ProtocolError as exc:
            self._bad_stream(conn, exc)

    def _bad_stream(self, conn: _Conn, exc: ProtocolError) -> None:
        self.stats["closed_bad"] += 1
        log.warning("%s: %s; closing the connection", conn.label(), exc)
        if conn.dec.too_large:
            self._send(conn, P.error_reply(None, P.TOO_LARGE, f"{exc} ([daemon] max_message_bytes): send a larger "
                                           "program in chunks with program_begin / program_chunk / program_end "
                                           "(hexacnc send does so for files over --chunk-bytes)"))
            conn.closing = True
            self._flush(conn)
        else:
            self._drop(conn, "undecodable message")

    # -- output ---------------------------------------------------------------
    def _send(self, conn: _Conn, msg: dict) -> None:
        if not conn.alive:
            return
        conn.out += P.encode(msg)
        if len(conn.out) > _MAX_OUT_BYTES:
            self._drop(conn, f"does not read its replies ({len(conn.out)} bytes unsent)")
            return
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        while conn.out:
            try:
                n = tlsio.send(conn.sock, conn.out)   # plain or TLS; 0: cannot take more now
            except OSError as exc:
                self._drop(conn, f"send failed: {exc}")
                return
            if not n:
                break
            del conn.out[:n]
        if not conn.out and conn.closing:
            self._drop(conn, "closed after a fatal error")
            return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.out else 0)
        if want != conn.registered_mask and conn.alive:
            self._sel.modify(conn.sock, want, conn)
            conn.registered_mask = want

    def _drop(self, conn: _Conn, why: str) -> None:
        if not conn.alive:
            return
        conn.alive = False
        conn.subs.clear()
        self._uploads.drop(conn.num)            # a disconnect drops the connection's open upload
        self._conns.pop(conn.num, None)
        self._preauth.pop(conn.num, None)
        try:
            if self._sel is not None:
                self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        try:
            conn.sock.close()
        except OSError:
            pass
        if self._controller is conn:
            self._controller = None
            log.info("%s gave up control (%s)", conn.label(), why)
        log.debug("%s: %s", conn.label(), why)


def check_socket_path(path: str, remove_stale: bool = False) -> None:
    """Raise HexacncError if ``path`` cannot be served: too long, no directory, not a socket, or
    another daemon answers on it.  A stale socket file (nobody listening) is removed when
    ``remove_stale``.  ``hexacnc run`` may call this before booting the drives."""
    if len(os.fsencode(path)) > 100:
        raise HexacncError(f"socket path {path!r} is too long for a Unix socket (max 100 bytes)")
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise HexacncError(f"socket path {path!r}: directory {d} does not exist")
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise HexacncError(f"socket path {path!r} exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(path)
    except (ConnectionRefusedError, FileNotFoundError):
        if remove_stale:
            log.info("removing stale socket %s", path)
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass
        return
    except OSError as exc:
        raise HexacncError(f"socket path {path!r} exists and cannot be checked: {exc.strerror or exc}") from exc
    finally:
        probe.close()
    raise HexacncError(f"another daemon is serving {path!r}; stop it or choose another "
                       f"--socket / [daemon] socket_path")
