"""The enable walk of the hot loop: CiA 402 controlwords in the cyclic frames, targets = measured.

While the drives are walked to Operation Enabled (transitions 2, 3, 4; 15 from Fault), SYNC runs
and every target is the measured position (clamped to the strut range), so enabling moves nothing.
No drive is enabled before its first position sample, nor while it reports a position outside the
strut range (refused after a quarter of the time-out).

Fault reset (transition 15) is a rising edge of controlword bit 7 that the drive must see: the walk
waits while a drive is in Fault reaction active (bit 7 low, so the edge is fresh once the reaction
ends), then raises bit 7 and holds it ``RESET_HOLD_NS`` or until the drive leaves Fault, then holds it
low ``RESET_LOW_NS`` before the next edge. Toggling it every loop cycle instead would alias with a bus
that runs every n-th loop cycle (``sync_every`` 2 on a drive taking whole ms only): the drive could
receive bit 7 low in every bus cycle and never see the edge.
"""
from __future__ import annotations

from drivers.cia402 import (CW_BIT_FAULT_RESET, CW_ENABLE_OPERATION, CW_FAULT_RESET, OPERATION_ENABLED,
                            is_operation_enabled, next_controlword)

#: time allowed for the walk (ns)
ENABLE_TIMEOUT_NS = 2_000_000_000
#: fault reset: bit 7 held high this long (or until the drive leaves Fault), then low ``RESET_LOW_NS``
#: before the next edge; both many bus periods long (the drive sees each level in at least one RPDO)
RESET_HOLD_NS = 50_000_000
RESET_LOW_NS = 20_000_000
#: statusword state bits (mask 0x4F) of Fault (0x0008) and Fault reaction active (0x000F)
_SW_FAULT_MASK = 0x004F
_SW_FAULT = 0x0008
_SW_FAULT_REACTION = 0x000F

def op_enabled(sw: int) -> bool:
    """The drive is in Operation Enabled (:func:`drivers.cia402.is_operation_enabled`)."""
    return is_operation_enabled(sw)


def next_cw(sw: int, prev_cw: int) -> int:
    """Controlword that moves a drive with statusword ``sw`` one step towards Operation Enabled:
    the one CiA 402 walk, :func:`drivers.cia402.next_controlword`."""
    return next_controlword(sw, OPERATION_ENABLED, prev_cw)


class EnableWalk:
    """``step(now, act, out)`` once per cycle in the boot state: 0 walking, 1 all enabled,
    -1 failed (``bad`` = 1-based drive, ``arg`` = -1 no position, -2 outside the range, else its
    statusword)."""

    def __init__(self, io, lmin, lmax):
        self.io = io
        self.lmin = lmin
        self.lmax = lmax
        self.cw = [-1] * 6            #: last controlword requested per drive
        self.reset_ns = [0] * 6       #: when bit 7 last changed level in Fault
        self.edges = [0] * 6          #: fault-reset edges sent per drive in this walk
        self.t0 = 0
        self.bad = 0
        self.arg = 0

    def begin(self, now: int) -> None:
        self.t0 = now
        for i in range(6):
            self.reset_ns[i] = now - RESET_HOLD_NS - RESET_LOW_NS      # an edge may come at once
            self.edges[i] = 0

    def set_all(self, cw: int) -> None:
        for i in range(6):
            self.io.set_controlword(i, cw)
            self.cw[i] = cw

    def track(self, act, out) -> None:
        """Targets = the measured positions, clamped to the strut range (nothing moves on enabling)."""
        lmin, lmax = self.lmin, self.lmax
        for i in range(6):
            v = act[i]
            out[i] = lmin[i] if v < lmin[i] else (lmax[i] if v > lmax[i] else v)

    def step(self, now: int, act, out) -> int:
        io = self.io
        self.track(act, out)
        ready = self._positions_ok(now, act)
        statusword = io.statusword
        all_on = ready
        for i in range(6 if ready else 0):
            sw = statusword[i]
            if not op_enabled(sw):
                all_on = False
                f = sw & _SW_FAULT_MASK
                if f == _SW_FAULT or f == _SW_FAULT_REACTION:
                    self._fault_reset(i, now, f == _SW_FAULT)
                    continue
                cw = next_cw(sw, self.cw[i])
                if cw != self.cw[i]:
                    io.set_controlword(i, cw)
                    self.cw[i] = cw
        if all_on:
            self.set_all(CW_ENABLE_OPERATION)
            return 1
        if now - self.t0 > ENABLE_TIMEOUT_NS:
            self._blame(act)
            return -1
        return 0

    def _fault_reset(self, i: int, now: int, in_fault: bool) -> None:
        """Drive ``i`` in Fault (``in_fault``) or Fault reaction active: the timed edge of bit 7."""
        cw = self.cw[i]
        high = cw >= 0 and cw & CW_BIT_FAULT_RESET
        if not in_fault:                    # the reaction runs: bit 7 low, the edge comes after it
            if high or cw < 0:
                self.io.set_controlword(i, 0)
                self.cw[i] = 0
                self.reset_ns[i] = now
            return
        since = now - self.reset_ns[i]
        if high:
            if since >= RESET_HOLD_NS:      # not taken (yet): low again, then a new edge
                self.io.set_controlword(i, 0)
                self.cw[i] = 0
                self.reset_ns[i] = now
        elif since >= RESET_LOW_NS:
            self.io.set_controlword(i, CW_FAULT_RESET)
            self.cw[i] = CW_FAULT_RESET
            self.reset_ns[i] = now
            self.edges[i] += 1

    def _positions_ok(self, now: int, act) -> bool:
        """Every drive has reported a position inside the strut range (never enable blind)."""
        pos_count = self.io.pos_count
        for i in range(6):
            if pos_count[i] == 0:
                return False
            if act[i] < self.lmin[i] or act[i] > self.lmax[i]:
                if now - self.t0 > ENABLE_TIMEOUT_NS // 4:
                    self.t0 = -ENABLE_TIMEOUT_NS       # refuse now
                return False
        return True

    def _blame(self, act) -> None:
        io = self.io
        self.bad, self.arg = 0, 0
        for i in range(6):
            if io.pos_count[i] == 0:
                self.bad, self.arg = i + 1, -1
                return
            if act[i] < self.lmin[i] or act[i] > self.lmax[i]:
                self.bad, self.arg = i + 1, -2
                return
            sw = io.statusword[i]
            if not op_enabled(sw):
                self.bad, self.arg = i + 1, sw
                if sw >= 0 and sw & _SW_FAULT_MASK == _SW_FAULT:
                    self.arg = (sw & 0xFFFF) | self.edges[i] << 16    # + fault-reset edges sent
                return
