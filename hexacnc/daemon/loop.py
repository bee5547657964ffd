"""The hot loop: a process that runs only the fixed-period cycle.

Started by the supervisor (:mod:`hexacnc.daemon.core`) with the ``spawn`` start
method, so nothing of the supervisor (threads, sockets, the planner) lives here.
Per cycle, on plain floats and preallocated lists:

1. sleep until ``[cycle] spin_s`` before the absolute deadline (``time.monotonic_ns``), spin to it;
2. ``io.poll`` - feedback frames (positions, statuswords, heartbeats, EMCY) of the previous SYNC;
3. supervision: heartbeat age, EMCY, drive state, following error of each strut;
4. next setpoint from the shared ring (hold the last pose when empty after an END row);
5. ``CycleTransform.command`` (IK, sag, thermal, length/joint/velocity/acceleration guard);
6. drive increments -> ``io.send`` (targets, then SYNC);
7. ``CycleTransform.feedback`` (FK of the measured lengths) and the status block.

A fault switches to the controlled stop (:class:`~hexacnc.daemon.stopgen.StrutStop`:
jerk-limited per strut, from the commanded motion to standstill), then the drives
are disabled by controlword and the fault latched until ``CMD_RESET``.

The bus object ``io`` is duck-typed (see :class:`IOProtocol`); :mod:`hexacnc.daemon.busio`
builds it from ``drivers.cyclic`` and boots the drives before the loop starts.
"""
from __future__ import annotations

import gc
import logging
import math
import os
import time
from typing import Protocol

from drivers.cia402 import (CW_DISABLE_VOLTAGE, CW_ENABLE_OPERATION, CW_FAULT_RESET, CW_SHUTDOWN,
                            CW_SWITCH_ON)

from ..transform import CycleTransform, OK as CT_OK
from . import shm as S
from .faults import (F_DEADLINE, F_DRIVE, F_EMCY, F_ENABLE, F_FEEDBACK, F_FOLLOWING, F_HEARTBEAT, F_LIMIT,
                     F_NMT, F_NONE, F_NOT_FOLLOWING, F_REMOTE, F_SETPOINT, F_SIGNAL, F_SUPERVISOR, F_BUS,
                     F_TEST, fault_code_name)
from .stopgen import StrutStop
from .supervise import DriveSupervisor, following_limits_mm

log = logging.getLogger("hexacnc.loop")

#: The loop sleeps until ``[cycle] spin_s`` (default 200 us) before each deadline, then spins; at
#: most SPIN_FRACTION of the period (SCHED_FIFO throttling, 95 % by default, the hot CPU's kernel
#: threads and everything else on the machine need the rest).  The VM's sleep overshoot often
#: exceeds 100 us: in 20 s of the bare loop (hexacnc.daemon.rt) with 45 us of work, 2513 / 696 / 65
#: wake-ups were late by over 100 us with a 100 / 200 / 350 us spin.  350 us suits a CPU that is
#: the hot loop's alone; on a loaded 2-CPU machine it starved the rest (the supervisor's feeder
#: missed refills) and, with a second daemon on the same CPU, ran into SCHED_FIFO throttling.
SPIN_FRACTION = 0.8
#: publish the status block every n cycles (and on every state change)
PUBLISH_EVERY = 8
#: time allowed for the CiA 402 enable walk (ns)
ENABLE_TIMEOUT_NS = 2_000_000_000
#: a strut command step below this (mm per cycle) counts as standstill
STANDSTILL_MM = 1e-7
#: a stop that ends with the drives disabled waits until every measured length is this close to its
#: final command (mm), at most SETTLE_NS
SETTLE_MM = 0.0003
SETTLE_NS = 100_000_000
#: thermal/spindle growth offsets are slewed at most this fast (mm/s), every THERMAL_EVERY cycles
THERMAL_SLEW_MM_S = 0.002
THERMAL_EVERY = 16

# test-only commands: stall the loop for arg microseconds once (deadline-burst test); raise in the
# cycle (a crashing hot loop: the drives must stop on their own, the supervisor must notice)
CMD_STALL = 16
CMD_CRASH = 17
#: the supervisor's presence is checked every this many cycles (getppid) besides the parent-death signal
SUPERVISOR_CHECK_EVERY = 32
#: the history of commands the following-error check matches samples to covers the feedback
#: time-out plus this margin (s)
HISTORY_MARGIN_S = 0.05

#: set by the signal handlers of the hot process (:func:`install_signal_handlers`): [0] the signal
#: that asks for a controlled stop (SIGTERM, SIGHUP), [1] 1 once the parent-death signal came
SIGNALS = [0, 0]


