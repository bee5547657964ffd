"""A python-can bus over a Unix stream socket pair: two processes, one wire.

The transport of the embedded default (simulated drives, no root, no network at all): the
supervisor makes one socket pair per CAN bus, hands one end to the simulated drives process
(:mod:`hexacnc.daemon.simhost`) and the other to the hot loop process.  Each datagram is one
frame is one fixed 72-byte record: ``struct "<IBB" (arbitration id, flags, length)`` + 64 data
bytes (a stream socket, because datagram queues are capped by ``net.unix.max_dgram_qlen``, often 10).  Nothing is echoed (the peer is
the only other station), nothing leaves the machine, and a send is one ``send(2)`` call - much
cheaper than udp_multicast (msgpack, echo of every own frame).  The master, the cyclic codec and
the simulated drives run unchanged on it: the same code path as SocketCAN and udp_multicast.
"""
from __future__ import annotations

import os
import select
import socket
import struct
import time

import can

_HDR = struct.Struct("<IBB")
REC = 72                   #: bytes per frame record
F_EXT = 1
F_FD = 2
F_BRS = 4
F_RTR = 8


def socket_pairs(n: int) -> list[tuple[socket.socket, socket.socket]]:
    """``n`` connected stream socket pairs (inheritable, for ``pass_fds``)."""
    out = []
    for _ in range(n):
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for s in (a, b):
            s.set_inheritable(True)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        out.append((a, b))
    return out


class PipeBus(can.BusABC):
    """python-can bus on one end (a file descriptor) of a :func:`socket_pairs` pair."""

    def __init__(self, channel=None, fd: int | None = None, **kwargs):
        if fd is None:
            fd = int(channel)
        self.sock = socket.socket(fileno=fd)
        self.sock.setblocking(False)
        self._fd = self.sock.fileno()
        self.channel_info = f"pipe fd {fd}"
        self._buf = bytearray(REC * 256)
        self._bufv = memoryview(self._buf)
        self._have = 0             # bytes in _buf
        self._pos = 0              # next record
        self._tx = bytearray(REC)
        self._txv = memoryview(self._tx)
        self._poller = select.poll()
        self._poller.register(self._fd, select.POLLIN)
        self._closed = False
        self.dropped = 0           #: frames lost because the peer's receive queue was full
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        flags = ((F_EXT if msg.is_extended_id else 0) | (F_FD if msg.is_fd else 0)
                 | (F_BRS if msg.bitrate_switch else 0) | (F_RTR if msg.is_remote_frame else 0))
        data = msg.data
        n = len(data) if data is not None else 0
        tx = self._tx
        _HDR.pack_into(tx, 0, msg.arbitration_id, flags, n)
        if n:
            tx[6:6 + n] = data
        try:
            k = self.sock.send(self._txv)
            if k != REC:                       # buffer (1 MiB) nearly full: finish the record
                self.dropped += 1
                view = self._txv[k:]
                while len(view):
                    select.select([], [self._fd], [], 0.01)
                    try:
                        view = view[self.sock.send(view):]
                    except BlockingIOError:
                        pass
        except BlockingIOError:
            # the peer's buffer is full: like a receiver overrun, the frame is lost for that
            # station (counted); the sender is never blocked
            self.dropped += 1
        except OSError as exc:
            raise can.CanOperationError(f"pipe bus: {exc}") from exc

    def _fill(self, timeout: float | None) -> bool:
        """Read more bytes; False if none arrived within ``timeout``."""
        if self._pos:
            rest = self._have - self._pos
            self._buf[:rest] = self._buf[self._pos:self._have]
            self._have = rest
            self._pos = 0
        if not self._poller.poll(0 if not timeout else (-1 if timeout is None else int(timeout * 1000) or 1)):
            return False
        try:
            n = self.sock.recv_into(self._bufv[self._have:])
        except BlockingIOError:
            return False
        except OSError as exc:
            raise can.CanOperationError(f"pipe bus: {exc}") from exc
        if n == 0:
            if timeout:
                time.sleep(min(timeout, 0.01))   # peer gone: behave like a silent bus
            return False
        self._have += n
        return True

    def _recv_internal(self, timeout: float | None):
        if self._have - self._pos < REC:
            if not self._fill(timeout):
                return None, False
            if self._have - self._pos < REC:   # a record split across reads: wait for its rest
                if not self._fill(0.01):
                    return None, False
                if self._have - self._pos < REC:
                    return None, False
        p = self._pos
        arb, flags, length = _HDR.unpack_from(self._buf, p)
        msg = can.Message(timestamp=time.time(), arbitration_id=arb, is_extended_id=bool(flags & F_EXT),
                          is_fd=bool(flags & F_FD), bitrate_switch=bool(flags & F_BRS),
                          is_remote_frame=bool(flags & F_RTR), dlc=length,
                          data=bytes(self._buf[p + _HDR.size:p + _HDR.size + length]), check=False)
        self._pos = p + REC
        return msg, False

    def recv(self, timeout: float | None = None):
        """One frame or None; python-can's generic loop skipped (this bus has no filters)."""
        if not self._filters and (timeout == 0.0 or self._have - self._pos >= REC):
            return self._recv_internal(timeout)[0]
        return super().recv(timeout)

    def fileno(self) -> int:
        return self._fd

    def shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        super().shutdown()
        try:
            self.sock.close()
        except OSError:
            pass


def close_fds(fds) -> None:
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass
