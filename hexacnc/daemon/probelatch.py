"""The drives' touch-probe latch (CiA 402 0x60B8-0x60BB), armed and read by the hot loop over SDO.

A probe move (G38.x, op ``probe``) wants the strut readings *at* the probe edge, not the next
sample's.  The drives latch their position at the edge of their touch-probe input within
microseconds (0x60BA positive edge = contact, 0x60BB negative edge = release); the hot loop fetches
the values with non-blocking expedited SDO (hand-packed 8-byte frames, at most one outstanding per
drive, answers collected by the cyclic I/O's ``poll``; the same channel as homing,
:mod:`.homeloop`), stepped once per cycle *after* the cycle's frames went out, so the critical path
(feedback, transform, frames out) never waits for it.  No PDO changes (the bus budget of the cyclic
frames is untouched); the SDO load is one request and one answer per drive every ``POLL_NS``
(2 ms) while armed, none otherwise.

Per drive: 0x60B8 = 0 (a fresh enable clears the stored values), 0x60B8 = enable | edge, then
0x60B9 read every ``POLL_NS`` until the edge's "value stored" bit, then 0x60BA (0x60BB) read.

Supervisor <-> loop through float slots of the shared status block (:mod:`.shm`):
the supervisor writes ``S_PROBE_ARM`` (0 disarm, 1 contact edge, 2 release edge) and then
increments ``S_PROBE_REQ``; the loop answers in ``S_PROBE_STATE`` (:data:`OFF`, :data:`ARMING`,
:data:`ARMED`, :data:`LATCHED` once all six values are read, or an error < 0), ``S_PROBE_MASK``
(bit per drive whose value is read), ``S_PROBE_POS`` (6: latched drive positions, increments),
``S_PROBE_ACK`` (the request served).  :func:`arm`, :func:`disarm`, :func:`read` are the
supervisor's side.
"""
from __future__ import annotations

import struct
import time

from drivers.touchprobe import FN_ENABLE, FN_NEG_EDGE, FN_POS_EDGE, ST_NEG_STORED, ST_POS_STORED

from . import shm as S

OFF, ARMING, ARMED, LATCHED = 0, 1, 2, 3
E_SDO_ABORT, E_SDO_TIMEOUT, E_UNSUPPORTED, E_BUSY = -1, -2, -3, -4
ERROR_TEXT = {E_SDO_ABORT: "a drive refused the touch-probe SDO (abort)", E_SDO_TIMEOUT: "no SDO answer",
              E_UNSUPPORTED: "this bus has no SDO channel", E_BUSY: "homing or enabling: the SDO channel is busy"}
POLL_NS = 2_000_000
SDO_TIMEOUT_NS = 100_000_000
_DL = struct.Struct("<BHBi")
_UL = struct.Struct("<BHBI")
_P_IDLE, _P_SETUP, _P_POLL, _P_VALUE, _P_DONE = range(5)


def _download(index: int, value: int) -> bytes:
    return _DL.pack(0x2B, index, 0, value)          # 2-byte expedited download (0x60B8 is UNSIGNED16)


def _upload(index: int) -> bytes:
    return _UL.pack(0x40, index, 0, 0)


