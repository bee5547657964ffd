"""The enable walk of the hot loop: CiA 402 controlwords in the cyclic frames, targets = measured.

While the drives are walked to Operation Enabled (transitions 2, 3, 4; 15 from Fault), SYNC runs
and every target is the measured position (clamped to the strut range), so enabling moves nothing.
No drive is enabled before its first position sample, nor while it reports a position outside the
strut range (refused after a quarter of the time-out).
"""
from __future__ import annotations

from drivers.cia402 import CW_ENABLE_OPERATION, OPERATION_ENABLED, is_operation_enabled, next_controlword

#: time allowed for the walk (ns)
ENABLE_TIMEOUT_NS = 2_000_000_000

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
        self.t0 = 0
        self.bad = 0
        self.arg = 0

    def begin(self, now: int) -> None:
        self.t0 = now

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
            if not op_enabled(io.statusword[i]):
                self.bad, self.arg = i + 1, io.statusword[i]
                return
