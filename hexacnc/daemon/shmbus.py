"""A python-can bus over a shared-memory frame ring: two processes, one wire, no syscall per frame.

The transport of the embedded default (``[bus] simulate`` with ``interface = "virtual"``): the
supervisor creates one segment per CAN bus (:func:`create_segments`), the hot loop process
attaches side ``0``, the simulated drives process side ``1``.  A segment holds two single-producer
single-consumer rings of :mod:`drivers.framerec` records (the same 72-byte records, hence the
same CAN frames, as the pipe bus), one per direction::

    [magic, records, creator pid][w 0->1][r 0->1][w 1->0][r 1->0]   (int64 each, on their own 64-byte line)
    [ring 0->1: N records][ring 1->0: N records]

Indices count records and only grow; record ``k`` lives in slot ``k % N``.  The producer copies
the records, then publishes its write index; the consumer reads up to the published index, then
publishes its read index (aligned 8-byte stores are atomic on x86-64 and not reordered with
other stores, so a published record is always complete).

The hot loop never makes a system call here: :meth:`ShmBus.send_records` is a copy into the ring
and :meth:`ShmBus.drain_records` hands out a view of the ring itself (zero copy).  The simulated
drives look for frames every ``poll_interval_s`` (a timed sleep on their own CPU), like a CAN
controller that nobody has to wake.  A full ring drops the records that do not fit (counted in
``dropped``, like a receiver overrun); the sender never blocks.
"""
from __future__ import annotations

import os
import threading
import time
from multiprocessing import shared_memory

import can

from drivers import framerec
from drivers.framerec import F_BRS, F_EXT, F_FD, F_RTR

_HDR = framerec.HEADER
REC = framerec.RECORD
MAGIC = 0x48584342555331            #: "HXCBUS1"
RING_RECORDS = 4096                 #: records per direction: ~400 ms of the default layout's traffic
_LINE = 64
_OFF_DATA = 5 * _LINE
# int64 slot indices (8 slots per 64-byte line)
_I_MAGIC = 0
_I_W = (8, 24)                      #: write index of the ring *from* side 0 / side 1
_I_R = (16, 32)                     #: read index of the ring *from* side 0 / side 1


def segment_size(records: int = RING_RECORDS) -> int:
    return _OFF_DATA + 2 * records * REC


def create_segments(n: int, records: int = RING_RECORDS) -> list[shared_memory.SharedMemory]:
    """``n`` fresh, zeroed segments (the creator unlinks them: :func:`release_segments`)."""
    out = []
    try:
        for _ in range(n):
            seg = shared_memory.SharedMemory(create=True, size=segment_size(records))
            seg.buf[:_OFF_DATA] = bytes(_OFF_DATA)
            h = seg.buf[:_OFF_DATA].cast("q")
            h[1] = records
            h[2] = os.getpid()
            h[_I_MAGIC] = MAGIC
            h.release()
            out.append(seg)
    except BaseException:
        release_segments(out)
        raise
    return out


def release_segments(segs) -> None:
    for seg in segs:
        try:
            seg.close()
        except BufferError:          # a view still open in this process: unlink anyway
            pass
        try:
            seg.unlink()
        except FileNotFoundError:
            pass


