"""The hot loop: a process that runs only the fixed-period cycle (started by :mod:`.hot`).

:meth:`HotLoop.run` is the cycle as a sequence of steps, on plain floats and preallocated lists:
``wait_until`` the absolute deadline (sleep until ``[cycle] spin_s`` before it, then spin);
``feedback_in`` (signals, the supervisor's presence, ``io.poll``: positions, statuswords,
heartbeats, EMCY; a supervisor command); ``supervise`` (:mod:`.supervise`); ``offsets`` (thermal,
spindle); ``next_setpoint`` (the shared ring); ``transform`` (``CycleTransform.command``: IK, sag,
thermal, limit guard - or the controlled stop, or the enable walk of :mod:`.enablewalk`);
``frames_out`` (increments, ``io.send``: targets then SYNC); ``CycleTransform.feedback`` (FK of the
measured lengths); ``account`` (:mod:`.cyclestats`) and the status block.

A fault switches to the controlled stop (:class:`~hexacnc.daemon.stopgen.StrutStop`: jerk-limited
per strut), then - once the struts stand at their final command - the drives are disabled by the
CiA 402 walk of :mod:`.disablewalk` (0x0007, then 0x0000, targets held) and the fault latched until
``CMD_RESET``; a drive that no longer follows (:data:`.supervise.QUICK_STOP_FAULTS`) gets quick stop.
The bus object ``io`` is duck-typed (:class:`IOProtocol`); :mod:`hexacnc.daemon.busio` builds it.
"""
from __future__ import annotations

import gc
import logging
import math
import os
import time
from typing import Protocol

from ..transform import CycleTransform, OK as CT_OK
from . import shm as S
from .disablewalk import DisableWalk
from .faults import F_BUS, F_DEADLINE, F_ENABLE, F_LIMIT, F_NONE, F_SETPOINT, F_SUPERVISOR, F_TEST
from .faults import fault_message  # noqa: F401 (re-export)
from .homeloop import HomingCycle, home_command, home_step
from .probelatch import ProbeLatch
from .dioloop import FLAG_IO, DigitalOut
from .torqueread import TorqueSampler
from .cyclestats import CycleStats, publish_status
from .hotsig import SIGNALS, install_signal_handlers, set_parent_death_signal  # noqa: F401 (re-export)
from .enablewalk import ENABLE_TIMEOUT_NS, EnableWalk, op_enabled  # noqa: F401 (re-export)
from .stopgen import StrutStop
from .supervise import QUICK_STOP_FAULTS, DriveSupervisor, following_limits_mm

log = logging.getLogger("hexacnc.loop")

