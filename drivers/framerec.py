"""Fixed-size CAN frame records for stream transports (the daemon's pipe bus).

One frame is one ``RECORD``-byte record: ``struct "<IBB"`` (arbitration id, flags, data length)
then 64 data bytes (classic frames use the first 0..8).  A stream of records needs no framing
beyond the fixed size, so several frames can go in one ``write(2)`` and be read with one
``read(2)``.

A bus object that carries such records may offer the batch interface that
:class:`drivers.cyclic.CyclicIO` uses on the hot path instead of ``send``/``recv`` of
``can.Message`` objects (attribute ``frame_records = True``):

* ``send_records(view) -> int``: write whole records (``len(view)`` a multiple of ``RECORD``) in
  one call; returns the number of records lost because the peer's queue was full (like a
  receiver overrun: the sender never blocks); raises ``can.CanOperationError`` if the transport
  failed;
* ``drain_records(max_records) -> (buf, start, end)``: read what arrived without blocking and
  hand over the whole records ``buf[start:end]`` (consumed by this call; valid until the next
  receive call on the bus); raises ``can.CanOperationError`` if the transport failed.

Optional: ``unread_by_peer() -> int``, the records sent that the peer has not consumed yet (a
simulated peer process that stalled and catches up has a backlog; real drives on a wire have none).
:class:`drivers.synctags.SyncTags` uses it to tell frames lost from frames still to come.

SocketCAN and udp_multicast buses do not have it: the kernel takes one frame per ``write``.
"""
from __future__ import annotations

import struct

HEADER = struct.Struct("<IBB")      #: arbitration id, flags (F_*), data length
RECORD = 72                         #: bytes per frame record
DATA_OFFSET = HEADER.size           #: first data byte within a record
MAX_DATA = RECORD - DATA_OFFSET     #: 64 (CAN FD)

F_EXT = 1
F_FD = 2
F_BRS = 4
F_RTR = 8


def encode(buf, offset: int, arbitration_id: int, data=b"", *, is_extended_id: bool = False,
           is_fd: bool = False, bitrate_switch: bool = False, is_remote_frame: bool = False) -> None:
    """Write one record at ``buf[offset:offset + RECORD]`` (data bytes beyond ``len(data)`` untouched)."""
    n = len(data)
    if n > MAX_DATA:
        raise ValueError(f"frame 0x{arbitration_id:X}: {n} data bytes, at most {MAX_DATA}")
    flags = ((F_EXT if is_extended_id else 0) | (F_FD if is_fd else 0)
             | (F_BRS if bitrate_switch else 0) | (F_RTR if is_remote_frame else 0))
    HEADER.pack_into(buf, offset, arbitration_id, flags, n)
    if n:
        buf[offset + DATA_OFFSET:offset + DATA_OFFSET + n] = data


def supports_batch(bus) -> bool:
    """True if ``bus`` offers ``send_records``/``drain_records`` (see the module doc)."""
    return getattr(bus, "frame_records", False) is True