class ShmBus(can.BusABC):
    """python-can bus on one side (0 or 1) of a shared-memory frame ring segment named ``name``.

    Offers the record batch interface of :mod:`drivers.framerec` (used by
    :class:`drivers.cyclic.CyclicIO` on the hot path) and the python-can ``send``/``recv`` (used by
    the master while booting and by the simulated drives).  ``poll_interval_s``: how often a
    blocking receive looks for new records (there is no wake-up on a shared ring).
    """

    frame_records = True

    def __init__(self, channel=None, side: int = 0, poll_interval_s: float = 0.0001, **kwargs):
        name = str(channel)
        if side not in (0, 1):
            raise ValueError(f"ShmBus side must be 0 or 1, not {side!r}")
        self._seg = shared_memory.SharedMemory(name=name)
        buf = self._seg.buf
        self._h = h = buf[:_OFF_DATA].cast("q")
        if h[2] != os.getpid():
            # attaching registered the segment with this process's resource tracker, which would
            # unlink it when this process exits; the creator (another process) owns it
            try:
                from multiprocessing import resource_tracker
                resource_tracker.unregister(self._seg._name, "shared_memory")  # type: ignore[attr-defined]
            except Exception:
                pass
        if h[_I_MAGIC] != MAGIC:
            self._h.release()
            self._seg.close()
            raise can.CanInitializationError(f"shared memory {name!r} is not a hexacnc frame ring")
        n = self._n = h[1]
        size = n * REC
        a = buf[_OFF_DATA:_OFF_DATA + size]
        b = buf[_OFF_DATA + size:_OFF_DATA + 2 * size]
        self._tx, self._rx = (a, b) if side == 0 else (b, a)
        self._iw_tx, self._ir_tx = _I_W[side], _I_R[side]          # ring we write
        self._iw_rx, self._ir_rx = _I_W[1 - side], _I_R[1 - side]  # ring we read
        self._size = size
        self._pending = 0          # records handed out by drain_records, released at the next receive
        self._one = bytearray(REC)
        self.poll_interval_s = float(poll_interval_s)
        self.channel_info = f"shared-memory frame ring {name} side {side}"
        self.dropped = 0           #: records not written because the peer's ring was full
        self._closed = False
        super().__init__(channel=channel, **kwargs)

    # -- batch interface (drivers.framerec) --------------------------------------------------
    def send_records(self, view) -> int:
        """Copy whole records into the ring and publish them; returns how many did not fit."""
        h = self._h
        w = h[self._iw_tx]
        nrec = len(view) // REC
        free = self._n - (w - h[self._ir_tx])
        k = nrec if nrec <= free else free
        if k > 0:
            p = (w % self._n) * REC
            nb = k * REC
            end = p + nb
            if end <= self._size:
                self._tx[p:end] = view[:nb] if nb != len(view) else view
            else:
                first = self._size - p
                self._tx[p:] = view[:first]
                self._tx[:nb - first] = view[first:nb]
            h[self._iw_tx] = w + k
        lost = nrec - k
        if lost:
            self.dropped += lost
        return lost

    def drain_records(self, max_records: int = 256):
        """The records that arrived, as ``(ring view, start, end)`` (zero copy, contiguous: at the
        ring's end the rest follows with the next call).  Consumed by this call, valid until the
        next receive call on this bus."""
        h = self._h
        r = h[self._ir_rx]
        if self._pending:
            r += self._pending
            h[self._ir_rx] = r
            self._pending = 0
        avail = h[self._iw_rx] - r
        if avail <= 0:
            return self._rx, 0, 0
        p = (r % self._n) * REC
        k = (self._size - p) // REC
        if avail < k:
            k = avail
        if k > max_records:
            k = max_records
        self._pending = k
        return self._rx, p, p + k * REC

    # -- python-can --------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        data = msg.data
        framerec.encode(self._one, 0, msg.arbitration_id, data if data is not None else b"",
                        is_extended_id=msg.is_extended_id, is_fd=msg.is_fd,
                        bitrate_switch=msg.bitrate_switch, is_remote_frame=msg.is_remote_frame)
        if self.send_records(self._one):
            raise can.CanOperationError("shared-memory frame ring full: the peer does not read")

    def _send_periodic_internal(self, msgs, period, duration=None, autostart=True, modifier_callback=None):
        """python-can's thread-based cyclic task (canopen's heartbeat producer uses it), kept alive when one
        send finds the ring full: python-can stops a task on its first send error unless ``on_error`` says
        otherwise, so a momentarily full ring silenced a simulated drive's heartbeat for good (the master
        then faulted "lost heartbeat" while the drive was well). One frame is lost, as a CAN controller
        with a full transmit queue loses it; the next period sends again. Lost frames are counted in
        ``periodic_send_errors``."""
        if not hasattr(self, "_lock_send_periodic"):
            self._lock_send_periodic = threading.Lock()
        self.periodic_send_errors = getattr(self, "periodic_send_errors", 0)

        def on_error(exc: Exception) -> bool:
            self.periodic_send_errors += 1
            return isinstance(exc, can.CanOperationError)       # a full ring: go on; anything else: stop

        return can.broadcastmanager.ThreadBasedCyclicSendTask(
            bus=self, lock=self._lock_send_periodic, messages=msgs, period=period, duration=duration,
            on_error=on_error, autostart=autostart, modifier_callback=modifier_callback)

    def _recv_internal(self, timeout: float | None):
        h = self._h
        t_end = None
        while True:
            r = h[self._ir_rx] + self._pending
            if self._pending:
                h[self._ir_rx] = r
                self._pending = 0
            if h[self._iw_rx] > r:
                p = (r % self._n) * REC
                rx = self._rx
                arb, flags, length = _HDR.unpack_from(rx, p)
                d = p + _HDR.size
                msg = can.Message(timestamp=time.time(), arbitration_id=arb, is_extended_id=bool(flags & F_EXT),
                                  is_fd=bool(flags & F_FD), bitrate_switch=bool(flags & F_BRS),
                                  is_remote_frame=bool(flags & F_RTR), dlc=length,
                                  data=bytes(rx[d:d + length]), check=False)
                h[self._ir_rx] = r + 1
                return msg, False
            if timeout is not None:
                if timeout <= 0.0:
                    return None, False
                now = time.monotonic()
                if t_end is None:
                    t_end = now + timeout
                elif now >= t_end:
                    return None, False
            if self._closed:
                return None, False
            time.sleep(self.poll_interval_s)

    def recv(self, timeout: float | None = None):
        """One frame or None (python-can's generic loop skipped unless filters are set)."""
        if not self._filters:
            return self._recv_internal(timeout)[0]
        return super().recv(timeout)

    def unread_by_peer(self) -> int:
        """Records this side sent that the peer has not consumed yet (its backlog; see
        :mod:`drivers.framerec`): records it holds from its last ``drain_records`` count as unread."""
        h = self._h
        return h[self._iw_tx] - h[self._ir_tx]

    def pending_records(self) -> int:
        """Records waiting to be read on this side (tests, diagnostics)."""
        return self._h[self._iw_rx] - self._h[self._ir_rx] - self._pending

    def shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        super().shutdown()
        for v in (self._tx, self._rx, self._h):
            v.release()
        try:
            self._seg.close()
        except BufferError:
            pass
