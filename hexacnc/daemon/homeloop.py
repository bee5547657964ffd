"""CiA 402 homing (mode 6) of every strut, run by the hot loop in its ``ST_HOMING`` state
(``[homing] method = "cia402"``; the supervisor asks with ``CMD_HOME``, :mod:`.operator`).

All six drives home at once, each through its own non-blocking sequence, one step per cycle (SYNC,
heartbeat and the cyclic frames keep running; the cyclic targets are the measured positions, so the
drive takes over from where it stands when it is back in cyclic synchronous position mode):

1. expedited SDO downloads (hand-packed 8-byte frames, one outstanding per drive, answer or abort
   awaited over the following cycles): 0x6098 method, 0x6099:1/2 speeds, 0x609A acceleration,
   0x607C home offset (``[homing]`` keys, mm -> position units by ``[bus] increments_per_mm``), then
   0x6060 = 6;
2. the statusword in mode 6 (bit 12 clear), then controlword bit 4 (0x001F) starts the method;
3. bit 12 homing attained (bit 13 homing error is a failure); controlword 0x000F; 0x6060 = 8.

Any SDO abort or silence, homing error, drive fault or state change, lost heartbeat, a measured
length outside the strut limits, or ``HOME_TIMEOUT_S`` fails the run: bit 4 is cleared (the drive
stops its homing motion), mode 8 is written back (best effort) once the drive reports the motion
halted (bit 10, at most ``SDO_TIMEOUT_S``) and the loop latches a fault (drives disabled).
``CMD_STOP`` stops it the same way but ends idle (re-seeded), ``CMD_DISABLE`` ends disabled.
Following-error supervision is off while homing (the drives move on their own).

Results in the shared header: ``H_HOME_RESULT`` (:data:`RUNNING`, :data:`DONE` or an error code
< 0, see :data:`ERROR_TEXT`) and ``H_HOME_STRUT`` (1-based strut of the error).
"""
from __future__ import annotations

import struct
import time

from drivers.cia402 import CW_ENABLE_OPERATION, SW_DRIVE_FOLLOWS, SW_FAULT

from . import shm as S
from .faults import F_HOMING, F_NONE
from .homecodes import (DONE, E_ABORTED, E_FAULT, E_HEARTBEAT, E_HOMING_ERROR, E_LIMIT,  # noqa: F401
                        E_SDO_ABORT, E_SDO_TIMEOUT, E_TIMEOUT, E_UNSUPPORTED, ERROR_TEXT, HOME_TIMEOUT_S, RUNNING, SDO_TIMEOUT_S)

MODE_HOMING = 6
MODE_CSP = 8
CW_HOMING_START = CW_ENABLE_OPERATION | (1 << 4)
SW_TARGET_REACHED = 1 << 10
SW_HOMING_ATTAINED = 1 << 12
SW_HOMING_ERROR = 1 << 13
SW_STATE_MASK, SW_OPERATION_ENABLED = 0x6F, 0x27
_P_SDO, _P_WAIT_MODE, _P_WAIT_ATTAINED, _P_BACK, _P_DONE, _P_HALT = range(6)
_SIZE_CS = {1: 0x2F, 2: 0x2B, 4: 0x23}
_REQ = struct.Struct("<BHBi")
_REQ_U = struct.Struct("<BHBI")


def sdo_download(index: int, sub: int, size: int, value: int) -> bytes:
    """An expedited SDO download request (client -> server), size indicated."""
    if value < 0:
        return _REQ.pack(_SIZE_CS[size], index, sub, value)
    return _REQ_U.pack(_SIZE_CS[size], index, sub, value & 0xFFFFFFFF)


def homing_writes(homing_cfg, ipm: float, strut: int) -> list[bytes]:
    """The SDO requests that set up drive ``strut`` for homing, ending with 0x6060 = 6."""
    hm = homing_cfg
    return [sdo_download(0x6098, 0, 1, int(hm.homing_method)),
            sdo_download(0x6099, 1, 4, max(1, int(round(hm.speed_search_mm_s * ipm)))),
            sdo_download(0x6099, 2, 4, max(1, int(round(hm.speed_zero_mm_s * ipm)))),
            sdo_download(0x609A, 0, 4, max(1, int(round(hm.acceleration_mm_s2 * ipm)))),
            sdo_download(0x607C, 0, 4, int(round(float(hm.offset_mm[strut]) * ipm))),
            sdo_download(0x6060, 0, 1, MODE_HOMING)]