def install_signal_handlers(pdeath_signal: int | None = None) -> None:
    """Hot process: SIGINT ignored (Ctrl-C reaches the whole process group: the supervisor orders
    the stop), SIGTERM/SIGHUP ask the loop for a controlled stop and exit, ``pdeath_signal`` (the
    kernel sends it when the supervisor dies, see :func:`set_parent_death_signal`) marks it gone.
    The handlers only set :data:`SIGNALS`; the cycle acts on them."""
    import signal

    def ask_stop(signum, frame):
        SIGNALS[0] = signum

    def parent_died(signum, frame):
        SIGNALS[1] = 1

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, ask_stop)
    signal.signal(signal.SIGHUP, ask_stop)
    if pdeath_signal:
        signal.signal(pdeath_signal, parent_died)


def set_parent_death_signal(signum: int) -> bool:
    """``prctl(PR_SET_PDEATHSIG, signum)``: the kernel signals this process when its parent dies
    (Linux; False where unavailable - the periodic ``getppid`` check remains)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(signum), 0, 0, 0) == 0     # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        return False


class IOProtocol(Protocol):
    """What the loop needs from the bus codec (all lists preallocated, length 6)."""
    target: list        #: int increments, written by the loop before send()
    pos: list           #: int increments from TPDO1
    pos_count: list     #: int, TPDO1 frames received per drive
    statusword: list    #: int, from TPDO2 (-1 until the first)
    hb_ns: list         #: int, monotonic ns of the last heartbeat (0: none yet)
    emcy_count: list    #: int, EMCY frames received per drive
    emcy_code: list     #: int, last EMCY error code
    bus_load: float     #: worst-case load of the layout (fraction of the period)

    def poll(self, now_ns: int) -> int: ...
    def send(self) -> int: ...
    def set_controlword(self, i: int, cw: int) -> None: ...
    def emcy_text(self, i: int) -> str: ...
    def close(self) -> None: ...


def spin_ns(period_ns: int, spin_s: float) -> int:
    """How long before each deadline the loop stops sleeping and spins (ns): ``[cycle] spin_s``,
    at most ``SPIN_FRACTION`` of the period."""
    return min(int(round(spin_s * 1e9)), int(SPIN_FRACTION * period_ns))


def _op_enabled(sw: int) -> bool:
    return sw >= 0 and (sw & 0x6F) == 0x27


def _next_cw(sw: int, prev_cw: int) -> int:
    """Controlword that moves a drive with statusword ``sw`` one step towards Operation Enabled."""
    if sw < 0 or (sw & 0x4F) == 0:                 # unknown / not ready: wait
        return prev_cw
    if sw & 0x08:                                  # fault: rising edge on bit 7 (transition 15)
        return CW_FAULT_RESET if prev_cw != CW_FAULT_RESET else CW_DISABLE_VOLTAGE
    if (sw & 0x4F) == 0x40:                        # switch on disabled -> 2
        return CW_SHUTDOWN
    if (sw & 0x6F) == 0x21:                        # ready to switch on -> 3
        return CW_SWITCH_ON
    if (sw & 0x6F) == 0x23:                        # switched on -> 4
        return CW_ENABLE_OPERATION
    if (sw & 0x6F) == 0x07:                        # quick stop active -> 12 (disable voltage)
        return CW_DISABLE_VOLTAGE
    return CW_ENABLE_OPERATION


class HotLoop:
    """The cycle. ``run()`` returns when told to shut down."""

    def __init__(self, cfg, sh: S.Shared, io: IOProtocol, ct: CycleTransform | None = None,
                 priv: dict | None = None, period_s: float | None = None):
        self.cfg = cfg
        self.sh = sh
        self.io = io
        self.ct = ct if ct is not None else CycleTransform(cfg, period_s=period_s)
        self.priv = priv or {}
        self.period_ns = int(round((period_s or cfg.cycle.period_s) * 1e9))
        self.dt = self.period_ns * 1e-9
        self.spin_ns = spin_ns(self.period_ns, float(getattr(cfg.cycle, "spin_s", 0.0002)))
        cy = cfg.cycle
        bus = cfg.bus
        self.ipm = float(bus.increments_per_mm)
        self.off = [float(v) for v in cfg.strut_offset_mm]
        self.hb_timeout_ns = int(bus.heartbeat_timeout_ms * 1_000_000)
        fb_to = float(getattr(cy, "feedback_timeout_s", 0.35))
        self.sup = DriveSupervisor(io, self.dt, following_limits_mm(cfg), bus.heartbeat_timeout_ms * 1e-3,
                                   fb_to, fb_to + HISTORY_MARGIN_S)
        self.max_in_row = int(cy.max_overruns_in_row)
        self.sp_timeout_ns = int(cy.setpoint_timeout_s * 1e9)
        self.stop = StrutStop(cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2, cfg.max_jerk_mm_s3,
                              cfg.min_length_mm, cfg.max_length_mm, self.dt)
        self.lmin = [float(v) for v in cfg.min_length_mm]
        self.lmax = [float(v) for v in cfg.max_length_mm]
        # preallocated state
        self.out = [0.0] * 6          # strut command this cycle, mm
        self.l0 = [0.0] * 6           # command history (last, one before, two before)
        self.l1 = [0.0] * 6
        self.l2 = [0.0] * 6
        self.act = [0.0] * 6          # measured lengths, mm
        self.hold = [0.0] * 6         # pose held when the ring is empty (mm, rad)
        self.cw = [-1] * 6            # last controlword requested per drive
        self.follow_max = self.sup.follow_max
        self.exit_signal = 0          # signal that ordered the stop and exit (0: none)
        self.settle_t0 = 0            # when the commands of a stop that ends disabled came to rest
        self.state = S.ST_BOOT
        self.fault = F_NONE
        self.fault_strut = 0
        self.fault_arg = 0
        self.fault_text = ""
        self.after_stop = S.ST_IDLE   # state once the controlled stop is done
        self.streaming = False
        self.starve_ns = 0
        self.enable_t0 = 0
        self.line = 0
        self.cmd_seen = sh.h[S.H_CMD_SEQ]
        self.exit_after = -1
        self.resync = False
        self.stats_reset = False
        self.travel = [0.0] * 6
        self.sends = 0

    # ------------------------------------------------------------------ slow path helpers
    def _lengths_from_pos(self, out) -> None:
        io = self.io
        for i in range(6):
            out[i] = io.pos[i] / self.ipm + self.off[i]

    def seed_from_feedback(self) -> None:
        """Standstill at the measured position: command = actual, guards and FK re-seeded."""
        self._lengths_from_pos(self.act)
        hx = self.ct.hx
        ct = self.ct
        # slow-path FK from the home pose (numpy), then the hot path takes over
        phys = ct.strut_map.strut_from_drive(self.act)      # [calibration] map (identity: a copy)
        geo = [float(phys[i]) + ct.sag_mm[i] + ct.thermal_mm[i] for i in range(6)]
        res = hx.forward(geo)
        X = [float(res.pose[0]), float(res.pose[1]), float(res.pose[2]),
             math.radians(res.pose[3]), math.radians(res.pose[4]), math.radians(res.pose[5])]
        ct.forget_motion()
        code = ct.command(*X)
        if code != CT_OK:
            log.error("hot loop: measured position is outside the limits: %s", ct.describe(code))
        # the sag depends on the pose: one more FK pass with the sag at this pose
        ct.reset_pose(X)
        ct.feedback(self.act)
        X = list(ct.pose_act)
        ct.forget_motion()
        ct.command(*X)
        ct.reset(ct.cmd_mm)
        ct.reset_pose(X)
        for i in range(6):
            self.hold[i] = X[i]
            self.out[i] = ct.cmd_mm[i]
            self.l0[i] = self.l1[i] = self.l2[i] = ct.cmd_mm[i]
        self.sup.fill(self.l0)
        self.streaming = False

    def _rehold_from(self, lengths) -> None:
        """After a stop: hold the pose whose commands are ``lengths`` (FK), guards at standstill."""
        ct = self.ct
        ct.feedback(lengths)          # pose of the commanded lengths
        X = ct.pose_act
        for i in range(6):
            self.hold[i] = X[i]
        ct.command(X[0], X[1], X[2], X[3], X[4], X[5])
        ct.reset(lengths)
        for i in range(6):
            self.out[i] = lengths[i]
        self.streaming = False

    def _fault(self, code: int, strut: int, arg: int) -> None:
        """Latch a fault and start the controlled stop (first fault wins)."""
        if self.fault == F_NONE:
            self.fault = code
            self.fault_strut = strut
            self.fault_arg = arg
            self.fault_text = ""
            self.sh.h[S.H_FAULT_NS] = time.monotonic_ns()
        if self.state in (S.ST_IDLE, S.ST_RUNNING):
            self.stop.start(self.l0, self.l1, self.l2)
            self.state = S.ST_STOPPING
        self.after_stop = S.ST_FAULT

    def _settled(self, now: int) -> bool:
        """After a stop that ends disabled: True once every measured length is within
        ``SETTLE_MM`` of its final command, or ``SETTLE_NS`` after the commands stopped (a drive
        that does not follow is disabled anyway). Disabling a strut still catching up with its
        command would leave the next enable's targets (the measured positions) a step away from
        the last commands."""
        if self.settle_t0 == 0:
            self.settle_t0 = now
        if now - self.settle_t0 <= SETTLE_NS:
            act = self.act
            out = self.out
            for i in range(6):
                d = act[i] - out[i]
                if d > SETTLE_MM or d < -SETTLE_MM:
                    return False
        self.settle_t0 = 0
        return True

    def _disable(self) -> None:
        for i in range(6):
            self.io.set_controlword(i, CW_DISABLE_VOLTAGE)
            self.cw[i] = CW_DISABLE_VOLTAGE

    def _command(self, code: int, arg: int, now: int) -> None:
        st = self.state
        if code == S.CMD_STOP:
            self.sh.h[S.H_RING_R] = self.sh.h[S.H_RING_W]
            if st in (S.ST_IDLE, S.ST_RUNNING):
                self.stop.start(self.l0, self.l1, self.l2)
                self.state = S.ST_STOPPING
                self.after_stop = S.ST_IDLE
        elif code == S.CMD_RESET:
            if st in (S.ST_FAULT, S.ST_DISABLED):
                self.fault = F_NONE
                self.fault_strut = self.fault_arg = 0
                self.sh.h[S.H_RING_R] = self.sh.h[S.H_RING_W]
                self.state = S.ST_BOOT
                self.enable_t0 = now
                self.sup.arm(now)
        elif code in (S.CMD_SHUTDOWN, S.CMD_DISABLE):
            self.sh.h[S.H_RING_R] = self.sh.h[S.H_RING_W]
            if st in (S.ST_IDLE, S.ST_RUNNING):
                self.stop.start(self.l0, self.l1, self.l2)
                self.state = S.ST_STOPPING
                self.after_stop = S.ST_DISABLED
            elif st == S.ST_STOPPING and self.after_stop == S.ST_IDLE:
                self.after_stop = S.ST_DISABLED
            elif st in (S.ST_BOOT,):
                self._disable()
                self.state = S.ST_DISABLED
            if code == S.CMD_SHUTDOWN:
                self.exit_after = 1
        elif code == S.CMD_FAULT_TEST:
            self._fault(F_TEST, 0, arg)
        elif code == S.CMD_STATS_RESET:
            self.stats_reset = True
        elif code == CMD_STALL:
            time.sleep(arg * 1e-6)
        elif code == CMD_CRASH:
            raise RuntimeError("hot loop crash requested by a test command")

    def _on_signal(self, signum: int) -> None:
        """SIGTERM/SIGHUP to the hot process: controlled stop, drives disabled, exit (as
        CMD_SHUTDOWN; the signal is reported in ``H_EXIT_SIGNAL``)."""
        self.exit_signal = signum
        self.sh.h[S.H_EXIT_SIGNAL] = signum
        self._command(S.CMD_SHUTDOWN, 0, 0)

    def publish(self, t0: int) -> None:
        sh = self.sh
        h = sh.h
        s = sh.s
        ct = self.ct
        h[S.H_STATUS_SEQ] += 1
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
            h[S.H_DRIVE_STATE + i] = 1 if _op_enabled(io.statusword[i]) else 0
        s[S.S_FK_RES] = ct.fk_residual_mm
        tr = self.travel
        th = ct.thermal_mm
        for i in range(6):
            s[S.S_TRAVEL + i] = tr[i]
            s[S.S_THERMAL_APP + i] = th[i]
        s[S.S_SPINDLE_APP] = ct.spindle_growth_mm
        h[S.H_STATUS_SEQ] += 1

    # ------------------------------------------------------------------ the cycle
    def run(self, max_cycles: int = -1) -> int:
        sh = self.sh
        h = sh.h
        ring = sh.ring
        hist_late = sh.hist_late
        hist_comp = sh.hist_comp
        io = self.io
        ct = self.ct
        stop = self.stop
        out = self.out
        act = self.act
        hold = self.hold
        l0 = self.l0
        l1 = self.l1
        l2 = self.l2
        off = self.off
        ipm = self.ipm
        inv_ipm = 1.0 / ipm
        target = io.target
        pos = io.pos
        pos_count = io.pos_count
        travel = self.travel
        shs = sh.s
        th_step = float(getattr(self.cfg.thermal, "max_offset_rate_mm_s", THERMAL_SLEW_MM_S)) * self.dt * THERMAL_EVERY
        th_app = ct.thermal_mm
        # drive supervision (heartbeat, EMCY, NMT, statusword, following error matched to the SYNC
        # each sample answers, stale feedback): hexacnc.daemon.supervise
        sup = self.sup
        sup.fill(self.l0)
        record = sup.record
        supervise = sup.check
        sends = self.sends          # SYNCs sent (ordinal of the last one; the codec tags samples with it)
        statusword = io.statusword
        sigs = SIGNALS
        period = self.period_ns
        max_in_row = self.max_in_row
        sp_timeout = self.sp_timeout_ns
        mono = time.monotonic_ns
        sleep = time.sleep
        spin = self.spin_ns
        mask = S.RING_ROWS - 1
        ROW = S.ROW
        lmin = self.lmin
        lmax = self.lmax
        lo_inc = [math.ceil((lmin[i] - off[i]) * ipm - 1e-9) for i in range(6)]
        hi_inc = [math.floor((lmax[i] - off[i]) * ipm + 1e-9) for i in range(6)]
        ST_IDLE, ST_RUNNING, ST_STOPPING, ST_FAULT, ST_DISABLED, ST_BOOT = (
            S.ST_IDLE, S.ST_RUNNING, S.ST_STOPPING, S.ST_FAULT, S.ST_DISABLED, S.ST_BOOT)

        s_bus = getattr(io, "bus_load", 0.0)
        sh.s[S.S_BUS_LOAD] = s_bus
        sh.s[S.S_PERIOD] = self.dt
        h[S.H_PID] = os.getpid()
        ppid = self.sh.h[S.H_SUP_PID] or os.getppid()
        if os.getppid() != ppid:
            sigs[1] = 1                 # the supervisor died before we could watch it
        overruns = 0
        in_row = 0
        max_row = 0
        lat_max = 0
        comp_max = 0
        cycles = 0
        last_state = -1
        # per-phase compute time (ns): sums and maxima since the last statistics reset
        ps0 = ps1 = ps2 = ps3 = ps4 = ps5 = 0
        pm0 = pm1 = pm2 = pm3 = pm4 = pm5 = 0
        H_PS = S.H_PHASE_SUM_NS
        H_PM = S.H_PHASE_MAX_NS
        t_end = 0
        if self.state == ST_BOOT:
            self.enable_t0 = mono()

        gc.collect()
        gc.freeze()
        gc.disable()
        deadline = mono() + period
        try:
            while True:
                # ---------------------------------------------------------- wait
                rem = deadline - mono()
                if rem > spin:
                    sleep((rem - spin) * 1e-9)
                while mono() < deadline:
                    pass
                t0 = mono()
                if t_end:                   # the previous cycle's statistics and publishing
                    d = t_end - t1
                    ps5 += d
                    if d > pm5:
                        pm5 = d
                h[S.H_LOOP_BEAT_NS] = t0
                if sigs[0] or sigs[1] or (cycles & (SUPERVISOR_CHECK_EVERY - 1)) == 0:
                    self._check_signals(t0, ppid)
                # ---------------------------------------------------------- feedback in
                io.poll(t0)
                for i in range(6):
                    act[i] = pos[i] * inv_ipm + off[i]
                seq = h[S.H_CMD_SEQ]
                if seq != self.cmd_seen:
                    self.cmd_seen = seq
                    self._command(h[S.H_CMD], h[S.H_CMD_ARG], t0)
                    h[S.H_CMD_ACK] = seq
                    if self.stats_reset:
                        self.stats_reset = False
                        overruns = in_row = max_row = lat_max = comp_max = 0
                        ps0 = ps1 = ps2 = ps3 = ps4 = ps5 = 0
                        pm0 = pm1 = pm2 = pm3 = pm4 = pm5 = 0
                        for j in range(2 * S.N_PHASES):
                            h[H_PS + j] = 0
                        h[S.H_OVERRUNS] = 0
                        h[S.H_MAX_IN_ROW] = 0
                        h[S.H_LAT_MAX_NS] = 0
                        h[S.H_COMP_MAX_NS] = 0
                        h[S.H_STATS_CYCLES0] = cycles
                state = self.state
                ta = mono()
                d = ta - t0
                ps0 += d
                if d > pm0:
                    pm0 = d
                # ---------------------------------------------------------- supervision
                if state == ST_RUNNING or state == ST_IDLE:
                    code = supervise(t0, act, sends)
                    if code:
                        self._fault(code, sup.strut, sup.arg)
                        state = self.state
                # ---------------------------------------------------------- thermal / spindle offsets
                if (cycles & (THERMAL_EVERY - 1)) == 0 and state != ST_STOPPING:
                    for i in range(6):
                        d = shs[S.S_THERMAL_TGT + i] - th_app[i]
                        if d != 0.0:
                            th_app[i] += th_step if d > th_step else (-th_step if d < -th_step else d)
                    d = shs[S.S_SPINDLE_TGT] - ct.spindle_growth_mm
                    if d != 0.0:
                        ct.spindle_growth_mm += th_step if d > th_step else (-th_step if d < -th_step else d)
                # ---------------------------------------------------------- setpoint + transform
                tb = mono()
                d = tb - ta
                ps1 += d
                if d > pm1:
                    pm1 = d
                if state == ST_RUNNING or state == ST_IDLE:
                    r = h[S.H_RING_R]
                    if r < h[S.H_RING_W]:
                        b = (r & mask) * ROW
                        hold[0] = ring[b]
                        hold[1] = ring[b + 1]
                        hold[2] = ring[b + 2]
                        hold[3] = ring[b + 3]
                        hold[4] = ring[b + 4]
                        hold[5] = ring[b + 5]
                        self.line = int(ring[b + 6])
                        self.streaming = not (int(ring[b + 7]) & S.FLAG_END)
                        h[S.H_RING_R] = r + 1
                        self.starve_ns = 0
                        if state == ST_IDLE:
                            state = self.state = ST_RUNNING
                        if not self.streaming:
                            h[S.H_END_SEEN] = r + 1
                    elif self.streaming:
                        moving = False
                        for i in range(6):
                            d = l0[i] - l1[i]
                            if d > STANDSTILL_MM or d < -STANDSTILL_MM:
                                moving = True
                        if moving:
                            h[S.H_UNDERRUNS] += 1
                            self._fault(F_SETPOINT, 0, 1)
                        elif self.starve_ns == 0:
                            self.starve_ns = t0
                        elif t0 - self.starve_ns > sp_timeout:
                            self._fault(F_SETPOINT, 0, 2)
                        state = self.state
                    elif state == ST_RUNNING:
                        state = self.state = ST_IDLE
                if state == ST_RUNNING or state == ST_IDLE:
                    code = ct.command(hold[0], hold[1], hold[2], hold[3], hold[4], hold[5])
                    if code == CT_OK:
                        cm = ct.cmd_mm
                        for i in range(6):
                            out[i] = cm[i]
                    else:
                        self._fault(F_LIMIT, ct.fail_index + 1, code)
                        sh.s[S.S_FAULT_VALUE] = ct.fail_value
                        state = self.state
                if state == ST_STOPPING:
                    if not stop.step(out):
                        if self.after_stop == ST_IDLE:
                            self._rehold_from(out)
                            state = self.state = ST_IDLE
                        elif self._settled(t0):     # disable once the struts stand where commanded
                            self._disable()
                            state = self.state = self.after_stop
                elif state == ST_BOOT:
                    # enable walk: the targets track the actual positions so enabling moves nothing
                    for i in range(6):
                        v = act[i]
                        out[i] = lmin[i] if v < lmin[i] else (lmax[i] if v > lmax[i] else v)
                    all_on = True
                    for i in range(6):
                        if pos_count[i] == 0:       # no position yet: never enable blind
                            all_on = False
                            break
                        if act[i] < lmin[i] or act[i] > lmax[i]:
                            all_on = False
                            if t0 - self.enable_t0 > ENABLE_TIMEOUT_NS // 4:
                                self.enable_t0 = -ENABLE_TIMEOUT_NS   # refuse now
                            break
                    for i in range(6 if all_on else 0):
                        sw = statusword[i]
                        if not _op_enabled(sw):
                            all_on = False
                            cw = _next_cw(sw, self.cw[i])
                            if cw != self.cw[i]:
                                io.set_controlword(i, cw)
                                self.cw[i] = cw
                    if all_on:
                        for i in range(6):
                            if not _op_enabled(statusword[i]):
                                all_on = False
                    if all_on:
                        for i in range(6):
                            io.set_controlword(i, CW_ENABLE_OPERATION)
                            self.cw[i] = CW_ENABLE_OPERATION
                        self.seed_from_feedback()
                        sup.arm(t0)
                        self.resync = True
                        state = self.state = ST_IDLE
                        h[S.H_READY] = 1
                    elif t0 - self.enable_t0 > ENABLE_TIMEOUT_NS:
                        bad = 0
                        arg = 0
                        for i in range(6):
                            if pos_count[i] == 0:
                                bad, arg = i + 1, -1
                                break
                            if act[i] < lmin[i] or act[i] > lmax[i]:
                                bad, arg = i + 1, -2
                                break
                            if not _op_enabled(statusword[i]):
                                bad, arg = i + 1, statusword[i]
                                break
                        self.fault = F_ENABLE
                        self.fault_strut = bad
                        self.fault_arg = arg
                        self._disable()
                        state = self.state = ST_FAULT
                        if h[S.H_READY] == 0:
                            h[S.H_READY] = -1
                # ---------------------------------------------------------- out to the bus
                tc = mono()
                d = tc - tb
                ps2 += d
                if d > pm2:
                    pm2 = d
                for i in range(6):
                    v = out[i]
                    d = v - l0[i]
                    travel[i] += d if d >= 0.0 else -d
                    t = round((v - off[i]) * ipm)
                    target[i] = lo_inc[i] if t < lo_inc[i] else (hi_inc[i] if t > hi_inc[i] else t)
                    l2[i] = l1[i]
                    l1[i] = l0[i]
                    l0[i] = v
                sends += 1
                record(sends, out)
                if io.send() != 0 and state != ST_FAULT and self.fault == F_NONE:
                    self._fault(F_BUS, 0, 1)
                # ---------------------------------------------------------- feedback: FK
                td = mono()
                d = td - tc
                ps3 += d
                if d > pm3:
                    pm3 = d
                if state != ST_BOOT:
                    ct.feedback(act)
                # ---------------------------------------------------------- statistics
                t1 = mono()
                d = t1 - td
                ps4 += d
                if d > pm4:
                    pm4 = d
                late = t0 - deadline
                comp = t1 - t0
                k = late // 1000
                hist_late[k if k < 4095 else 4095] += 1
                k = comp // 1000
                hist_comp[k if k < 4095 else 4095] += 1
                if late > lat_max:
                    lat_max = late
                    h[S.H_LAT_MAX_NS] = late
                if comp > comp_max:
                    comp_max = comp
                    h[S.H_COMP_MAX_NS] = comp
                cycles += 1
                h[S.H_CYCLES] = cycles
                deadline += period
                if self.resync:             # a slow-path cycle (enable, reseed): realign, no overrun
                    self.resync = False
                    if t1 > deadline:
                        deadline = t1 + period
                elif t1 > deadline:
                    missed = (t1 - deadline) // period + 1
                    deadline += (missed - 1) * period
                    overruns += missed
                    in_row += missed
                    h[S.H_OVERRUNS] = overruns
                    if in_row > max_row:
                        max_row = in_row
                        h[S.H_MAX_IN_ROW] = max_row
                    # a burst matters while moving; holding still, the drives keep the position
                    if in_row > max_in_row and self.state == ST_RUNNING:
                        self._fault(F_DEADLINE, 0, in_row)
                else:
                    in_row = 0
                if self.state != last_state or cycles % PUBLISH_EVERY == 0:
                    last_state = self.state
                    h[H_PS] = ps0
                    h[H_PS + 1] = ps1
                    h[H_PS + 2] = ps2
                    h[H_PS + 3] = ps3
                    h[H_PS + 4] = ps4
                    h[H_PS + 5] = ps5
                    h[H_PM] = pm0
                    h[H_PM + 1] = pm1
                    h[H_PM + 2] = pm2
                    h[H_PM + 3] = pm3
                    h[H_PM + 4] = pm4
                    h[H_PM + 5] = pm5
                    self.publish(t0)
                if self.exit_after > 0 and self.state in (ST_DISABLED, ST_FAULT):
                    self.exit_after += 1
                    if self.exit_after > 20:
                        break
                if cycles == max_cycles:
                    break
                t_end = mono()
        except BaseException:
            h[S.H_EXIT] = 2             # crashed: the supervisor reports it, the drives stop on their own
            raise
        finally:
            self.sends = sends
            gc.enable()
            gc.unfreeze()
        self.publish(mono())
        h[S.H_EXIT] = 1
        return 0

    def _check_signals(self, now: int, ppid: int) -> None:
        """A stop signal (SIGTERM/SIGHUP) or the supervisor's death (parent-death signal, or we
        were re-parented): controlled stop, drives disabled, exit.

        A live but slow supervisor is not a fault by itself: while streaming, an empty ring is
        (dead setpoint source); at rest the drives just hold.
        """
        sig = SIGNALS[0]
        if sig:
            SIGNALS[0] = 0
            if not self.exit_signal:
                self._on_signal(sig)
        if SIGNALS[1] or os.getppid() != ppid:
            if os.getppid() == ppid:        # a parent *thread* ended, not the process: ignore
                SIGNALS[1] = 0
                return
            beat = self.sh.h[S.H_SUP_BEAT_NS]
            if self.fault == F_NONE:
                self._fault(F_SUPERVISOR, 0, (now - beat) // 1_000_000 if beat else -1)
            if self.state == S.ST_BOOT:
                self._disable()
                self.state = S.ST_FAULT
            if self.exit_after < 0:
                self.exit_after = 1     # nobody left to reset us: stop, disable, exit


def fault_message(code: int, strut: int, arg: int, emcy_text: str = "", detail: str = "") -> str:
    """Human-readable cause of a fault (slow path)."""
    name = fault_code_name(code)
    if code == F_HEARTBEAT:
        return (f"lost heartbeat of drive {strut}" + (f" ({arg} ms since the last one)" if arg >= 0
                                                       else " (none received)"))
    if code == F_EMCY:
        return f"EMCY from drive {strut}: 0x{arg & 0xFFFF:04X}" + (f" {emcy_text}" if emcy_text else "")
    if code == F_FOLLOWING:
        return f"following error of strut {strut}: {arg / 1000.0:.3f} mm over the limit"
    if code == F_LIMIT:
        return f"setpoint outside limits: {detail}" if detail else f"setpoint outside limits (code {arg})"
    if code == F_DEADLINE:
        return f"missed-deadline burst: {arg} cycles in a row over the period"
    if code == F_SETPOINT:
        return ("dead setpoint source: setpoint ring ran empty while moving" if arg == 1
                else "dead setpoint source: no setpoint within [cycle] setpoint_timeout_s")
    if code == F_DRIVE:
        return f"drive {strut} left Operation Enabled (statusword 0x{arg & 0xFFFF:04X})"
    if code == F_SUPERVISOR:
        return "supervisor process gone" + (f" (last sign of life {arg} ms before)" if arg >= 0 else "")
    if code == F_FEEDBACK:
        return f"stale feedback from drive {strut}: no position sample for {arg} ms"
    if code == F_NMT:
        return (f"drive {strut} was reset (boot-up message)" if arg == 0
                else f"drive {strut} left NMT Operational (heartbeat state {arg})")
    if code == F_REMOTE:
        return f"drive {strut} lost remote (statusword bit 9 clear: 0x{arg & 0xFFFF:04X})"
    if code == F_NOT_FOLLOWING:
        return f"drive {strut} does not follow its target (statusword bit 12 clear: 0x{arg & 0xFFFF:04X})"
    if code == F_SIGNAL:
        import signal
        try:
            name = signal.Signals(arg).name
        except ValueError:
            name = f"signal {arg}"
        return f"stopped by {name}"
    if code == F_BUS:
        return "bus send failed"
    if code == F_ENABLE:
        if arg == -2:
            return f"drive {strut} reports a position outside the strut length range: not enabled"
        if arg == -1:
            return f"no position feedback from drive {strut}: not enabled"
        return f"drive {strut} did not reach Operation Enabled (statusword 0x{arg & 0xFFFF:04X})"
    if code == F_TEST:
        return "test fault"
    return name



def hot_main(cfg, shm_name: str, io_mode: str, period_s: float, realtime: bool, log_level: str,
             report, sim_args: dict | None = None, cpu: int | None = None,
             pdeath_signal: int | None = None) -> None:
    """Body of the hot process: boot the bus, take privileges, run the cycle.

    ``report(kind, payload)`` sends one message to the supervisor ("ready" or "error").
    """
    import sys
    logging.basicConfig(level=getattr(logging, str(log_level).upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s hexacnc[hot %(process)d] %(levelname)s %(message)s")
    logging.getLogger("canopen").setLevel(logging.WARNING)
    logging.getLogger("can").setLevel(logging.WARNING)
    sh = S.Shared(shm_name)
    install_signal_handlers(pdeath_signal)
    from . import busio, rt
    # memory lock and CPU first (slow, and the drives must not wait for the cycle after the boot),
    # SCHED_FIFO last: threads the bus boot starts must not inherit it
    locked, m1 = rt.mlockall()
    (log.info if locked else log.warning)("hot loop: %s", m1)
    cpu, m2 = rt.pin_cpu(cfg.cycle.cpu if cpu is None else cpu)
    (log.info if cpu >= 0 else log.warning)("hot loop: %s", m2)
    io = None
    try:
        io = busio.open_io(cfg, io_mode, period_s, sim_args or {})
    except Exception as exc:
        log.error("hot loop: bus start failed: %s", exc)
        sh.h[S.H_READY] = -1
        report("error", f"{type(exc).__name__}: {exc}")
        sh.close()
        return
    if realtime:
        fifo, m3 = rt.sched_fifo(cfg.cycle.realtime_priority)
    else:
        fifo, m3 = False, "SCHED_FIFO not requested"
    (log.info if fifo else log.warning)("hot loop: %s", m3)
    priv = {"sched_fifo": fifo, "mlockall": locked, "affinity_cpu": cpu, "messages": [m1, m2, m3]}
    sh.h[S.H_PRIV_FIFO] = 1 if priv["sched_fifo"] else 0
    sh.h[S.H_PRIV_MLOCK] = 1 if priv["mlockall"] else 0
    sh.h[S.H_PRIV_AFFINITY] = priv["affinity_cpu"] + 1
    report("ready", {"privileges": priv, "bus_load": getattr(io, "bus_load", 0.0),
                     "io_info": getattr(io, "info", {})})
    loop = HotLoop(cfg, sh, io, priv=priv, period_s=period_s)
    try:
        loop.run()
    finally:
        try:
            io.close()
        finally:
            n = sh.h[S.H_CYCLES]
            sh.h[S.H_STATE] = S.ST_EXITED
            sh.close()
    log.info("hot loop: exited after %d cycles", n)
