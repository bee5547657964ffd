"""Cycle statistics of the hot loop: lateness and compute histograms, overruns, per-phase times.

Written into the shared status block (:mod:`.shm`) for the supervisor's ``status`` → ``cycle``.
Phases (``shm.PHASE_NAMES``): poll, supervise, transform, send, feedback, stats.
"""
from __future__ import annotations

from . import shm as S
from .enablewalk import op_enabled

N_PHASES = S.N_PHASES


class CycleStats:
    """Counters of one :meth:`HotLoop.run` (plain ints, preallocated lists)."""

    def __init__(self, sh: S.Shared, period_ns: int):
        self.sh = sh
        self.h = sh.h
        self.period = period_ns
        self.hist_late = sh.hist_late
        self.hist_comp = sh.hist_comp
        self.ps = [0] * N_PHASES      #: summed ns per phase since the last reset
        self.pm = [0] * N_PHASES      #: longest ns per phase
        self.overruns = 0
        self.in_row = 0
        self.max_row = 0
        self.lat_max = 0
        self.comp_max = 0
        self.cycles = 0

    def phase(self, k: int, d: int) -> None:
        self.ps[k] += d
        if d > self.pm[k]:
            self.pm[k] = d

    def reset(self) -> None:
        """Statistics afresh (``CMD_STATS_RESET``; the supervisor zeroes the histograms)."""
        h = self.h
        self.overruns = self.in_row = self.max_row = self.lat_max = self.comp_max = 0
        for j in range(N_PHASES):
            self.ps[j] = 0
            self.pm[j] = 0
        for j in range(2 * N_PHASES):
            h[S.H_PHASE_SUM_NS + j] = 0
        h[S.H_OVERRUNS] = 0
        h[S.H_MAX_IN_ROW] = 0
        h[S.H_LAT_MAX_NS] = 0
        h[S.H_COMP_MAX_NS] = 0
        h[S.H_STATS_CYCLES0] = self.cycles

    def account(self, t0: int, t1: int, deadline: int, resync: bool) -> int:
        """One cycle that started at ``t0`` (due at ``deadline``) and ended at ``t1``; returns
        the next deadline. ``resync``: a slow-path cycle (enable, reseed) realigns, no overrun."""
        h = self.h
        late = t0 - deadline
        comp = t1 - t0
        k = late // 1000
        self.hist_late[k if k < 4095 else 4095] += 1
        k = comp // 1000
        self.hist_comp[k if k < 4095 else 4095] += 1
        if late > self.lat_max:
            self.lat_max = late
            h[S.H_LAT_MAX_NS] = late
        if comp > self.comp_max:
            self.comp_max = comp
            h[S.H_COMP_MAX_NS] = comp
        self.cycles += 1
        h[S.H_CYCLES] = self.cycles
        period = self.period
        deadline += period
        if resync:
            if t1 > deadline:
                deadline = t1 + period
        elif t1 > deadline:
            missed = (t1 - deadline) // period + 1
            deadline += (missed - 1) * period
            self.overruns += missed
            self.in_row += missed
            h[S.H_OVERRUNS] = self.overruns
            if self.in_row > self.max_row:
                self.max_row = self.in_row
                h[S.H_MAX_IN_ROW] = self.max_row
        else:
            self.in_row = 0
        return deadline

    def publish_phases(self) -> None:
        h = self.h
        for j in range(N_PHASES):
            h[S.H_PHASE_SUM_NS + j] = self.ps[j]
            h[S.H_PHASE_MAX_NS + j] = self.pm[j]


def publish_status(self) -> None:
    """Write the hot loop ``self``'s status block (poses, struts, following error, statuswords,
    drive states, thermal offsets, travel) under the seqlock ``H_STATUS_SEQ``."""

    sh = self.sh
    h = sh.h
    s = sh.s
    ct = self.ct
    h[S.H_STATUS_SEQ] += 1
    h[S.H_STATUS_CYCLE] = h[S.H_CYCLES]
    h[S.H_STATE] = self.state
    h[S.H_FAULT] = self.fault
    h[S.H_FAULT_STRUT] = self.fault_strut
    h[S.H_FAULT_ARG] = self.fault_arg
    h[S.H_LINE] = self.line
    pc = ct.pose_cmd
    pa = ct.pose_act
    out = self.out
    act = self.act
    io = self.io
    fm = self.follow_max
    l0 = self.l0
    l1 = self.l1
    inv_dt = 1.0 / self.dt
    for i in range(6):
        s[S.S_POSE_CMD + i] = pc[i]
        s[S.S_POSE_ACT + i] = pa[i]
        s[S.S_STRUT_CMD + i] = out[i]
        s[S.S_STRUT_ACT + i] = act[i]
        s[S.S_FOLLOW_MAX + i] = fm[i]
        s[S.S_STRUT_VEL + i] = (l0[i] - l1[i]) * inv_dt
        h[S.H_STATUSWORDS + i] = io.statusword[i]
        h[S.H_DRIVE_STATE + i] = 1 if op_enabled(io.statusword[i]) else 0
    s[S.S_FK_RES] = ct.fk_residual_mm
    tr = self.travel
    th = ct.thermal_mm
    for i in range(6):
        s[S.S_TRAVEL + i] = tr[i]
        s[S.S_THERMAL_APP + i] = th[i]
    s[S.S_SPINDLE_APP] = ct.spindle_growth_mm
    h[S.H_BOOTUPS] = getattr(io, "bootups", 0)             # reference trust (hexacnc.daemon.reference)
    h[S.H_ENCODER_ERRORS] = getattr(io, "encoder_errors", 0)
    h[S.H_STATUS_SEQ] += 1
