"""The disable walk of the hot loop: CiA 402 controlwords in the cyclic frames, targets held.

A normal disable (after a controlled stop that ends disabled, a ``disable`` op, shutdown, a stop
signal, an enable that failed) walks every drive to Switch on disabled with the one CiA 402 walk
(:func:`drivers.cia402.next_controlword`): transition 5 (0x0007 "disable operation": the drive
stops per 0x605C and engages its holding brake, Switched on), then 10 (0x0000). SYNC and the
targets (the last command, held by the loop) keep flowing meanwhile. A drive in Quick stop active
gets (or keeps) the quick stop command until it leaves that state by itself (0x605A options 1,
2: transition 12 once stopped); a drive in Fault is never reset by a disable. After
``DISABLE_TIMEOUT_NS`` every drive still on gets 0x0000 as the last resort (logged).

Quick stop (:data:`drivers.cia402.CW_QUICK_STOP`, controlword bit 2 cleared, transition 11) is
sent by :meth:`DisableWalk.quick_stop` to a drive that no longer follows the loop's own stop.
"""
from __future__ import annotations

import logging

from drivers.cia402 import (CW_DISABLE_VOLTAGE, CW_QUICK_STOP, FAULT, NOT_READY, QUICK_STOP_ACTIVE,
                            SWITCH_ON_DISABLED, next_controlword, state_from_status, state_name)

log = logging.getLogger("hexacnc.loop")

#: time allowed for the walk to Switch on disabled before 0x0000 is sent regardless (ns)
DISABLE_TIMEOUT_NS = 500_000_000


def disabled_enough(state: int) -> bool:
    """The drive's power stage is off (nothing left to walk): Switch on disabled, Fault, Not ready."""
    return state == SWITCH_ON_DISABLED or state == FAULT or state == NOT_READY


class DisableWalk:
    """``begin(now)`` then ``step(now)`` once per cycle until it returns True (all disabled).

    ``cw``: the list of the last controlword requested per drive, shared with the enable walk
    (:class:`~hexacnc.daemon.enablewalk.EnableWalk`), so that either walk continues from what
    the drives last received."""

    def __init__(self, io, cw: list):
        self.io = io
        self.cw = cw
        self.active = False
        self.t0 = 0
        self.timeouts = 0           #: walks ended by the time-out (0x0000 as the last resort)

    def begin(self, now: int) -> None:
        if not self.active:
            self.active = True
            self.t0 = now

    def cancel(self) -> None:
        """A new enable walk takes over (reset): the controlwords are its business now."""
        self.active = False

    def _set(self, i: int, cw: int) -> None:
        if cw != self.cw[i]:
            self.io.set_controlword(i, cw)
            self.cw[i] = cw

    def quick_stop(self, i: int) -> None:
        """Quick stop (transition 11) for drive ``i`` (0-based): it decelerates per 0x605A/0x6085."""
        self._set(i, CW_QUICK_STOP)

    def step(self, now: int) -> bool:
        """One cycle of the walk: True once every drive is disabled (then ``active`` is False)."""
        statusword = self.io.statusword
        done = True
        for i in range(6):
            sw = statusword[i]
            if sw < 0:
                continue            # never heard of: nothing to walk (gets 0x0000 at the end)
            st = state_from_status(sw)
            if disabled_enough(st):
                continue
            done = False
            if st == QUICK_STOP_ACTIVE:     # the drive ends its own quick stop ramp (transition 12);
                self._set(i, CW_QUICK_STOP)  # never 0x000F there (transition 16 would re-enable it)
                continue
            self._set(i, next_controlword(sw, SWITCH_ON_DISABLED, self.cw[i]))
        if not done and now - self.t0 > DISABLE_TIMEOUT_NS:
            self._give_up(statusword)
            done = True
        if done:
            for i in range(6):
                self._set(i, CW_DISABLE_VOLTAGE)
            self.active = False
        return done

    def _give_up(self, statusword) -> None:
        self.timeouts += 1
        late = [f"drive {i + 1}: {state_name(state_from_status(statusword[i]))} (0x{statusword[i] & 0xFFFF:04X})"
                for i in range(6) if statusword[i] >= 0 and not disabled_enough(state_from_status(statusword[i]))]
        log.warning("hot loop: drives not in Switch on disabled %.1f s after the disable walk began; "
                    "sending 0x0000 (disable voltage): %s", DISABLE_TIMEOUT_NS * 1e-9, "; ".join(late))
