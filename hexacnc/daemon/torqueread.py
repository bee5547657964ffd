"""Drive torque and current actual values (CiA 402 0x6077 / 0x6078), sampled by the hot loop over SDO.

Decimated and off the critical path: stepped once per cycle *after* the cycle's frames went out (with
the touch-probe latch, :mod:`.probelatch`), one non-blocking expedited SDO upload (hand-packed 8-byte
frame) at most every ``GAP_NS`` over all drives, round robin over (drive, object), the answers collected
by the cyclic I/O's ``poll``.  With six drives and two objects each drive's pair is refreshed every
``12 * GAP_NS`` (~100 ms); the bus carries at most one request and one answer per ``GAP_NS`` more, no
PDO changes (the cyclic frames' budget is untouched).

Bus budget (``hexacnc bus load`` counts one 2-byte asynchronous frame per cycle; an SDO frame has 8):
at rest (idle) the sampler runs every ``GAP_NS``; in motion (running, stopping) only when the layout's
worst case still fits ``[bus] max_load`` with an 8-byte frame in place of the 2-byte reserve
(:func:`motion_room`), and then every ``GAP_MOTION_NS`` (``hexacnc bus demand --torque-sdo-ms``: p99
unchanged).  The default layout (0.5 ms, paired, load 0.93) has no such room: no sampling in motion.
At rest the cycle's frames carry constant targets, so a cycle whose frames end late behind an SDO
frame (simulated: at most ~60 us past the period) changes nothing for the drives.

Torque in motion (``[bus] torque_pdo_every`` > 0, :mod:`drivers.torquepdo`): the drives send 0x6077 in a
decimated synchronous TPDO3, decoded by the codec (``torque_pdo_*``); :meth:`TorqueSampler.step` copies
each new value into the torque slots at every cycle, whatever the state, and the SDO sampler then reads
only the current 0x6078 (at rest).

The SDO channel is shared with homing (:mod:`.homeloop`) and the probe latch: the sampler sends only in
idle/running/stopping, never while the latch is busy or asked for, and those wait while a sample request
of the same drive is outstanding (:meth:`TorqueSampler.holds`).

A drive that aborts the upload (no 0x6077 / 0x6078: SDO abort) or does not answer ``MAX_TIMEOUTS``
times is simply not sampled again for that object: its value stays NaN, never a fault.

Shared status slots (:mod:`.shm`): ``S_TORQUE`` (6, per mille of rated torque), ``S_CURRENT`` (6, per
mille of rated current), ``S_TORQUE_T`` / ``S_CURRENT_T`` (monotonic s of the *oldest* of the six
samples, NaN until every supported drive answered once), ``S_TORQUE_MASK`` / ``S_CURRENT_MASK`` (bit
per drive with a value).  :func:`status_keys` turns them into the daemon status keys
``torque_actual_permille`` / ``current_actual_permille`` (6 values, None where a drive has none) and
``torque_actual_age_s`` / ``current_actual_age_s``.
"""
from __future__ import annotations

import math
import struct

from . import shm as S

GAP_NS = 8_000_000                  #: at rest: at most one sample request on the bus every 8 ms
GAP_MOTION_NS = 250_000_000         #: in motion (only with room in the worst-case budget): every 250 ms
SDO_TIMEOUT_NS = 100_000_000
MAX_TIMEOUTS = 3
OBJECTS = (0x6077, 0x6078)
_SLOT = (S.S_TORQUE, S.S_CURRENT)
_T_SLOT = (S.S_TORQUE_T, S.S_CURRENT_T)
_MASK = (S.S_TORQUE_MASK, S.S_CURRENT_MASK)
_UL = struct.Struct("<BHBI")
_REQ = tuple(_UL.pack(0x40, idx, 0, 0) for idx in OBJECTS)
_MOTION_STATES = (S.ST_RUNNING, S.ST_STOPPING)


def motion_room(cfg) -> bool:
    """True when the worst cycle of the layout fits ``[bus] max_load`` with an 8-byte SDO frame in place
    of the 2-byte asynchronous reserve of :func:`drivers.busload.bus_time`."""
    from drivers.busload import ASYNC_RESERVE_BYTES, bus_time, frame_time_us
    from drivers.description import bus_period_s
    try:
        bus_cfg = cfg.bus
        period = bus_period_s(bus_cfg, cfg.cycle.period_s)
        rep = bus_time(bus_cfg, period)
    except Exception:               # no layout figures (test doubles): no sampling in motion
        return False
    extra = frame_time_us(8, bus_cfg.bitrate)[1] - frame_time_us(ASYNC_RESERVE_BYTES, bus_cfg.bitrate)[1]
    return rep["max_us"] + extra <= bus_cfg.max_load * rep["period_us"]


def _pdo_every(cfg) -> int:
    try:
        return int(getattr(cfg.bus, "torque_pdo_every", 0) or 0)
    except AttributeError:          # test doubles without a [bus]
        return 0


