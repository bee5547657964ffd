"""A python-can bus over a Unix stream socket pair: two processes, one wire.

The transport of the embedded default (simulated drives, no root, no network at all): the
supervisor makes one socket pair per CAN bus, hands one end to the simulated drives process
(:mod:`hexacnc.daemon.simhost`) and the other to the hot loop process.  Each datagram is one
frame is one fixed 72-byte record (:mod:`drivers.framerec`: ``struct "<IBB" (arbitration id, flags,
length)`` + 64 data bytes; a stream socket, because datagram queues are capped by
``net.unix.max_dgram_qlen``, often 10).  Nothing is echoed (the peer is the only other station),
nothing leaves the machine, and a send is one ``send(2)`` call - much cheaper than udp_multicast
(msgpack, echo of every own frame).  The master and the simulated drives use it as a python-can
bus; the hot loop's codec (:class:`drivers.cyclic.CyclicIO`) uses the batch interface of
:mod:`drivers.framerec` instead: all frames of a cycle in one ``send(2)`` per bus and one
``recv(2)`` per bus for everything that arrived, decoded in place without ``can.Message`` objects.
"""
from __future__ import annotations

import os
import select
import socket
import time

import can

from drivers import framerec
from drivers.framerec import F_BRS, F_EXT, F_FD, F_RTR  # noqa: F401  (re-exported)

_HDR = framerec.HEADER
REC = framerec.RECORD      #: bytes per frame record


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
    """python-can bus on one end (a file descriptor) of a :func:`socket_pairs` pair.

    ``poll_interval_s`` > 0: a blocking receive looks for data every ``poll_interval_s`` instead of
    sleeping in ``poll(2)`` until the peer writes.  The simulated drives use it: a write that has to
    wake a process sleeping on the socket costs the *writer* the cross-CPU wake-up (about 20 us in
    a VM), paid by the hot loop on every cycle; real drives on a CAN controller wake nobody on the
    hot loop's CPU.  The price is up to ``poll_interval_s`` of extra reaction time at the receiver.
    """

    def __init__(self, channel=None, fd: int | None = None, poll_interval_s: float = 0.0, **kwargs):
        if fd is None:
            fd = int(channel)
        self.poll_interval_s = float(poll_interval_s)
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

    frame_records = True       #: offers send_records / drain_records (drivers.framerec)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        data = msg.data
        framerec.encode(self._tx, 0, msg.arbitration_id, data if data is not None else b"",
                        is_extended_id=msg.is_extended_id, is_fd=msg.is_fd,
                        bitrate_switch=msg.bitrate_switch, is_remote_frame=msg.is_remote_frame)
        self.send_records(self._txv)

    def send_records(self, view) -> int:
        """Write whole records (``len(view)`` a multiple of :data:`REC`) with one ``send(2)``.

        Never blocks for long: when the peer's receive buffer (1 MiB) is full, the record being
        written is finished (the stream must stay aligned) and the records after it are lost for the
        peer, like a receiver overrun; returns how many were lost (also counted in ``dropped``).
        Raises ``can.CanOperationError`` when the socket failed.
        """
        n = len(view)
        try:
            k = self.sock.send(view)
        except BlockingIOError:
            k = 0
        except OSError as exc:
            raise can.CanOperationError(f"pipe bus: {exc}") from exc
        if k == n:
            return 0
        part = k % REC
        if part:                                # finish the record cut in the middle
            rest = view[k:k - part + REC]
            while len(rest):
                select.select([], [self._fd], [], 0.01)
                try:
                    rest = rest[self.sock.send(rest):]
                except BlockingIOError:
                    pass
                except OSError as exc:
                    raise can.CanOperationError(f"pipe bus: {exc}") from exc
            k += REC - part
        lost = (n - k) // REC
        self.dropped += lost
        return lost

    def drain_records(self, max_records: int = 256):
        """Non-blocking: read what arrived; returns ``(buf, start, end)`` with the whole records
        ``buf[start:end]`` (at most ``max_records``), consumed by this call and valid until the
        next receive call.  ``start == end``: nothing new (also when the peer has gone)."""
        pos = self._pos
        have = self._have
        if pos:
            rest = have - pos
            if rest:
                self._buf[:rest] = self._buf[pos:have]
            have = rest
            pos = 0
        buf = self._buf
        if have < len(buf):
            try:
                have += self.sock.recv_into(self._bufv[have:])
            except BlockingIOError:
                pass
            except OSError as exc:
                self._have = have
                self._pos = 0
                raise can.CanOperationError(f"pipe bus: {exc}") from exc
        end = (have // REC) * REC
        if end > max_records * REC:
            end = max_records * REC
        self._have = have
        self._pos = end
        return buf, 0, end

    def _fill(self, timeout: float | None) -> bool:
        """Read more bytes; False if none arrived within ``timeout``."""
        if self._pos:
            rest = self._have - self._pos
            self._buf[:rest] = self._buf[self._pos:self._have]
            self._have = rest
            self._pos = 0
        if self.poll_interval_s > 0.0 and timeout != 0.0:
            return self._fill_polling(timeout)
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

    def _fill_polling(self, timeout: float | None) -> bool:
        """:meth:`_fill` by non-blocking reads every ``poll_interval_s`` (see the class doc)."""
        t_end = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                n = self.sock.recv_into(self._bufv[self._have:])
            except BlockingIOError:
                n = -1
            except OSError as exc:
                raise can.CanOperationError(f"pipe bus: {exc}") from exc
            if n > 0:
                self._have += n
                return True
            if n == 0:                                   # peer gone: behave like a silent bus
                time.sleep(min(timeout, 0.01) if timeout else 0.01)
                return False
            if t_end is not None and time.monotonic() >= t_end:
                return False
            time.sleep(self.poll_interval_s)

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
