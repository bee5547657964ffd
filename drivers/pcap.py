"""Capture of every CAN frame the master sends and receives, as a standard pcap file with link
type ``LINKTYPE_CAN_SOCKETCAN`` (227), readable by Wireshark/tshark (CANopen: "Decode As" CANopen,
or ``tshark -d can.subdissector,canopen``... see drivers/README.md).

Record layout (the SocketCAN ``struct can_frame`` / ``canfd_frame`` as libpcap defines it for
link type 227): CAN ID in network byte order (bit 31 EFF, bit 30 RTR), payload length, FD flags
(0x04 = FD frame, 0x01 = bit-rate switch), two reserved bytes, then 8 (classic) or 64 (FD) data
bytes.

:class:`CaptureBus` wraps a python-can bus (or the daemon's frame-record buses) and writes every
frame it passes, both directions, with the wall-clock time; nothing else changes on the bus.
``hexacnc run --capture FILE.pcap`` sets ``HEXACNC_CAPTURE`` for the hot process, which wraps its
buses with :func:`capture_buses` (one file per bus: FILE.pcap, FILE-bus1.pcap, ...). With simulated
drives, their process captures its ends of the buses too (FILE-drives.pcap, FILE-drives-bus1.pcap,
:func:`drives_capture_path`): what a bus monitor would record, including the drives' reaction after the
master fell silent (a capture inside the master ends with it).
"""
from __future__ import annotations

import os
import struct
import threading
import time
from typing import Sequence

import can

from . import framerec

LINKTYPE_CAN_SOCKETCAN = 227
ENV_CAPTURE = "HEXACNC_CAPTURE"
_GLOBAL = struct.Struct("<IHHiIII")
_RECORD = struct.Struct("<IIII")
_CAN_HDR = struct.Struct(">IBBBB")
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CANFD_BRS = 0x01
CANFD_FDF = 0x04
FLUSH_S = 0.25


class PcapWriter:
    """Thread-safe pcap writer for SocketCAN frames (bounded buffer, flushed every 0.25 s).

    ``background=True``: :meth:`write` only appends to a memory buffer and a thread writes it out every
    ``FLUSH_S``, so a slow disk never blocks the caller (the simulated drives write under their lock)."""

    def __init__(self, path: str | os.PathLike, background: bool = False):
        self.path = str(path)
        self._f = open(self.path, "wb")
        self._f.write(_GLOBAL.pack(0xA1B2C3D4, 2, 4, 0, 0, 72, LINKTYPE_CAN_SOCKETCAN))
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self.frames = 0
        self.closed = False
        self._pending: bytearray | None = None
        self._thread: threading.Thread | None = None
        if background:
            self._pending = bytearray()
            self._wake = threading.Event()
            self._thread = threading.Thread(target=self._drain, name="pcap-writer", daemon=True)
            self._thread.start()

    def _drain(self) -> None:
        while not self._wake.wait(FLUSH_S):
            self._write_pending()
        self._write_pending()

    def _write_pending(self) -> None:
        with self._lock:
            chunk, self._pending = self._pending, bytearray()
        if chunk:
            self._f.write(chunk)
            self._f.flush()

    def write(self, arbitration_id: int, data, *, is_extended_id: bool = False, is_fd: bool = False,
              bitrate_switch: bool = False, is_remote_frame: bool = False, t_s: float | None = None) -> None:
        t = time.time() if t_s is None else t_s
        n = len(data)
        can_id = arbitration_id | (CAN_EFF_FLAG if is_extended_id else 0) | (CAN_RTR_FLAG if is_remote_frame else 0)
        size = 64 if is_fd else 8
        flags = (CANFD_FDF | (CANFD_BRS if bitrate_switch else 0)) if is_fd else 0
        body = _CAN_HDR.pack(can_id, n, flags, 0, 0) + bytes(data) + bytes(size - n)
        sec = int(t)
        with self._lock:
            if self.closed:
                return
            self.frames += 1
            if self._pending is not None:
                self._pending += _RECORD.pack(sec, int((t - sec) * 1e6), len(body), len(body))
                self._pending += body
                return
            self._f.write(_RECORD.pack(sec, int((t - sec) * 1e6), len(body), len(body)))
            self._f.write(body)
            now = time.monotonic()
            if now - self._last_flush > FLUSH_S:
                self._last_flush = now
                self._f.flush()

    def write_message(self, msg: can.Message) -> None:
        self.write(msg.arbitration_id, msg.data, is_extended_id=msg.is_extended_id, is_fd=msg.is_fd,
                   bitrate_switch=msg.bitrate_switch, is_remote_frame=msg.is_remote_frame)

    def write_records(self, buf, start: int, end: int) -> None:
        """Frames held as :mod:`drivers.framerec` records in ``buf[start:end]``."""
        hdr, rec, off = framerec.HEADER, framerec.RECORD, framerec.DATA_OFFSET
        t = time.time()
        for p in range(start, end, rec):
            cob, flags, n = hdr.unpack_from(buf, p)
            self.write(cob, bytes(buf[p + off:p + off + n]), is_extended_id=bool(flags & framerec.F_EXT),
                       is_fd=bool(flags & framerec.F_FD), bitrate_switch=bool(flags & framerec.F_BRS),
                       is_remote_frame=bool(flags & framerec.F_RTR), t_s=t)

    def close(self) -> None:
        if self._thread is not None:
            with self._lock:
                self.closed = True          # no more frames; the thread writes what is pending
            self._wake.set()
            self._thread.join(5.0)
        with self._lock:
            self.closed = True
            if not self._f.closed:
                self._f.close()


