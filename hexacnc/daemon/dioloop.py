"""Program digital outputs (M62-M65) in the hot loop: 0x60FE:1 written by non-blocking SDO.

A row of the setpoint ring whose flags carry :data:`FLAG_IO` asks for up to :data:`SLOTS` output
changes, packed into the same flags float above bit :data:`SHIFT` (10 bits each, :func:`encode`):
``1 | value << 1 | drive << 2 | bit << 5``.  The producer (:mod:`.ioprog`) puts M62/M63 on the first
row of the next motion and M64/M65 on the row where the program reaches them; the hot loop takes the
change when it consumes that row (:meth:`DigitalOut.take`, no allocation) into a shadow output word
per drive, and :meth:`DigitalOut.step`, run once per cycle *after* the cycle's frames went out (as
the touch-probe latch, :mod:`.probelatch`), writes the changed words with expedited SDO downloads
(0x23, 0x60FE:1, 4 bytes, hand-packed), at most one outstanding per drive, answers collected by the
cyclic I/O's ``poll``.  The critical path (feedback, transform, frames out) never waits for it.

The SDO channel is shared with homing, the touch-probe latch and the torque sampler (.torqueread): while one is busy, writes wait.
It also reads a drive's 0x60FD (digital inputs) on request of the supervisor (M66,
:mod:`.dioread`): ``S_DIN_DRIVE``, ``S_DIN_REQ`` in, ``S_DIN_VAL``, ``S_DIN_ACK`` out.
Status slots (:mod:`.shm`): ``S_IO_OUT`` (6: the word each drive acknowledged), ``S_IO_WRITES``
(writes acknowledged), ``S_IO_ERR`` (0, or < 0: last error, :data:`ERROR_TEXT`).
"""
from __future__ import annotations

import struct

from ..setpoint import FLAG_IO  # noqa: F401 (re-exported: the row carries output changes)
from . import shm as S

SHIFT = 16                  #: first bit of the packed changes in the flags
WIDTH = 10
SLOTS = 3                   #: changes per row (16 + 3 * 10 = 46 bits < 53: exact in a float64)
SDO_TIMEOUT_NS = 100_000_000
E_SDO_ABORT, E_SDO_TIMEOUT, E_UNSUPPORTED = -1, -2, -3
ERROR_TEXT = {E_SDO_ABORT: "a drive refused the 0x60FE:1 write (SDO abort)",
              E_SDO_TIMEOUT: "no SDO answer to the 0x60FE:1 write",
              E_UNSUPPORTED: "this bus has no SDO channel: digital outputs cannot be written"}
_DL = struct.Struct("<BHBI")
_UL = _DL


def encode(drive: int, bit: int, value: bool) -> int:
    """One packed output change (``drive`` 0..5, ``bit`` 0..31)."""
    return 1 | (1 if value else 0) << 1 | (int(drive) & 7) << 2 | (int(bit) & 31) << 5


def decode(code: int) -> tuple[int, int, bool]:
    """``(drive, bit, value)`` of a packed change."""
    return (code >> 2) & 7, (code >> 5) & 31, bool(code & 2)


def pack_row(flags: int, codes) -> int:
    """``flags`` with :data:`FLAG_IO` and up to :data:`SLOTS` packed changes."""
    f = int(flags) | FLAG_IO
    for k, c in enumerate(codes):
        f |= int(c) << (SHIFT + WIDTH * k)
    return f


class DigitalOut:
    """The hot loop's side (see the module text)."""

    def __init__(self, loop):
        self.loop = loop
        self.io = loop.io
        self.s = loop.sh.s
        self.word = [0] * 6          #: shadow of each drive's 0x60FE:1
        self.dirty = [False] * 6
        self.sent = [0] * 6          #: value in flight
        self.sent_at = [0] * 6
        self.count0 = [0] * 6
        self.active = False
        self.has_sdo = hasattr(self.io, "send_sdo")
        self.din_seen = self.s[S.S_DIN_REQ]      # input reads (M66, hexacnc.daemon.dioread)
        self.din_drive = -1                      #: drive whose 0x60FD is still to be asked for
        self.reading = [0.0] * 6                 #: request number of an upload in flight, 0 none

    def take(self, flags: int) -> int:
        """Apply the changes packed in a consumed row's ``flags`` to the shadow words; returns ``flags``."""
        c = flags >> SHIFT
        while c:
            code = c & 1023
            if code & 1:
                d = (code >> 2) & 7
                if d < 6:
                    m = 1 << ((code >> 5) & 31)
                    self.word[d] = (self.word[d] | m) if code & 2 else (self.word[d] & ~m)
                    self.dirty[d] = True
                    self.active = True
            c >>= WIDTH
        return flags

    def _failed(self, i: int, code: int) -> None:
        self.s[S.S_IO_ERR] = code
        if self.reading[i]:                      # the read is answered: with an error (value -1)
            self.s[S.S_DIN_VAL] = -1.0
            self.s[S.S_DIN_ACK] = self.reading[i]
            self.reading[i] = 0.0

    def step(self, now: int) -> None:
        """Once per cycle after the frames went out: collect answers, send changed words, read inputs."""
        if self.s[S.S_DIN_REQ] != self.din_seen:
            self.din_seen = self.s[S.S_DIN_REQ]
            self.din_drive = int(self.s[S.S_DIN_DRIVE])
            self.active = True
        if not self.active:
            return
        if not self.has_sdo:
            self.s[S.S_IO_ERR] = E_UNSUPPORTED
            self.active = False
            return
        lp = self.loop
        if lp.latch.active or lp.state == S.ST_HOMING or lp.state == S.ST_BOOT:
            return                   # the SDO channel is someone else's now: wait
        io = self.io
        busy = False
        torque = getattr(lp, "torque", None)      # a torque sample (.torqueread) in flight: wait for its answer
        for i in range(6):
            if torque is not None and not self.sent_at[i] and torque.holds(i) and (self.dirty[i] or i == self.din_drive):
                busy = True
                continue
            if self.sent_at[i]:
                if io.sdo_count[i] == self.count0[i]:
                    if now - self.sent_at[i] > SDO_TIMEOUT_NS:
                        self.sent_at[i] = 0
                        self._failed(i, E_SDO_TIMEOUT)
                    else:
                        busy = True
                    continue
                self.sent_at[i] = 0
                if io.sdo_resp[i][0] == 0x80:
                    self._failed(i, E_SDO_ABORT)
                elif self.reading[i]:
                    self.s[S.S_DIN_VAL] = float(int.from_bytes(bytes(io.sdo_resp[i][4:8]), "little"))
                    self.s[S.S_DIN_ACK] = self.reading[i]
                    self.reading[i] = 0.0
                else:
                    self.s[S.S_IO_OUT + i] = float(self.sent[i])
                    self.s[S.S_IO_WRITES] += 1.0
            if self.dirty[i]:
                self.count0[i] = io.sdo_count[i]
                if io.send_sdo(i, _DL.pack(0x23, 0x60FE, 1, self.word[i] & 0xFFFFFFFF)):
                    self.sent[i] = self.word[i]
                    self.sent_at[i] = now or 1
                    self.dirty[i] = False
                busy = True
            elif i == self.din_drive:
                self.count0[i] = io.sdo_count[i]
                if io.send_sdo(i, _UL.pack(0x40, 0x60FD, 0, 0)):
                    self.reading[i] = self.din_seen
                    self.sent_at[i] = now or 1
                    self.din_drive = -1
                busy = True
        self.active = busy
