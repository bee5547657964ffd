"""Optional TLS for the daemon's TCP socket, and the non-blocking reads/writes the server uses
for plain and TLS sockets alike.

TLS is on when ``[daemon] tls_cert`` and ``tls_key`` are set (PEM files; the key readable by the
daemon's user only).  It is what lets ``[daemon] tcp_host`` be other than loopback: a client off
the host then checks the daemon's certificate (``hexacnc send/status --tls-ca FILE``), the token
stays secret on the wire, and the token rules (2 s, 1 KiB, per-address back-off) apply as
without TLS.  The handshake happens inside the first reads, under the same 2 s limit.
"""
from __future__ import annotations

import os
import socket
import ssl
import stat

from ..errors import HexacncError

_WOULD_BLOCK = (BlockingIOError, InterruptedError, ssl.SSLWantReadError, ssl.SSLWantWriteError)


def server_context(cert: str, key: str) -> ssl.SSLContext:
    """A TLS >= 1.2 server context from PEM files; refuses a key file others may read."""
    for what, path in (("tls_cert", cert), ("tls_key", key)):
        if not os.path.isfile(path):
            raise HexacncError(f"[daemon] {what} {path}: no such file")
    st = os.stat(key)
    if st.st_mode & 0o077 or st.st_uid not in (os.geteuid(), 0):
        raise HexacncError(f"[daemon] tls_key {key}: mode {stat.S_IMODE(st.st_mode):04o}, owner uid "
                           f"{st.st_uid}: the private key must belong to the daemon's user (or root) and "
                           f"be readable by nobody else (chmod 600)")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (ssl.SSLError, OSError) as exc:
        raise HexacncError(f"[daemon] tls_cert/tls_key {cert}, {key}: {exc}") from None
    return ctx


def client_context(cafile: str) -> ssl.SSLContext:
    """A client context that trusts ``cafile`` (the daemon's certificate or its CA)."""
    try:
        return ssl.create_default_context(cafile=cafile)
    except (ssl.SSLError, OSError) as exc:
        raise HexacncError(f"--tls-ca {cafile}: {exc}") from None


def wrap_server(sock: socket.socket, ctx: ssl.SSLContext | None) -> socket.socket:
    """The accepted ``sock`` as a non-blocking TLS server socket (handshake on the first reads)."""
    if ctx is None:
        return sock
    return ctx.wrap_socket(sock, server_side=True, do_handshake_on_connect=False)


def recv(sock: socket.socket, n: int) -> bytes | None:
    """Up to ``n`` bytes, b"" at end of stream, None when nothing is there now.  A TLS socket's
    decrypted bytes already buffered are read too (no readiness event would announce them)."""
    try:
        data = sock.recv(n)
    except _WOULD_BLOCK:
        return None
    if data and isinstance(sock, ssl.SSLSocket):
        while len(data) < n and sock.pending():
            try:
                more = sock.recv(min(n - len(data), sock.pending()))
            except _WOULD_BLOCK:
                break
            if not more:
                break
            data += more
    return data


def send(sock: socket.socket, data: bytes | bytearray) -> int:
    """Bytes sent (0 when the socket cannot take any now)."""
    try:
        return sock.send(data)
    except _WOULD_BLOCK:
        return 0


__all__ = ["server_context", "client_context", "wrap_server", "recv", "send"]