class CaptureBus(can.BusABC):
    """A bus that writes every frame passing through it (sent or received) to a :class:`PcapWriter`.

    Periodic sends (``send_periodic``, the master heartbeat) go through :meth:`send` and are
    captured too. The frame-record batch interface is passed through when the inner bus has it."""

    def __init__(self, inner: can.BusABC, writer: PcapWriter, close_writer: bool = True):
        self.inner = inner
        self.writer = writer
        self._close_writer = close_writer
        super().__init__(channel=getattr(inner, "channel_info", "capture"))
        self.channel_info = f"capture({getattr(inner, 'channel_info', '?')})"
        if framerec.supports_batch(inner):
            self.frame_records = True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)
        self.writer.write_message(msg)

    def _recv_internal(self, timeout: float | None):
        msg = self.inner.recv(timeout)
        if msg is not None:
            self.writer.write_message(msg)
        return msg, True

    def send_records(self, view) -> int:
        lost = self.inner.send_records(view)
        self.writer.write_records(view, 0, len(view))
        return lost

    def drain_records(self, max_records: int):
        buf, start, end = self.inner.drain_records(max_records)
        if end > start:
            self.writer.write_records(buf, start, end)
        return buf, start, end

    def shutdown(self) -> None:
        try:
            self.inner.shutdown()
        finally:
            if self._close_writer:
                self.writer.close()
            super().shutdown()

    def __getattr__(self, name):          # anything else (fileno, state, ...) from the inner bus
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def capture_path(path: str, bus_index: int) -> str:
    """FILE.pcap for bus 0, FILE-bus1.pcap for bus 1, ..."""
    if bus_index == 0:
        return path
    root, ext = os.path.splitext(path)
    return f"{root}-bus{bus_index}{ext or '.pcap'}"


def drives_capture_path(path: str) -> str:
    """FILE-drives.pcap for FILE.pcap: the capture taken on the simulated drives' side of the buses
    (every frame on the wire, also after the master fell silent; ``capture_path`` of it per bus)."""
    root, ext = os.path.splitext(path)
    return f"{root}-drives{ext or '.pcap'}"


def capture_buses(buses: Sequence[can.BusABC], path: str | None = None, background: bool = False) -> list:
    """Wrap ``buses`` in :class:`CaptureBus` when ``path`` (default: ``$HEXACNC_CAPTURE``) is set,
    one pcap file per bus (``background``: see :class:`PcapWriter`); otherwise return them unchanged."""
    path = path if path is not None else os.environ.get(ENV_CAPTURE, "")
    if not path:
        return list(buses)
    return [CaptureBus(b, PcapWriter(capture_path(path, i), background)) for i, b in enumerate(buses)]


def read_pcap(path: str) -> list[tuple[float, int, bytes, int]]:
    """Frames of a SocketCAN pcap as (time s, CAN ID with flag bits, data, FD flags) - for tests
    and quick looks (Wireshark/tshark is the independent decoder)."""
    out = []
    with open(path, "rb") as f:
        head = f.read(_GLOBAL.size)
        magic, _, _, _, _, _, link = _GLOBAL.unpack(head)
        if magic != 0xA1B2C3D4 or link != LINKTYPE_CAN_SOCKETCAN:
            raise ValueError(f"{path}: not a little-endian SocketCAN pcap (magic 0x{magic:08X}, link type {link})")
        while True:
            rh = f.read(_RECORD.size)
            if len(rh) < _RECORD.size:
                break
            sec, usec, incl, _ = _RECORD.unpack(rh)
            body = f.read(incl)
            if len(body) < incl:
                break
            can_id, n, flags, _, _ = _CAN_HDR.unpack_from(body)
            out.append((sec + usec * 1e-6, can_id, body[8:8 + n], flags))
    return out
