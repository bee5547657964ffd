"""Per-cycle supervision of the drives (hot path: plain floats and ints, preallocated lists).

:class:`DriveSupervisor` is one step of the hot loop's cycle. Every cycle, for each drive, in
this order (the first finding wins and names the drive):

1. heartbeat older than ``[bus] heartbeat_timeout_ms`` (at least ``feedback_timeout_s`` plus one
   heartbeat period ``[bus] heartbeat_ms``: a stall below the bound is no fault) -> ``F_HEARTBEAT``
2. a new EMCY                                               -> ``F_EMCY``
3. boot-up or an NMT state other than Operational           -> ``F_NMT``
4. statusword: not Operation Enabled                        -> ``F_DRIVE``;
   remote (bit 9) cleared -> ``F_REMOTE``; CSP "follows the command value" (bit 12) cleared
   -> ``F_NOT_FOLLOWING``
5. a fresh position sample: compared with the command of the SYNC it answers (``io.pos_sync``,
   the SYNC ordinal the codec tagged it with; ``record`` keeps the command sent with each SYNC in
   a ring of ``n_hist`` SYNCs) -> ``F_FOLLOWING`` over ``[struts] max_following_error_mm``;
   a sample older than the ring is not compared (the stale-feedback check covers it)
6. no fresh sample within ``[cycle] feedback_timeout_s``   -> ``F_FEEDBACK`` (whatever the
   heartbeat says)

The sample answering SYNC k reports the position after the drive applied the target that came
with SYNC k; a drive that reports the position latched at the SYNC (before its interpolation step)
answers with the target of SYNC k - 1.  The error is therefore the distance from the sample to
the interval between the commands of SYNC k - 1 and k (zero at standstill, one cycle of travel
of slack in motion, never a window that grows with lost frames or stalls). SYNC ordinals count
loop cycles: on a bus that runs every n-th loop cycle (``io.sync_every``, a drive taking whole
milliseconds only) the SYNC before k is k - n, the loop cycles between them never reached a drive.
"""
from __future__ import annotations

from drivers.cia402 import SW_DRIVE_FOLLOWS, SW_REMOTE

from .faults import (F_DRIVE, F_EMCY, F_FEEDBACK, F_FOLLOWING, F_HEARTBEAT, F_NMT, F_NONE,
                     F_NOT_FOLLOWING, F_REMOTE)

#: statusword bits of "Operation enabled" (CiA 402 table: xxxx xxxx x01x 0111 under mask 0x6F)
SW_STATE_MASK = 0x6F
SW_OPERATION_ENABLED = 0x27
NMT_OPERATIONAL = 5
NMT_UNKNOWN = -1
#: findings after which the named drive no longer follows the loop's own controlled stop (lost
#: heartbeat, EMCY, NMT or CiA 402 state lost, command value not followed): it gets quick stop
#: (controlword bit 2 cleared, transition 11) at once and decelerates per 0x605A / 0x6085, while
#: the drives that still follow take the loop's jerk-limited stop
QUICK_STOP_FAULTS = frozenset((F_HEARTBEAT, F_EMCY, F_NMT, F_DRIVE, F_NOT_FOLLOWING))


def history_slots(period_s: float, span_s: float) -> int:
    """Ring size (a power of two) holding at least ``span_s`` of commands at ``period_s``."""
    n = 1
    need = int(span_s / period_s) + 2
    while n < need:
        n <<= 1
    return n