class HomingCycle:
    """The homing steps of :class:`~hexacnc.daemon.loop.HotLoop` (``loop``); see the module doc."""

    def __init__(self, loop):
        self.loop = loop
        self.io = loop.io
        self.n = 6
        self.ipm = loop.ipm
        self.queue: list[list[bytes]] = [[] for _ in range(6)]
        self.sent_at = [0] * 6            #: ns of the outstanding request (0: none)
        self.count0 = [0] * 6             #: sdo_count when it was sent
        self.phase = [_P_DONE] * 6
        self.back_ns = [0] * 6       #: when each drive's mode 8 was acknowledged (statusword bit 12 awaited)
        self.t0 = 0
        self.error = 0
        self.strut = 0
        self.aborting = False
        self.abort_t0 = 0

    # -- entry / exit -------------------------------------------------------------------------
    def begin(self, now: int) -> bool:
        """Start homing every strut; False (result set) when the bus has no SDO channel."""
        h = self.loop.sh.h
        self.error = self.strut = 0
        self.aborting = False
        if not hasattr(self.io, "send_sdo"):
            self._result(E_UNSUPPORTED, 0)
            return False
        hm = self.loop.cfg.operator.homing
        for i in range(6):
            self.queue[i] = homing_writes(hm, self.ipm, i)
            self.sent_at[i] = 0
            self.phase[i] = _P_SDO
        self.t0 = now
        h[S.H_HOME_RESULT] = RUNNING
        h[S.H_HOME_STRUT] = 0
        return True

    def abort(self, code: int, strut: int, now: int) -> None:
        """Fail: bit 4 cleared, mode 8 written back, then the loop's fault (see :meth:`step`)."""
        if self.aborting:
            return
        self.error, self.strut = code, strut
        self.aborting = True
        self.abort_t0 = now
        io = self.io
        for i in range(6):
            io.set_controlword(i, CW_ENABLE_OPERATION)
            self.queue[i] = self.queue[i][:1] if self.sent_at[i] else []    # the answer still awaited
            self.phase[i] = _P_HALT

    def _result(self, code: int, strut: int) -> None:
        h = self.loop.sh.h
        h[S.H_HOME_STRUT] = strut
        h[S.H_HOME_RESULT] = code

    # -- the cycle ------------------------------------------------------------------------------
    def step(self, now: int) -> int:
        """One cycle: hold the targets at the measured lengths, advance each drive. Returns
        RUNNING, DONE, or an error code (< 0) once the abort finished."""
        loop = self.loop
        act, out = loop.act, loop.out
        for i in range(6):
            out[i] = act[i]
        if not self.aborting:
            self._check(now)
        busy = False
        for i in range(6):
            if self._drive(i, now):
                busy = True
        if self.aborting:
            if busy and now - self.abort_t0 < 3 * SDO_TIMEOUT_S * 1e9:
                return RUNNING
            self._result(self.error, self.strut)
            return self.error
        if busy:
            return RUNNING
        self._result(DONE, 0)
        return DONE

    def _check(self, now: int) -> None:
        loop = self.loop
        sw = self.io.statusword
        act = loop.act
        hb = getattr(self.io, "hb_ns", None)
        hb_to = loop.hb_timeout_ns
        for i in range(6):
            if sw[i] >= 0 and (sw[i] & SW_FAULT or sw[i] & SW_STATE_MASK != SW_OPERATION_ENABLED):
                return self.abort(E_FAULT, i + 1, now)
            if hb is not None and hb[i] and now - hb[i] > hb_to:
                return self.abort(E_HEARTBEAT, i + 1, now)
            if not loop.lmin[i] - 1e-6 <= act[i] <= loop.lmax[i] + 1e-6:
                return self.abort(E_LIMIT, i + 1, now)
        if now - self.t0 > HOME_TIMEOUT_S * 1e9:
            self.abort(E_TIMEOUT, 0, now)

    def _drive(self, i: int, now: int) -> bool:
        """Advance drive ``i``; True while it is not finished."""
        io = self.io
        if self.sent_at[i]:                           # an SDO request outstanding
            if io.sdo_count[i] != self.count0[i]:
                r = io.sdo_resp[i]
                self.sent_at[i] = 0
                if r[0] == 0x80 and not self.aborting:
                    self.abort(E_SDO_ABORT, i + 1, now)
                    return True
                self.queue[i].pop(0)
            elif now - self.sent_at[i] > SDO_TIMEOUT_S * 1e9:
                self.sent_at[i] = 0
                if self.aborting:
                    self.queue[i] = []
                else:
                    self.abort(E_SDO_TIMEOUT, i + 1, now)
                    return True
            else:
                return True
        if self.queue[i]:
            tq = getattr(self.loop, "torque", None)
            if tq is not None and tq.holds(i):       # a torque sample's answer is due first (.torqueread)
                return True
            self.count0[i] = io.sdo_count[i]
            if io.send_sdo(i, self.queue[i][0]):
                self.sent_at[i] = now or 1
            return True
        ph = self.phase[i]
        sw = io.statusword[i]
        if ph == _P_HALT:                             # aborted: the homing motion halted, then mode 8
            if sw >= 0 and sw & SW_TARGET_REACHED or now - self.abort_t0 > SDO_TIMEOUT_S * 1e9:
                self.queue[i] = [sdo_download(0x6060, 0, 1, MODE_CSP)]
                self.phase[i] = _P_BACK
                self.back_ns[i] = 0
            return True
        if ph == _P_SDO:                              # mode 6 written: its statusword, then bit 4
            self.phase[i] = _P_WAIT_MODE
            return True
        if ph == _P_WAIT_MODE:
            if sw >= 0 and not sw & SW_HOMING_ATTAINED and sw & SW_TARGET_REACHED:
                io.set_controlword(i, CW_HOMING_START)
                self.phase[i] = _P_WAIT_ATTAINED
            return True
        if ph == _P_WAIT_ATTAINED:
            if sw & SW_HOMING_ERROR:
                self.abort(E_HOMING_ERROR, i + 1, now)
            elif sw & SW_HOMING_ATTAINED:
                io.set_controlword(i, CW_ENABLE_OPERATION)
                self.queue[i] = [sdo_download(0x6060, 0, 1, MODE_CSP)]
                self.phase[i] = _P_BACK
                self.back_ns[i] = 0
            return True
        if ph == _P_BACK:       # mode 8 acknowledged: wait (bounded) until the statusword shows CSP following
            if not self.back_ns[i]:
                self.back_ns[i] = now or 1
            if sw >= 0 and sw & SW_DRIVE_FOLLOWS or now - self.back_ns[i] > SDO_TIMEOUT_S * 1e9:
                self.phase[i] = _P_DONE
                return False
            return True
        return False


