"""CiA 402 touch probe 1 of a simulated drive: objects 0x60B8 (function), 0x60B9 (status),
0x60BA (position latched at the positive edge), 0x60BB (at the negative edge).

0x60B8 bits: 0 enable touch probe 1; 1 trigger mode (0 first event, 1 continuous); 2-3 trigger
source (00: touch probe input 1, the only one simulated); 4 enable latching at the positive edge;
5 at the negative edge.  0x60B9 bits: 0 touch probe 1 enabled; 1 positive edge value stored; 2
negative edge value stored.  In first-event mode a stored value stays until the probe is enabled
again (bit 0 or bit 4/5 written from 0 to 1).

The input is a signal given per step: ``> 0`` open (no contact), ``<= 0`` closed (contact; the
simulated one is the distance of the true tool tip to the artefact's surface, mm).  A real drive
latches its encoder at the input edge within microseconds; the simulation interpolates the
position linearly in the signal between the two steps around the edge, so the stored reading is
the one at contact, not the next cycle's.
"""
from __future__ import annotations

FN_ENABLE = 0x01
FN_CONTINUOUS = 0x02
FN_SOURCE = 0x0C
FN_POS_EDGE = 0x10
FN_NEG_EDGE = 0x20
ST_ENABLED = 0x01
ST_POS_STORED = 0x02
ST_NEG_STORED = 0x04

INDEX_FUNCTION, INDEX_STATUS, INDEX_POS_VALUE, INDEX_NEG_VALUE = 0x60B8, 0x60B9, 0x60BA, 0x60BB


class TouchProbe:
    __slots__ = ("function", "status", "pos_value", "neg_value", "_prev", "edges")

    def __init__(self) -> None:
        self.function = 0
        self.status = 0
        self.pos_value = 0
        self.neg_value = 0
        self._prev: tuple[float, int] | None = None
        self.edges = 0

    @property
    def armed(self) -> bool:
        return bool(self.function & FN_ENABLE)

    def write_function(self, value: int) -> None:
        v = int(value) & 0xFFFF
        newly = v & ~self.function
        self.function = v
        if not v & FN_ENABLE:
            self.status = 0
            self._prev = None
            return
        if newly & FN_ENABLE:
            self.status = ST_ENABLED
            self.pos_value = self.neg_value = 0
            self._prev = None
        if newly & FN_POS_EDGE:
            self.status &= ~ST_POS_STORED
        if newly & FN_NEG_EDGE:
            self.status &= ~ST_NEG_STORED

    def sample(self, pos_inc: int, signal: float) -> None:
        """One step: the drive's position (increments) and the probe input signal."""
        if not self.function & FN_ENABLE or self.function & FN_SOURCE:
            return
        prev = self._prev
        if prev is not None:
            s0, p0 = prev
            if s0 > 0.0 >= signal:
                self._edge(True, p0, pos_inc, s0, signal)
            elif s0 <= 0.0 < signal:
                self._edge(False, p0, pos_inc, s0, signal)
        self._prev = (signal, pos_inc)

    def _edge(self, rising: bool, p0: int, p1: int, s0: float, s1: float) -> None:
        self.edges += 1
        enable, stored = (FN_POS_EDGE, ST_POS_STORED) if rising else (FN_NEG_EDGE, ST_NEG_STORED)
        if not self.function & enable:
            return
        if self.status & stored and not self.function & FN_CONTINUOUS:
            return                                  # first event: keep the first latched value
        w = s0 / (s0 - s1) if s0 != s1 else 1.0
        v = int(round(p0 + w * (p1 - p0)))
        if rising:
            self.pos_value = v
        else:
            self.neg_value = v
        self.status |= stored