class ProbeLatch:
    """The hot loop's side: :meth:`step` once per cycle (cheap when nothing is requested)."""

    def __init__(self, loop):
        self.loop = loop
        self.io = loop.io
        self.s = loop.sh.s
        self.seen = self.s[S.S_PROBE_REQ]
        self.active = False
        self.edge = 0
        self.queue: list[list[bytes]] = [[] for _ in range(6)]
        self.phase = [_P_IDLE] * 6
        self.sent_at = [0] * 6
        self.count0 = [0] * 6
        self.next_poll = [0] * 6
        self.stale = [False] * 6          #: an answer still due to a request of the previous arming

    def step(self, now: int) -> None:
        if self.s[S.S_PROBE_REQ] != self.seen:
            self._request(now)
        if self.active:
            self._advance(now)

    def _request(self, now: int) -> None:
        s = self.s
        self.seen = s[S.S_PROBE_REQ]
        edge = int(s[S.S_PROBE_ARM])
        s[S.S_PROBE_MASK] = 0.0
        if edge not in (1, 2):                       # disarm: 0x60B8 = 0 on every drive
            self.edge = 0
            self._setup([_download(0x60B8, 0)], OFF)
        elif not hasattr(self.io, "send_sdo"):
            s[S.S_PROBE_STATE] = E_UNSUPPORTED
        elif self.loop.state in (S.ST_HOMING, S.ST_BOOT):
            s[S.S_PROBE_STATE] = E_BUSY
        else:
            self.edge = edge
            fn = FN_ENABLE | (FN_POS_EDGE if edge == 1 else FN_NEG_EDGE)
            self._setup([_download(0x60B8, 0), _download(0x60B8, fn)], ARMING)
        s[S.S_PROBE_ACK] = self.seen

    def _setup(self, frames: list, state: int) -> None:
        if not hasattr(self.io, "send_sdo"):
            self.s[S.S_PROBE_STATE] = OFF
            return
        for i in range(6):
            self.stale[i] = bool(self.sent_at[i])
            self.queue[i] = list(frames)
            self.phase[i] = _P_SETUP
            self.next_poll[i] = 0
        self.active = True
        self.s[S.S_PROBE_STATE] = state

    def _fail(self, code: int) -> None:
        self.active = False
        self.s[S.S_PROBE_STATE] = code

    def _advance(self, now: int) -> None:
        io = self.io
        busy = False
        for i in range(6):
            if self.sent_at[i]:
                if io.sdo_count[i] == self.count0[i]:
                    if now - self.sent_at[i] > SDO_TIMEOUT_NS:
                        self.sent_at[i] = 0
                        return self._fail(E_SDO_TIMEOUT)
                    busy = True
                    continue
                self.sent_at[i] = 0
                r = io.sdo_resp[i]
                if self.stale[i]:
                    self.stale[i] = False
                elif r[0] == 0x80:
                    return self._fail(E_SDO_ABORT)
                else:
                    self._answer(i, r, now)
            if self.queue[i]:
                tq = getattr(self.loop, "torque", None)     # a torque sample's answer is due first
                if now >= self.next_poll[i] and (tq is None or not tq.holds(i)):
                    self.count0[i] = io.sdo_count[i]
                    if io.send_sdo(i, self.queue[i][0]):
                        self.sent_at[i] = now or 1
                busy = True
            elif self.phase[i] != _P_DONE:
                busy = True
        if not busy:
            self.active = False

    def _answer(self, i: int, r, now: int) -> None:
        """The answer to drive ``i``'s request at the head of its queue."""
        self.queue[i].pop(0)
        ph = self.phase[i]
        s = self.s
        if ph == _P_SETUP:
            if self.queue[i]:
                return
            if self.edge == 0:
                self.phase[i] = _P_DONE
                return
            self.phase[i] = _P_POLL
            self.queue[i] = [_upload(0x60B9)]
            if all(p != _P_SETUP for p in self.phase):
                s[S.S_PROBE_STATE] = ARMED
        elif ph == _P_POLL:
            stored = ST_POS_STORED if self.edge == 1 else ST_NEG_STORED
            if r[4] & stored:
                self.phase[i] = _P_VALUE
                self.queue[i] = [_upload(0x60BA if self.edge == 1 else 0x60BB)]
            else:
                self.queue[i] = [_upload(0x60B9)]
                self.next_poll[i] = now + POLL_NS
        elif ph == _P_VALUE:
            s[S.S_PROBE_POS + i] = float(int.from_bytes(bytes(r[4:8]), "little", signed=True))
            self.phase[i] = _P_DONE
            m = int(s[S.S_PROBE_MASK]) | (1 << i)
            s[S.S_PROBE_MASK] = float(m)
            if m == 0x3F:
                s[S.S_PROBE_STATE] = LATCHED


# -- the supervisor's side -------------------------------------------------------------------
def arm(sh, edge: int) -> float:
    """Ask the hot loop to arm every drive's latch (1: contact edge, 2: release edge, 0: disarm);
    returns the request number (``S_PROBE_ACK`` reaches it once the loop took it)."""
    sh.s[S.S_PROBE_ARM] = float(edge)
    req = sh.s[S.S_PROBE_REQ] + 1.0
    sh.s[S.S_PROBE_REQ] = req
    return req


def disarm(sh) -> float:
    return arm(sh, 0)


def read(sh) -> tuple[int, int, list[float]]:
    """``(state, mask of drives latched, latched positions in increments)``."""
    s = sh.s
    pos = [float(s[S.S_PROBE_POS + i]) for i in range(6)]
    return int(s[S.S_PROBE_STATE]), int(s[S.S_PROBE_MASK]), pos


def wait_state(sh, req: float, states, timeout_s: float) -> int:
    """Wait until the loop took request ``req`` and its state is one of ``states`` (or an error)."""
    t_end = time.monotonic() + timeout_s
    while True:
        st = int(sh.s[S.S_PROBE_STATE])
        if sh.s[S.S_PROBE_ACK] >= req and (st in states or st < 0):
            return st
        if time.monotonic() > t_end:
            return st
        time.sleep(0.001)
