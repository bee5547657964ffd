"""Reactions of a simulated drive (:class:`drivers.simnode.SimDrive`): stop ramps and the
supervision of the master, exactly as the master configured them by SDO.

* Stop ramps: quick stop (controlword bit 2, transition 11) per 0x605A, fault reaction per 0x605E,
  disable operation (transition 5) per 0x605C; each that ends with the power stage off (0x605A 1 and 2,
  0x605E 1 and 2, 0x605C 1) holds the strut at rest with torque on for the holding brake's engage delay
  (0x2110:2) before it leaves the state, so the brake grips before the torque goes; slow-down ramp = 0x6084, quick-stop ramp = 0x6085
  (position units/s^2), jerk-limited at the profile jerk 0x60A4:1 (units/s^3) where the drive has it. The ramp runs on the drive's own clock: on SYNC while the master sends
  them, on the housekeeping clock (every ``TICK_S``) once SYNC has stopped.
* Communication loss: RPDO1 deadline monitoring (0x1400 sub 5 event timer, armed by the first
  RPDO after NMT start, supervised while the drive is enabled: Operation enabled / Quick stop
  active) -> EMCY 0x8250; SYNC lost (no SYNC for the SYNC-loss time-out, armed by the first SYNC
  after NMT start, supervised while enabled) -> EMCY 0x8700; master heartbeat lost (0x1016) -> EMCY 0x8130. Each
  applies 0x1029 sub 1 (NMT state) and 0x6007 (1 fault -> 0x605E, 2 disable voltage, 3 quick
  stop -> 0x605A) while the power stage is on.

SYNC-loss time-out: manufacturer object 0x2010 (ms, written and read back by the master as
``[bus] comm_loss_timeout_s``), or 1.5 x the communication cycle period 0x1006 where 0x2010 is 0 or
absent (the CiA 301 SYNC consumer's rule; 0x1006 = 0: no SYNC supervision).

Every reaction is appended to ``events`` as (monotonic s, text) for tests and the log.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from . import cia402
from .jerkstop import stop_accel

if TYPE_CHECKING:
    from .simnode import SimDrive

log = logging.getLogger("hexacnc.simdrive")

#: housekeeping period of the simulated drives (supervision resolution, ramp steps without SYNC)
TICK_S = 0.002
_POWERED = (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.SWITCHED_ON, cia402.READY_TO_SWITCH_ON)


class Ramp:
    """Demand decelerating from the strut's velocity to rest at ``decel_mm_s2``, then held there (torque
    on) for ``hold_s`` (the holding brake's engage delay); ``then`` = state after that (``None``: stay).
    With ``jerk_mm_s3`` > 0 (the drive's profile jerk 0x60A4:1) the deceleration is reached and left at
    that jerk (:func:`drivers.jerkstop.stop_accel`, from the acceleration ``accel_mm_s2`` the demand had),
    else it is applied at once (a trapezoid)."""
    __slots__ = ("x_mm", "v_mm_s", "a_mm_s2", "decel_mm_s2", "jerk_mm_s3", "then", "done", "stopped",
                 "hold_s", "held_s")

    def __init__(self, x_mm: float, v_mm_s: float, decel_mm_s2: float, then: int | None,
                 jerk_mm_s3: float = 0.0, accel_mm_s2: float = 0.0, hold_s: float = 0.0):
        self.x_mm, self.v_mm_s, self.decel_mm_s2, self.then = x_mm, v_mm_s, max(1e-9, decel_mm_s2), then
        self.jerk_mm_s3 = max(0.0, jerk_mm_s3)
        self.a_mm_s2 = accel_mm_s2 if self.jerk_mm_s3 > 0 else 0.0
        self.hold_s, self.held_s = hold_s, 0.0
        self.stopped = abs(v_mm_s) < 1e-12 and self.a_mm_s2 == 0.0
        self.done = self.stopped and hold_s <= 0

    def _stop(self) -> None:
        self.stopped = True
        self.done = self.hold_s <= 0

    def step(self, dt: float) -> float:
        if self.stopped:                    # at rest: held for the brake's engage delay
            self.held_s += dt
            self.done = self.held_s >= self.hold_s - 1e-9
            return self.x_mm
        v = self.v_mm_s
        if self.jerk_mm_s3 > 0.0:
            a = stop_accel(v, self.a_mm_s2, self.jerk_mm_s3, self.decel_mm_s2, dt)
            nv = v + a * dt
            self.x_mm += nv * dt
            self.v_mm_s, self.a_mm_s2 = nv, a
            if nv == 0.0 and a == 0.0:
                self._stop()
            return self.x_mm
        dv = self.decel_mm_s2 * dt
        nv = 0.0 if abs(v) <= dv else v - (dv if v > 0 else -dv)
        self.x_mm += 0.5 * (v + nv) * dt
        self.v_mm_s = nv
        if nv == 0.0:
            self._stop()
        return self.x_mm


class Reactions:
    """Per drive; all calls with the drives' lock held."""

    def __init__(self, drive: "SimDrive"):
        self.d = drive
        self.ramp: Ramp | None = None
        self.events: list[tuple[float, str]] = []
        self.rpdo_timer_s = 0.0
        self.last_rpdo_s: float | None = None
        self.abort_option = cia402.ABORT_FAULT
        self.comm_error = cia402.COMM_ERROR_PRE_OPERATIONAL
        self.last_step_s = 0.0
        self.last_tick_s: float | None = None
        self.sync_loss_s = 0.0
        self._sync_seen_s = 0.0                 #: the drive's last_sync_s when last looked at
        self._sync_ref_s: float | None = None   #: SYNC-loss deadline base (None: not armed)
        self.brake = HoldingBrake()
        drive.hooks.on_read(0x2110, lambda sub: int(self.brake.engaged) if sub == 3 else None)
        drive.hooks.on_sync(self._brake_sync)
        self.last_hk_s: float | None = None          # the drive's last housekeeping tick
        self.demands: list[float] | None = None      # the last 9 demands, mm, newest first

    # -- the demand the drive had (where a stop ramp starts) ------------------------------------
    def fill_demands(self, x_mm: float) -> None:
        self.demands = [x_mm] * 9

    def track_demand(self, x_mm: float) -> None:
        dem = self.demands
        if dem is None:
            self.demands = [x_mm] * 9
            return
        dem.pop()
        dem.insert(0, x_mm)

    def demand_state_mm(self) -> tuple[float, float, float]:
        """Position (mm), velocity (mm/s) and acceleration (mm/s^2) of the last demands: the
        acceleration over 4-cycle steps, so the rounding of the targets to units hardly shows."""
        d = self.d
        dem = self.demands or [d.pos_inc / d.k] * 9
        dt = d._dt_s
        return dem[0], (dem[0] - dem[1]) / dt, (dem[0] - 2.0 * dem[4] + dem[8]) / (4.0 * dt) ** 2

    def excuse_own_stall(self, now: float, master_hb_s: float | None) -> float | None:
        """The master heartbeat's time moved on by the drive's own stall (housekeeping late by more
        than 3 ticks): a descheduled simulator is not a silent master, the frames queued meanwhile are
        still to be read (as for the RPDO deadline in :meth:`supervise`)."""
        last, self.last_hk_s = self.last_hk_s, now
        if last is not None and master_hb_s is not None and now - last > 3 * TICK_S:
            return master_hb_s + (now - last)
        return master_hb_s

    def frames_waiting(self, now: float) -> None:
        """Frames for this drive wait unread in its receive queue: the simulator is behind, the master is
        not silent. The RPDO, SYNC-loss and master-heartbeat deadlines start again from ``now`` (a
        descheduled reader thread beside a punctual housekeeping thread is no stall of the process, so
        :meth:`supervise` would not excuse it)."""
        if self.last_rpdo_s is not None:
            self.last_rpdo_s = now
        if self._sync_ref_s is not None:
            self._sync_ref_s = now
        if self.d.master_hb_s is not None:
            self.d.master_hb_s = now

    # -- configuration (NMT start) -------------------------------------------------------------
    def configure(self) -> None:
        d = self.d
        self.rpdo_timer_s = d.raw_or(0x1400, 5, 0) * 1e-3
        self.abort_option = d.raw_or(0x6007, 0, cia402.ABORT_FAULT)
        self.comm_error = d.raw_or(0x1029, 1, cia402.COMM_ERROR_PRE_OPERATIONAL)
        self.last_rpdo_s = None
        self.sync_loss_s = sync_loss_timeout_s(d.raw_or(0x2010, 0, 0), d.raw_or(0x1006, 0, 0))
        self._sync_seen_s, self._sync_ref_s = d.last_sync_s, None
        self.brake.release_s = d.raw_or(0x2110, 1, 0) * 1e-3
        self.brake.engage_s = d.raw_or(0x2110, 2, 0) * 1e-3

    def note(self, now: float, text: str, level: int = logging.INFO) -> None:
        self.events.append((now, text))
        if len(self.events) > 256:
            del self.events[:128]
        log.log(level, "node %d: %s", self.d.node_id, text)

    # -- ramps --------------------------------------------------------------------------------
    def decel_mm_s2(self, quick: bool) -> float:
        d = self.d
        units = d.raw_or(0x6085, 0, 0) if quick else d.raw_or(0x6084, 0, 0) or d.raw_or(0x6085, 0, 0)
        return units / d.k if units > 0 else d.model_amax()

    def start_ramp(self, quick: bool, then: int | None, now: float, why: str, hold_s: float = 0.0) -> None:
        """The ramp starts where the demand was (position, velocity and acceleration of the last
        demands: the strut model follows its demand, a restart from the measured position would
        step it), at the profile jerk 0x60A4:1 where the drive has one; held ``hold_s`` at rest."""
        d = self.d
        a = self.decel_mm_s2(quick)
        j = d.raw_or(0x60A4, 1, 0) / d.k
        x, v, acc = self.demand_state_mm()
        self.ramp = Ramp(x, v, a, then, j, acc, hold_s)
        self.last_step_s = now
        self.note(now, f"{why}: {'quick stop' if quick else 'slow down'} ramp {a:g} mm/s^2"
                       + (f", jerk {j:g} mm/s^3" if j > 0 else "") + f" from {v:.3f} mm/s")

    def quick_stop_option(self, now: float, why: str) -> None:
        """Start the quick stop reaction per 0x605A (state already Quick stop active)."""
        qs = self.d.raw_or(0x605A, 0, cia402.QS_QUICK_RAMP_DISABLE)
        if qs <= 0:            # 0: disable drive function at once
            self.d.state = cia402.SWITCH_ON_DISABLED
            self.note(now, f"{why}: quick stop option {qs}: drive function disabled at once")
            return
        then = cia402.SWITCH_ON_DISABLED if qs in (1, 2) else None
        hold = self.brake.engage_s if then is not None else 0.0     # 5, 6: stays in Quick stop active, torque on
        self.start_ramp(qs in (2, 6), then, now, f"{why} (0x605A = {qs})" + self._brake_text(hold), hold)
        self.brake.engaging = hold > 0

    def fault_reaction(self, now: float) -> None:
        fr = self.d.raw_or(0x605E, 0, cia402.FAULT_REACTION_QUICK_RAMP)
        if fr in (1, 2):
            hold = self.brake.engage_s
            self.start_ramp(fr == 2, cia402.FAULT, now, f"fault reaction (0x605E = {fr})" + self._brake_text(hold),
                            hold)
            self.brake.engaging = hold > 0
        else:
            self.ramp = None
            self.note(now, f"fault reaction (0x605E = {fr}): drive disabled, motor free")

    @staticmethod
    def _brake_text(hold_s: float) -> str:
        return (f", then the holding brake engages with torque on for {hold_s * 1e3:g} ms (0x2110:2)"
                if hold_s > 0 else "")

    def disable_operation(self, now: float) -> bool:
        """Transition 5 asked: True when the drive ramps first (0x605C = 1, still moving)."""
        opt = self.d.raw_or(0x605C, 0, cia402.DISABLE_OP_SLOW_DOWN)
        hold = self.brake.engage_s
        if opt == cia402.DISABLE_OP_SLOW_DOWN and (abs(self.d.model.velocity_mm_s) > 1e-9 or hold > 0):
            self.start_ramp(False, cia402.SWITCHED_ON, now, "disable operation (0x605C = 1)" + self._brake_text(hold),
                            hold)
            self.brake.engaging = hold > 0
            return True
        self.note(now, f"disable operation (0x605C = {opt}): brake engaged, Switched on")
        return False

    def ramp_demand(self, dt: float) -> float:
        return self.ramp.step(dt)

    def _brake_sync(self, d, now: float) -> None:
        """After each step: the brake opens (0x2110:1 release delay; 0x2110:3 reads engaged until then:
        the strut is not held meanwhile, the master's enable walk sends the measured position) once
        Operation enabled, and is engaged when the power stage is off or the disable ramp's hold ends."""
        b = self.brake
        if not b.fitted():
            return
        if d.state == cia402.OPERATION_ENABLED and not d.disabling:
            if b.engaged:
                if b.release_t0 is None:
                    b.release_t0 = now
                    self.note(now, f"holding brake releasing ({b.release_s * 1e3:g} ms, 0x2110:1)")
                if now - b.release_t0 < b.release_s:
                    return
                b.engaged, b.release_t0 = False, None
                self.note(now, "holding brake released")
        elif not b.engaged and (d.state not in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE,
                                                cia402.FAULT_REACTION_ACTIVE) or (b.engaging and (self.ramp is None or self.ramp.done))):
            b.engaged, b.engaging = True, False
            self.note(now, f"holding brake engaged, torque off ({cia402.state_name(d.state)})")

    # -- supervision ----------------------------------------------------------------------------
    def rpdo_received(self, now: float) -> None:
        self.last_rpdo_s = now

    def supervise(self, now: float) -> None:
        """Housekeeping: RPDO deadline; ramp steps on the drive's own clock when SYNC has stopped."""
        d = self.d
        # A simulated drive can be descheduled (a real one cannot): a gap in its own clock is not
        # the master's silence, and frames queued meanwhile are still to be read. Extend the
        # deadline by the drive's own stall.
        stall = now - self.last_tick_s if self.last_tick_s is not None else 0.0
        if self.last_rpdo_s is not None and stall > 3 * TICK_S:
            self.last_rpdo_s += stall
        self.last_tick_s = now
        self._supervise_sync(now, stall)
        if (self.rpdo_timer_s > 0 and self.last_rpdo_s is not None
                and now - self.last_rpdo_s > self.rpdo_timer_s
                and d.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE)):
            self.last_rpdo_s = None                 # once; re-armed by the next RPDO
            self.comm_loss(cia402.EMCY_RPDO_TIMEOUT, now,
                           f"no RPDO for {self.rpdo_timer_s * 1e3:g} ms (0x1400:05)")
        if self.ramp is not None and now - max(d.last_sync_s, self.last_step_s) > 2 * d._dt_s:
            n = 0
            while self.last_step_s + d._dt_s <= now and n < 1000 and self.ramp is not None:
                self.last_step_s += d._dt_s
                d.step(d._dt_s, self.last_step_s, own_clock=True)
                n += 1

    def _supervise_sync(self, now: float, stall: float) -> None:
        """SYNC loss: armed by each SYNC (the drive's ``last_sync_s``), extended by the drive's own stall."""
        d = self.d
        if d.last_sync_s != self._sync_seen_s:
            self._sync_seen_s = self._sync_ref_s = d.last_sync_s
        elif self._sync_ref_s is not None and stall > 3 * TICK_S:
            self._sync_ref_s += stall
        if (self.sync_loss_s > 0 and self._sync_ref_s is not None and now - self._sync_ref_s > self.sync_loss_s
                and d.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE)):
            self._sync_ref_s = None                 # once; re-armed by the next SYNC
            self.comm_loss(cia402.EMCY_SYNC_LOSS, now, f"no SYNC for {self.sync_loss_s * 1e3:g} ms "
                           "(0x2010 SYNC-loss time-out, else 1.5 x 0x1006)")

    def comm_loss(self, code: int, now: float, why: str) -> None:
        """Communication error: EMCY, 0x1029 NMT reaction, 0x6007 drive reaction (when powered)."""
        d = self.d
        d.node.emcy.send(code, 0x11)
        d.error_code = code
        self.note(now, f"communication error 0x{code:04X}: {why}; 0x6007 = {self.abort_option}, "
                       f"0x1029:1 = {self.comm_error}", logging.WARNING)     # in the daemon's log too
        if d.state in _POWERED:
            opt = self.abort_option
            if opt == cia402.ABORT_FAULT:
                d.fault(code, send_emcy=False)
            elif opt == cia402.ABORT_DISABLE_VOLTAGE:
                d.state = cia402.SWITCH_ON_DISABLED
                self.ramp = None
            elif opt == cia402.ABORT_QUICK_STOP and d.state == cia402.OPERATION_ENABLED:
                d.state = cia402.QUICK_STOP_ACTIVE
                self.quick_stop_option(now, "abort connection quick stop")
            d.status_changed(now)
        if self.comm_error == cia402.COMM_ERROR_PRE_OPERATIONAL:
            d.node.nmt.state = "PRE-OPERATIONAL"
        elif self.comm_error == cia402.COMM_ERROR_STOPPED:
            d.node.nmt.state = "STOPPED"


def sync_loss_timeout_s(obj_2010_ms: int, cycle_period_us: int) -> float:
    """The SYNC-loss time-out of a simulated drive: 0x2010 (ms) when set, else 1.5 x 0x1006 (us); 0: none."""
    if obj_2010_ms > 0:
        return obj_2010_ms * 1e-3
    return 1.5 * cycle_period_us * 1e-6


class HoldingBrake:
    """The holding brake of a simulated drive, managed by the drive: delays from the bundled EDS's
    manufacturer record 0x2110 "Holding brake" (sub 1 release delay ms, sub 2 engage delay ms, sub 3
    engaged, read only). Real drives keep these in vendor objects too (e.g. Synapticon 0x2004 brake
    options); 0 / 0: no brake fitted."""
    __slots__ = ("release_s", "engage_s", "engaged", "engaging", "release_t0")

    def __init__(self):
        self.release_s = self.engage_s = 0.0
        self.engaged = True                 #: power off: the brake holds
        self.engaging = False               #: disable operation: held with torque for engage_s
        self.release_t0: float | None = None

    def fitted(self) -> bool:
        return self.release_s > 0 or self.engage_s > 0