class TorqueSampler:
    """The hot loop's side: :meth:`step` once per cycle after the frames went out."""

    def __init__(self, loop):
        self.loop = loop
        self.io = loop.io
        self.s = loop.sh.s
        self.enabled = hasattr(self.io, "send_sdo")
        self.sent_at = [0] * 6
        self.obj = [0] * 6
        self.count0 = [0] * 6
        self.supported = [[True, True] for _ in range(6)]
        self.timeouts = [[0, 0] for _ in range(6)]
        self.t_sample = [[math.nan] * 6, [math.nan] * 6]
        self.cursor = 0
        self.next_ns = 0
        self.in_motion = motion_room(loop.cfg)        #: sample while running / stopping too
        self.pdo = _pdo_every(loop.cfg) > 0 and hasattr(self.io, "torque_pdo_count")   #: 0x6077 by TPDO3
        self.pdo_seen = [0] * 6
        if self.pdo:
            for i in range(6):
                self.supported[i][0] = False          # the SDO sampler leaves 0x6077 to the TPDO3
        s = self.s
        for k in range(2):
            for i in range(6):
                s[_SLOT[k] + i] = math.nan
            s[_T_SLOT[k]] = math.nan
            s[_MASK[k]] = 0.0

    def holds(self, i: int) -> bool:
        """True while a sample request of drive ``i`` awaits its answer (other SDO users wait)."""
        return self.sent_at[i] != 0

    def step(self, now: int) -> None:
        if self.pdo:
            self._from_pdo()
        if not self.enabled:
            return
        io = self.io
        pending = False
        for i in range(6):
            if self.sent_at[i]:
                if io.sdo_count[i] != self.count0[i]:
                    self.sent_at[i] = 0
                    self._answer(i, io.sdo_resp[i], now)
                elif now - self.sent_at[i] > SDO_TIMEOUT_NS:
                    self.sent_at[i] = 0
                    k = self.obj[i]
                    self.timeouts[i][k] += 1
                    if self.timeouts[i][k] >= MAX_TIMEOUTS:
                        self.supported[i][k] = False
                else:
                    pending = True
        if pending or now < self.next_ns or not self._channel_free():
            return
        gap = GAP_MOTION_NS if self.loop.state in _MOTION_STATES else GAP_NS
        for _ in range(12):
            c = self.cursor
            self.cursor = (c + 1) % 12
            i, k = c >> 1, c & 1
            if self.supported[i][k]:
                self.count0[i] = io.sdo_count[i]
                if io.send_sdo(i, _REQ[k]):
                    self.obj[i] = k
                    self.sent_at[i] = now or 1
                self.next_ns = now + gap
                return
        self.next_ns = now + gap

    def _from_pdo(self) -> None:
        """New TPDO3 torque values into the slots (a compare per drive when nothing arrived)."""
        io = self.io
        cnt = io.torque_pdo_count
        seen = self.pdo_seen
        new = False
        for i in range(6):
            if cnt[i] != seen[i]:
                seen[i] = cnt[i]
                self.s[S.S_TORQUE + i] = float(io.torque_pdo_permille[i])
                self.t_sample[0][i] = io.torque_pdo_time_s[i]
                new = True
        if new:
            s = self.s
            ts = self.t_sample[0]
            m = 0
            oldest = math.inf
            for i in range(6):
                if ts[i] == ts[i]:
                    m |= 1 << i
                    if ts[i] < oldest:
                        oldest = ts[i]
            s[S.S_TORQUE_MASK] = float(m)
            s[S.S_TORQUE_T] = oldest if m == 0x3F else math.nan

    def _channel_free(self) -> bool:
        loop = self.loop
        st = loop.state
        if st != S.ST_IDLE and not (self.in_motion and st in _MOTION_STATES):
            return False
        latch = loop.latch
        dio = getattr(loop, "dio", None)          # program digital I/O (.dioloop) shares the channel too
        return not latch.active and self.s[S.S_PROBE_REQ] == latch.seen and not (dio is not None and dio.active)

    def _answer(self, i: int, r, now: int) -> None:
        k = self.obj[i]
        if r[0] == 0x80 or (r[0] & 0xE0) != 0x40 or (r[1] | r[2] << 8) != OBJECTS[k]:
            self.supported[i][k] = False                # abort (object absent) or a foreign answer
            return
        self.timeouts[i][k] = 0
        v = r[4] | r[5] << 8
        s = self.s
        s[_SLOT[k] + i] = float(v - 0x10000 if v & 0x8000 else v)
        ts = self.t_sample[k]
        ts[i] = now * 1e-9
        s[_MASK[k]] = float(int(s[_MASK[k]]) | (1 << i))
        sup = self.supported
        oldest = min((ts[j] for j in range(6) if sup[j][k]), default=math.nan)
        s[_T_SLOT[k]] = oldest            # NaN while a supported drive has not answered yet


def status_keys(s, now_s: float) -> dict:
    """The daemon status keys from the shared slots ``s`` (``now_s``: monotonic s)."""
    out = {}
    for name, slot, t_slot, m_slot in (("torque", S.S_TORQUE, S.S_TORQUE_T, S.S_TORQUE_MASK),
                                       ("current", S.S_CURRENT, S.S_CURRENT_T, S.S_CURRENT_MASK)):
        m = int(s[m_slot]) if s[m_slot] == s[m_slot] else 0
        if not m:
            continue
        t = s[t_slot]
        out[f"{name}_actual_permille"] = [float(s[slot + i]) if m >> i & 1 else None for i in range(6)]
        out[f"{name}_actual_age_s"] = round(now_s - t, 4) if t == t else None
    return out