def home_command(loop, code: int, now: int) -> bool:
    """In :meth:`HotLoop._command`: CMD_HOME (idle only), and stop/disable/shutdown while homing.
    True: handled."""
    if code == S.CMD_HOME:
        if loop.state == S.ST_IDLE and not loop.streaming:
            if loop.homer is None:
                loop.homer = HomingCycle(loop)
            loop.home_then = S.ST_IDLE
            if loop.homer.begin(now):
                loop.state = S.ST_HOMING
        else:
            loop.sh.h[S.H_HOME_STRUT] = 0
            loop.sh.h[S.H_HOME_RESULT] = E_ABORTED
        return True
    if loop.state == S.ST_HOMING and code in (S.CMD_STOP, S.CMD_DISABLE, S.CMD_SHUTDOWN):
        loop.sh.h[S.H_RING_R] = loop.sh.h[S.H_RING_W]
        if code != S.CMD_STOP:
            loop.home_then = S.ST_DISABLED
        if code == S.CMD_SHUTDOWN:
            loop.exit_after = 1
        loop.homer.abort(E_ABORTED, 0, now)
        return True
    return False


def home_step(loop, t0: int) -> None:
    """In :meth:`HotLoop.transform` while ``ST_HOMING``: one homing cycle; at its end: re-seeded
    from the measured positions (idle), or stopped (idle / disabled), or a homing fault (drives
    disabled)."""
    hm = loop.homer
    if loop.fault != F_NONE and not hm.aborting:
        hm.abort(E_ABORTED, 0, t0)
    r = hm.step(t0)
    if r == RUNNING:
        return
    if r == DONE or (r == E_ABORTED and loop.fault == F_NONE and loop.home_then == S.ST_IDLE):
        loop.seed_from_feedback()
        loop.sup.arm(t0)
        loop.resync = True
        loop.state = S.ST_IDLE
        return
    if loop.fault == F_NONE and r != E_ABORTED:
        loop.fault, loop.fault_strut, loop.fault_arg = F_HOMING, hm.strut, r
        loop.sh.h[S.H_FAULT_NS] = time.monotonic_ns()
    loop._disable()
    loop.state = S.ST_FAULT if loop.fault != F_NONE else S.ST_DISABLED