class DriveSupervisor:
    """Supervision of six drives; ``arm`` after enabling, ``record`` per SYNC, ``check`` per cycle.

    ``io``: the loop's bus object (``hb_ns``, ``emcy_count``, ``emcy_code``, ``statusword``,
    ``nmt_state``, ``pos_count``, ``pos_sync``). ``follow_mm``: 6 limits (mm);
    ``history_s``: how old a sample may be and still be compared (the longest stall accepted).
    """

    def __init__(self, io, period_s: float, follow_mm, hb_timeout_s: float, feedback_timeout_s: float,
                 history_s: float, hb_period_s: float = 0.0):
        self.io = io
        self.follow_mm = [float(v) for v in follow_mm]
        # a stall shorter than the feedback bound delays a heartbeat by up to the stall plus one
        # heartbeat period: never a fault by itself (the stale-feedback check is the bound)
        self.hb_to_ns = int(max(hb_timeout_s, feedback_timeout_s + hb_period_s) * 1e9)
        self.fb_to_ns = int(feedback_timeout_s * 1e9)
        self.n_hist = history_slots(period_s, history_s)
        self.mask = self.n_hist - 1
        self.hist = [[0.0] * self.n_hist for _ in range(6)]
        self.emcy_seen = list(io.emcy_count)
        self.pos_seen = list(io.pos_count)
        self.fresh_ns = [0] * 6
        self.follow_max = [0.0] * 6
        self.follow_now = [0.0] * 6
        self.strut = 0          #: 1-based drive of the last finding
        self.arg = 0            #: detail of the last finding (see hexacnc.daemon.faults)
        self._nmt = getattr(io, "nmt_state", None) or [NMT_UNKNOWN] * 6
        self._sync = getattr(io, "pos_sync", None) or [0] * 6
        #: loop cycles per bus cycle: a sample lies between the commands of its SYNC and the one before
        self._step = int(getattr(io, "sync_every", 1))

    def fill(self, lengths) -> None:
        """Every slot of the command history = ``lengths`` (standstill, after seeding)."""
        for i in range(6):
            h = self.hist[i]
            v = lengths[i]
            for k in range(self.n_hist):
                h[k] = v

    def arm(self, now_ns: int) -> None:
        """Start supervising from now (after enabling or re-enabling): old EMCYs and samples are
        history, every drive gets a full feedback time-out for its first sample."""
        io = self.io
        for i in range(6):
            self.emcy_seen[i] = io.emcy_count[i]
            self.pos_seen[i] = io.pos_count[i]
            self.fresh_ns[i] = now_ns
            self.follow_max[i] = 0.0

    def record(self, k: int, out) -> None:
        """The commands (mm) sent with SYNC ordinal ``k``."""
        j = k & self.mask
        hist = self.hist
        for i in range(6):
            hist[i][j] = out[i]

    def check(self, now_ns: int, act, sends: int) -> int:
        """One cycle's supervision; ``act``: measured lengths (mm) of the samples in ``io.pos``;
        ``sends``: SYNCs sent so far. Returns ``F_NONE`` or a fault code (``strut``, ``arg`` set)."""
        io = self.io
        hb_ns = io.hb_ns
        emcy_count = io.emcy_count
        statusword = io.statusword
        pos_count = io.pos_count
        nmt = self._nmt
        sync = self._sync
        for i in range(6):
            hb = hb_ns[i]
            if now_ns - hb > self.hb_to_ns:
                return self._found(F_HEARTBEAT, i, (now_ns - hb) // 1_000_000 if hb else -1)
            if emcy_count[i] != self.emcy_seen[i]:
                self.emcy_seen[i] = emcy_count[i]
                return self._found(F_EMCY, i, io.emcy_code[i])
            st = nmt[i]
            if st != NMT_OPERATIONAL and st != NMT_UNKNOWN:
                return self._found(F_NMT, i, st)
            sw = statusword[i]
            if (sw & SW_STATE_MASK) != SW_OPERATION_ENABLED:
                return self._found(F_DRIVE, i, sw)
            if not sw & SW_REMOTE:
                return self._found(F_REMOTE, i, sw)
            if not sw & SW_DRIVE_FOLLOWS:
                return self._found(F_NOT_FOLLOWING, i, sw)
            if pos_count[i] != self.pos_seen[i]:
                self.pos_seen[i] = pos_count[i]
                self.fresh_ns[i] = now_ns
                k = sync[i]
                if 0 < k <= sends and sends - k < self.n_hist - self._step:   # both commands still held
                    h = self.hist[i]
                    c1 = h[k & self.mask]
                    c0 = h[(k - self._step) & self.mask]
                    a = act[i]
                    lo, hi = (c0, c1) if c0 < c1 else (c1, c0)
                    e = lo - a if a < lo else (a - hi if a > hi else 0.0)
                    self.follow_now[i] = e
                    if e > self.follow_max[i]:
                        self.follow_max[i] = e
                    if e > self.follow_mm[i]:
                        return self._found(F_FOLLOWING, i, int(e * 1000.0))
            elif now_ns - self.fresh_ns[i] > self.fb_to_ns:
                return self._found(F_FEEDBACK, i, (now_ns - self.fresh_ns[i]) // 1_000_000)
        return F_NONE

    def _found(self, code: int, i: int, arg: int) -> int:
        self.strut = i + 1
        self.arg = arg
        return code


def following_limits_mm(cfg) -> list[float]:
    """Per-strut following-error limits (mm): ``[struts] max_following_error_mm``, else
    ``[cycle] following_error_mm`` for every strut."""
    v = getattr(cfg, "max_following_error_mm", None)
    if v is None:
        return [float(cfg.cycle.following_error_mm)] * 6
    return [float(x) for x in v]