#: The loop sleeps until ``[cycle] spin_s`` (default 200 us) before each deadline, then spins; at
#: most SPIN_FRACTION of the period (SCHED_FIFO throttling and the rest of the machine need the
#: rest; measurements: docs/architecture.md, "Wake-up").
SPIN_FRACTION = 0.8
#: publish the status block every n cycles (and on every state change)
PUBLISH_EVERY = 8
#: setpoint ring index mask
RING_MASK = S.RING_ROWS - 1
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
                                   fb_to, fb_to + HISTORY_MARGIN_S, bus.heartbeat_ms * 1e-3)
        self.max_in_row = int(cy.max_overruns_in_row)
        self.sp_timeout_ns = int(cy.setpoint_timeout_s * 1e9)
        self.stop = StrutStop(cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2, cfg.max_jerk_mm_s3,
                              cfg.min_length_mm, cfg.max_length_mm, self.dt)
        self.lmin = [float(v) for v in cfg.min_length_mm]
        self.lmax = [float(v) for v in cfg.max_length_mm]
        off, ipm = self.off, self.ipm
        self.inv_ipm = 1.0 / ipm
        self.lo_inc = [math.ceil((self.lmin[i] - off[i]) * ipm - 1e-9) for i in range(6)]
        self.hi_inc = [math.floor((self.lmax[i] - off[i]) * ipm + 1e-9) for i in range(6)]
        self.th_step = (float(getattr(cfg.thermal, "max_offset_rate_mm_s", THERMAL_SLEW_MM_S))
                        * self.dt * THERMAL_EVERY)
        self.stats = CycleStats(sh, self.period_ns)
        self.ppid = 0
        # preallocated state
        self.out = [0.0] * 6          # strut command this cycle, mm
        self.l0 = [0.0] * 6           # command history (last, one before, two before)
        self.l1, self.l2 = [0.0] * 6, [0.0] * 6
        self.act = [0.0] * 6          # measured lengths, mm
        self.hold = [0.0] * 6         # pose held when the ring is empty (mm, rad)
        self.walk = EnableWalk(io, self.lmin, self.lmax)
        self.dwalk = DisableWalk(io, self.walk.cw)     # both walks continue from the last controlword
        #: the enable walk may run ([daemon] enable_at_start, else from the first reset/enable)
        self.enable_ok = bool(getattr(cfg.daemon, "enable_at_start", True))
        self.follow_max = self.sup.follow_max
        self.exit_signal = 0          # signal that ordered the stop and exit (0: none)
        self.settle_t0 = 0            # when the commands of a stop that ends disabled came to rest
        self.state = S.ST_BOOT
        self.fault = F_NONE
        self.fault_strut = self.fault_arg = 0
        self.fault_text = ""
        self.after_stop = S.ST_IDLE   # state once the controlled stop is done
        self.streaming = False
        self.starve_ns = self.line = 0
        self.cmd_seen = sh.h[S.H_CMD_SEQ]
        self.exit_after = -1
        self.resync = self.stats_reset = False
        self.travel = [0.0] * 6
        self.sends = 0
        self.homer: HomingCycle | None = None
        self.home_then = S.ST_IDLE    # state after a homing that was stopped
        self.latch, self.dio = ProbeLatch(self), DigitalOut(self)  # SDO after the frames: probe latch, M62-M65
        self.torque = TorqueSampler(self)  # 0x6077/0x6078 over SDO, decimated, after the frames went out

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
        """Begin the disable walk (transitions 5, 10; :mod:`.disablewalk`), stepped every cycle."""
        self.dwalk.begin(time.monotonic_ns())

    def _command(self, code: int, arg: int, now: int) -> None:
        if (code == S.CMD_HOME or self.state == S.ST_HOMING) and home_command(self, code, now):
            return
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
                self.dwalk.cancel()
                self.walk.begin(now)
                self.sup.arm(now)
            elif st == S.ST_BOOT and not self.enable_ok:     # waiting for enable since the start
                self.enable_ok = True
                self.dwalk.cancel()
                self.walk.begin(now)
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
        """The status block for the supervisor (seqlock), see :func:`.cyclestats.publish_status`."""
        publish_status(self)

    # ------------------------------------------------------------------ the cycle
    def run(self, max_cycles: int = -1) -> int:
        """The cycle until shut down (or ``max_cycles`` cycles of this call): wait for the
        deadline, then feedback in, supervision, offsets, next setpoint, transform and guard (or
        the stop / enable walk), frames out, forward kinematics, statistics."""
        self._enter_run()
        stats = self.stats = CycleStats(self.sh, self.period_ns)
        h = self.sh.h
        mono, phase = time.monotonic_ns, stats.phase
        ct, act = self.ct, self.act
        last_state = -1
        t_end = t1 = 0
        gc.collect()
        gc.freeze()
        gc.disable()
        deadline = mono() + self.period_ns
        try:
            while True:
                t0 = self.wait_until(deadline)
                if t_end:                           # the previous cycle's statistics and publishing
                    phase(5, t_end - t1)
                h[S.H_LOOP_BEAT_NS] = t0
                self.feedback_in(t0)
                ta = mono()
                phase(0, ta - t0)
                self.supervise(t0)
                self.offsets()
                tb = mono()
                phase(1, tb - ta)
                self.next_setpoint(t0)
                self.transform(t0)
                tc = mono()
                phase(2, tc - tb)
                self.frames_out()
                td = mono()
                phase(3, td - tc)
                if self.state != S.ST_BOOT:
                    ct.feedback(act)                # FK of the measured lengths
                t1 = mono()
                phase(4, t1 - td)
                deadline = self.account(t0, t1, deadline)
                if self.state != last_state or stats.cycles % PUBLISH_EVERY == 0:
                    last_state = self.state
                    stats.publish_phases()
                    self.publish(t0)
                if self.exit_after > 0 and self.state in (S.ST_DISABLED, S.ST_FAULT) and not self.dwalk.active:
                    self.exit_after += 1
                    if self.exit_after > 20:
                        break
                if stats.cycles == max_cycles:
                    break
                t_end = mono()
        except BaseException:
            h[S.H_EXIT] = 2             # crashed: the supervisor reports it, the drives stop on their own
            raise
        finally:
            gc.enable()
            gc.unfreeze()
        self.publish(mono())
        h[S.H_EXIT] = 1
        return 0

    def _enter_run(self) -> None:
        sh = self.sh
        sh.s[S.S_BUS_LOAD] = getattr(self.io, "bus_load", 0.0)
        sh.s[S.S_PERIOD] = self.dt
        sh.h[S.H_PID] = os.getpid()
        self.ppid = sh.h[S.H_SUP_PID] or os.getppid()
        if os.getppid() != self.ppid:
            SIGNALS[1] = 1              # the supervisor died before we could watch it
        self.sup.fill(self.l0)
        if self.state == S.ST_BOOT:
            self.walk.begin(time.monotonic_ns())

    def wait_until(self, deadline: int) -> int:
        """Sleep until ``[cycle] spin_s`` before the deadline, spin to it; returns the wake time."""
        mono = time.monotonic_ns
        rem = deadline - mono()
        if rem > self.spin_ns:
            time.sleep((rem - self.spin_ns) * 1e-9)
        while mono() < deadline:
            pass
        return mono()

    def feedback_in(self, t0: int) -> None:
        """Signals and the supervisor's presence, feedback frames (positions -> measured lengths
        ``act``), a command from the supervisor."""
        if SIGNALS[0] or SIGNALS[1] or (self.stats.cycles & (SUPERVISOR_CHECK_EVERY - 1)) == 0:
            self._check_signals(t0, self.ppid)
        io = self.io
        io.poll(t0)
        pos = io.pos
        act = self.act
        off = self.off
        k = self.inv_ipm
        for i in range(6):
            act[i] = pos[i] * k + off[i]
        h = self.sh.h
        seq = h[S.H_CMD_SEQ]
        if seq != self.cmd_seen:
            self.cmd_seen = seq
            self._command(h[S.H_CMD], h[S.H_CMD_ARG], t0)
            h[S.H_CMD_ACK] = seq
            if self.stats_reset:
                self.stats_reset = False
                self.stats.reset()

    def supervise(self, t0: int) -> None:
        """Drive supervision (:class:`~hexacnc.daemon.supervise.DriveSupervisor`) while enabled."""
        st = self.state
        if st == S.ST_RUNNING or st == S.ST_IDLE:
            sup = self.sup
            code = sup.check(t0, self.act, self.sends)
            if code:
                if code in QUICK_STOP_FAULTS:       # this drive no longer follows the loop's stop
                    self.dwalk.quick_stop(sup.strut - 1)
                self._fault(code, sup.strut, sup.arg)

    def offsets(self) -> None:
        """Thermal and spindle growth slewed towards the supervisor's targets (every THERMAL_EVERY cycles)."""
        if (self.stats.cycles & (THERMAL_EVERY - 1)) or self.state == S.ST_STOPPING:
            return
        shs = self.sh.s
        ct = self.ct
        th_app = ct.thermal_mm
        step = self.th_step
        for i in range(6):
            d = shs[S.S_THERMAL_TGT + i] - th_app[i]
            if d != 0.0:
                th_app[i] += step if d > step else (-step if d < -step else d)
        d = shs[S.S_SPINDLE_TGT] - ct.spindle_growth_mm
        if d != 0.0:
            ct.spindle_growth_mm += step if d > step else (-step if d < -step else d)

    def next_setpoint(self, t0: int) -> None:
        """The next row of the setpoint ring into ``hold`` (idle -> running); an empty ring holds
        the last pose after an END row, else it is a dead setpoint source."""
        st = self.state
        if st != S.ST_RUNNING and st != S.ST_IDLE:
            return
        h = self.sh.h
        r = h[S.H_RING_R]
        if r < h[S.H_RING_W]:
            ring = self.sh.ring
            b = (r & RING_MASK) * S.ROW
            hold = self.hold
            hold[0] = ring[b]
            hold[1] = ring[b + 1]
            hold[2] = ring[b + 2]
            hold[3] = ring[b + 3]
            hold[4] = ring[b + 4]
            hold[5] = ring[b + 5]
            self.line, fl = int(ring[b + 6]), int(ring[b + 7])
            self.streaming = not ((self.dio.take(fl) if fl >= FLAG_IO else fl) & S.FLAG_END)
            h[S.H_RING_R] = r + 1
            self.starve_ns = 0
            if st == S.ST_IDLE:
                self.state = S.ST_RUNNING
            if not self.streaming:
                h[S.H_END_SEEN] = r + 1
        elif self.streaming:
            self._starving(t0)
        elif st == S.ST_RUNNING:
            self.state = S.ST_IDLE

    def _starving(self, t0: int) -> None:
        l0, l1 = self.l0, self.l1
        for i in range(6):
            d = l0[i] - l1[i]
            if d > STANDSTILL_MM or d < -STANDSTILL_MM:     # moving: fault at once
                self.sh.h[S.H_UNDERRUNS] += 1
                self._fault(F_SETPOINT, 0, 1)
                return
        if self.starve_ns == 0:
            self.starve_ns = t0
        elif t0 - self.starve_ns > self.sp_timeout_ns:
            self._fault(F_SETPOINT, 0, 2)

    def transform(self, t0: int) -> None:
        """Strut commands ``out`` of this cycle: IK + sag + thermal + limit guard of the held pose,
        or the next step of the controlled stop, or of the enable walk; the disable walk runs on
        (targets held) until every drive is disabled."""
        st = self.state
        if st == S.ST_RUNNING or st == S.ST_IDLE:
            self.guard()
            st = self.state
        if st == S.ST_STOPPING:
            self.stopping(t0)
        elif st == S.ST_BOOT:
            self.enabling(t0)
        elif st == S.ST_HOMING:
            home_step(self, t0)
        elif self.dwalk.active:
            self.dwalk.step(t0)

    def guard(self) -> None:
        ct = self.ct
        hold = self.hold
        code = ct.command(hold[0], hold[1], hold[2], hold[3], hold[4], hold[5])
        if code == CT_OK:
            cm = ct.cmd_mm
            out = self.out
            for i in range(6):
                out[i] = cm[i]
        else:
            self._fault(F_LIMIT, ct.fail_index + 1, code)
            self.sh.s[S.S_FAULT_VALUE] = ct.fail_value

    def stopping(self, t0: int) -> None:
        if self.stop.step(self.out):
            return
        if self.after_stop == S.ST_IDLE:
            self._rehold_from(self.out)
            self.state = S.ST_IDLE
        elif self.dwalk.active or self._settled(t0):    # disable once the struts stand where commanded
            self.dwalk.begin(t0)
            if self.dwalk.step(t0):             # stopping until every drive is disabled
                self.state = self.after_stop

    def enabling(self, t0: int) -> None:
        if not self.enable_ok:              # [daemon] enable_at_start false: hold, disabled, until enable
            self.walk.track(self.act, self.out)
            return
        r = self.walk.step(t0, self.act, self.out)
        if r > 0:
            self.seed_from_feedback()
            self.sup.arm(t0)
            self.resync = True
            self.state = S.ST_IDLE
            self.sh.h[S.H_READY] = 1
        elif r < 0:
            self.fault = F_ENABLE
            self.fault_strut = self.walk.bad
            self.fault_arg = self.walk.arg
            self._disable()
            self.state = S.ST_FAULT
            if self.sh.h[S.H_READY] == 0:
                self.sh.h[S.H_READY] = -1

    def frames_out(self) -> None:
        """Drive increments of ``out`` (clamped to the strut range), command history, send."""
        out = self.out
        l0, l1, l2 = self.l0, self.l1, self.l2
        travel = self.travel
        off = self.off
        ipm = self.ipm
        lo_inc, hi_inc = self.lo_inc, self.hi_inc
        target = self.io.target
        for i in range(6):
            v = out[i]
            d = v - l0[i]
            travel[i] += d if d >= 0.0 else -d
            t = round((v - off[i]) * ipm)
            target[i] = lo_inc[i] if t < lo_inc[i] else (hi_inc[i] if t > hi_inc[i] else t)
            l2[i] = l1[i]
            l1[i] = l0[i]
            l0[i] = v
        self.sends += 1
        self.sup.record(self.sends, out)
        if self.io.send() != 0 and self.state != S.ST_FAULT and self.fault == F_NONE:
            self._fault(F_BUS, 0, 1)

    def account(self, t0: int, t1: int, deadline: int) -> int:
        """Cycle statistics; an overrun burst while moving is a fault. Returns the next deadline."""
        resync = self.resync
        self.resync = False
        stats = self.stats
        before = stats.overruns
        self.latch.step(t0)
        self.dio.step(t0)
        self.torque.step(t0)
        deadline = stats.account(t0, t1, deadline, resync)
        if stats.overruns != before and stats.in_row > self.max_in_row and self.state == S.ST_RUNNING:
            self._fault(F_DEADLINE, 0, stats.in_row)
        return deadline

    def _check_signals(self, now: int, ppid: int) -> None:
        """A stop signal (SIGTERM/SIGHUP) or the supervisor's death: controlled stop, drives disabled, exit.

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
