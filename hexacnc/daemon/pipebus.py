"""A python-can bus over a Unix ``SOCK_SEQPACKET`` socket pair: two processes, one wire.

The transport of the embedded default (simulated drives, no root, no network at all): the
supervisor makes one socket pair per CAN bus, hands one end to the simulated drives process
(:mod:`hexacnc.daemon.simhost`) and the other to the hot loop process.  Each datagram is one
frame: ``struct "<IBB" (arbitration id, flags, length)`` + data.  Nothing is echoed (the peer is
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
F_EXT = 1
F_FD = 2
F_BRS = 4
F_RTR = 8


def socket_pairs(n: int) -> list[tuple[socket.socket, socket.socket]]:
    """``n`` connected SOCK_SEQPACKET pairs (inheritable, for ``pass_fds``)."""
    out = []
    for _ in range(n):
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
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
        self._buf = bytearray(_HDR.size + 64)
        self._tx = bytearray(_HDR.size + 64)
        self._txv = memoryview(self._tx)
        self._poller = select.poll()
        self._poller.register(self._fd, select.POLLIN)
        self._closed = False
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
            self.sock.send(self._txv[:6 + n])
        except BlockingIOError:
            # the peer is not reading: wait a little, then report (never block the cycle long)
            r = select.select([], [self._fd], [], 0.0 if timeout is None else timeout)[1]
            if not r:
                raise can.CanOperationError("pipe bus: peer not reading (send buffer full)") from None
            self.sock.send(self._txv[:6 + n])
        except OSError as exc:
            raise can.CanOperationError(f"pipe bus: {exc}") from exc

    def _recv_internal(self, timeout: float | None):
        # poll first: a would-block recv raises, and exceptions cost more than the poll
        if not self._poller.poll(0 if not timeout else (-1 if timeout is None else int(timeout * 1000) or 1)):
            return None, False
        try:
            n = self.sock.recv_into(self._buf)
        except BlockingIOError:
            return None, False
        except OSError as exc:
            raise can.CanOperationError(f"pipe bus: {exc}") from exc
        if n == 0:
            if timeout:
                time.sleep(min(timeout, 0.01))   # peer gone: behave like a silent bus
            return None, False
        arb, flags, length = _HDR.unpack_from(self._buf)
        msg = can.Message(timestamp=time.time(), arbitration_id=arb, is_extended_id=bool(flags & F_EXT),
                          is_fd=bool(flags & F_FD), bitrate_switch=bool(flags & F_BRS),
                          is_remote_frame=bool(flags & F_RTR), dlc=length,
                          data=bytes(self._buf[_HDR.size:_HDR.size + length]), check=False)
        return msg, False

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
