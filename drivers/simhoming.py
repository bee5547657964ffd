"""Homing mode (CiA 402 mode 6) of the simulated drives, registered in :data:`drivers.simhooks.EXTENSIONS`.

Objects (added to a drive's dictionary when its description lacks them; position units are the
drive's increments): 0x6098 homing method (int8), 0x6099 sub 1 speed during search for switch,
sub 2 speed during search for zero (units/s), 0x609A homing acceleration (units/s^2), 0x607C home
offset (int32).

With mode 6 selected (0x6060 = 6, also while Operation enabled: the drive switches between 6 and
8 on the fly) a rising edge of controlword bit 4 starts the method:

* 35 / 37: the current position is home: the position value becomes the home offset at once;
* 17 / 18: search the negative / positive limit switch at the search speed, back off it at the
  zero speed; the switch's releasing edge is home (position value := home offset there, the edge
  latched at the cycle that sees it: at most one cycle of travel at the zero speed past it), then stop.
  The simulated switches stand ``SWITCH_FROM_START_MM`` below / above the strut's power-up position
  (``drive.home_switch_mm`` = (negative, positive) in the drive's physical mm, settable per drive);
  no switch within ``MAX_SEARCH_MM`` of travel is a homing error.

Statusword in mode 6: bit 12 homing attained, bit 13 homing error, bit 10 target reached (set when
not homing: not started, interrupted or done). Any other method is a homing error. Clearing bit 4
during homing stops it (interrupted: bits 12/13 clear, bit 10 set once stopped). In homing mode the
drive ignores 0x607A (the target position of the cyclic frames).

NMT reset node (0x81, the simulated power cycle) drops the home shift: the position value restarts
from the raw encoder count (the power-up position scale) and the drive is no longer referenced.
"""
from __future__ import annotations

from . import cia402
from .simhooks import EXTENSIONS

MODE_HOMING = 6
CW_HOMING_START = 1 << 4
SW_HOMING_ATTAINED = 1 << 12
SW_HOMING_ERROR = 1 << 13
METHODS_HERE = (35, 37)
METHODS_SWITCH = {17: -1, 18: +1}
#: the simulated limit switches: this far below / above the power-up position (mm)
SWITCH_FROM_START_MM = 2.0
#: a switch search gives up (homing error) after this much travel (mm)
MAX_SEARCH_MM = 50.0

_IDLE, _SEARCH, _BACKOFF, _STOP, _DONE, _ERROR = range(6)

_OBJECTS = ((0x6098, 0, "Homing method", 0x0002, 35), (0x607C, 0, "Home offset", 0x0004, 0),
            (0x609A, 0, "Homing acceleration", 0x0007, 100000))


def _add_objects(od) -> None:
    from canopen.objectdictionary import ODRecord, ODVariable
    for index, sub, name, dtype, default in _OBJECTS:
        if index not in od:
            v = ODVariable(name, index, sub)
            v.data_type, v.access_type, v.default, v.pdo_mappable = dtype, "rw", default, False
            od.add_object(v)
    if 0x6099 not in od:
        rec = ODRecord("Homing speeds", 0x6099)
        n = ODVariable("Highest sub-index supported", 0x6099, 0)
        n.data_type, n.access_type, n.default = 0x0005, "ro", 2
        rec.add_member(n)
        for sub, name, default in ((1, "Speed during search for switch", 100000),
                                   (2, "Speed during search for zero", 20000)):
            v = ODVariable(name, 0x6099, sub)
            v.data_type, v.access_type, v.default = 0x0007, "rw", default
            rec.add_member(v)
        od.add_object(rec)


class SimHoming:
    """Homing state of one :class:`drivers.simnode.SimDrive` (called with the drives' lock held)."""

    def __init__(self, drive):
        self.drive = drive
        x0 = drive.pos_inc / drive.k
        self.home_switch_mm = (x0 - SWITCH_FROM_START_MM, x0 + SWITCH_FROM_START_MM)
        self.shift_inc = 0            #: position value - physical position (increments)
        self.phase = _IDLE
        self.v = 0.0                  #: profile velocity (units/s)
        self.x = 0.0                  #: profile position (units, drive coordinates)
        self.dir = 0
        self.travel = 0.0
        self.edge_phys = 0.0
        self.referenced = False       #: homing attained at least once since power-up

    # -- hooks ------------------------------------------------------------------------------
    def status_bits(self, drive) -> int:
        if drive.mode != MODE_HOMING:
            return 0
        ph = self.phase
        if ph == _DONE:
            return SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED
        if ph == _ERROR:
            return SW_HOMING_ERROR | cia402.SW_TARGET_REACHED
        if ph == _IDLE:
            return cia402.SW_TARGET_REACHED
        return 0

    def on_controlword(self, drive, cw: int) -> None:
        rising = cw & CW_HOMING_START and not drive.cw & CW_HOMING_START
        if drive.mode != MODE_HOMING or drive.state != cia402.OPERATION_ENABLED:
            return
        if rising:
            self.start(drive)
        elif not cw & CW_HOMING_START and self.phase in (_SEARCH, _BACKOFF):
            self.phase = _STOP          # interrupted: stop, not attained
            self.dir = 0

    def on_mode(self, sub: int, value: int) -> None:
        d = self.drive
        if value == MODE_HOMING:
            self.phase = _IDLE
            self.x = float(d.pos_inc)
            self.v = 0.0
        d.target_inc = d.demand_inc = d.pos_inc     # either way: no step from an old target

    # -- the method -------------------------------------------------------------------------
    def start(self, drive) -> None:
        method = drive.raw(0x6098)
        self.x = float(drive.pos_inc)
        self.v = 0.0
        self.travel = 0.0
        if method in METHODS_HERE:
            self._set_home(drive, drive.pos_inc - self.shift_inc)
            self.phase = _DONE
        elif method in METHODS_SWITCH:
            self.dir = METHODS_SWITCH[method]
            self.phase = _SEARCH
        else:
            self.phase = _ERROR

    def _phys_mm(self, drive) -> float:
        return (drive.pos_inc - self.shift_inc) / drive.k

    def _set_home(self, drive, edge_phys_inc: float) -> None:
        """Position value := home offset at the physical position ``edge_phys_inc``."""
        offset = drive.raw(0x607C)
        new_shift = int(round(offset - edge_phys_inc))
        delta = new_shift - self.shift_inc
        self.shift_inc = new_shift
        drive.pos_inc += delta
        drive.demand_inc = drive.target_inc = drive.pos_inc
        drive.model.reset(drive.pos_inc / drive.k)      # at standstill only
        self.x += delta
        self.referenced = True

    def power_cycle(self, drive) -> None:
        """NMT reset node (a power cycle): the position counter restarts from the raw encoder count
        (the home shift is gone), not referenced."""
        delta = -self.shift_inc
        self.shift_inc = 0
        self.referenced = False
        self.phase = _IDLE
        self.v = 0.0
        self.dir = 0
        if delta:
            drive.pos_inc += delta
            drive.demand_inc = drive.target_inc = drive.pos_inc
            drive.model.reset(drive.pos_inc / drive.k)

    def on_sync(self, drive, now_s: float) -> None:
        if drive.mode != MODE_HOMING or drive.state != cia402.OPERATION_ENABLED:
            if self.phase in (_SEARCH, _BACKOFF, _STOP):
                self.phase = _IDLE          # left mode 6 or disabled: interrupted
            return
        ph = self.phase
        if ph not in (_SEARCH, _BACKOFF, _STOP):
            return
        dt = drive._dt_s
        acc = max(1.0, float(drive.raw(0x609A)))
        if ph == _SEARCH:
            want = self.dir * float(drive.raw(0x6099, 1))
        elif ph == _BACKOFF:
            want = -self.dir * float(drive.raw(0x6099, 2))
        else:
            want = 0.0
        dv = want - self.v
        step = acc * dt
        self.v += step if dv > step else (-step if dv < -step else dv)
        self.x += self.v * dt
        self.travel += abs(self.v * dt) / drive.k
        drive.target_inc = int(round(self.x))
        phys = self._phys_mm(drive)
        neg, pos = self.home_switch_mm
        on_switch = phys <= neg if self.dir < 0 else phys >= pos
        if ph == _SEARCH:
            if on_switch:
                self.phase = _BACKOFF
            elif self.travel > MAX_SEARCH_MM:
                self.phase = _ERROR
                self.v = 0.0
                drive.target_inc = drive.pos_inc
        elif ph == _BACKOFF and not on_switch and self.v * self.dir < 0:
            # the releasing edge is home, latched at the cycle that sees it (like a drive sampling its
            # switch input at its servo cycle): up to one cycle of travel at the zero speed past it
            self.edge_phys = phys * drive.k
            self.phase = _STOP
        elif ph == _STOP and self.v == 0.0 and abs(drive.pos_inc - drive.target_inc) <= 1 \
                and abs(getattr(drive.model, "velocity_mm_s", 0.0)) < 1e-3:
            if self.dir:                    # stopped after the edge: position := offset there
                self._set_home(drive, self.edge_phys)
                self.phase = _DONE
            else:                           # interrupted (bit 4 cleared)
                self.phase = _IDLE
            drive.target_inc = drive.pos_inc


def attach(drive) -> None:
    """Give ``drive`` homing mode 6 (objects, mode, statusword bits, controlword bit 4, the motion)."""
    _add_objects(drive.node.object_dictionary)
    h = SimHoming(drive)
    drive.homing = h
    drive.modes[MODE_HOMING] = False          # a mode that ignores 0x607A
    drive.switch_modes.update((MODE_HOMING, cia402.MODE_CSP))
    drive.hooks.on_status(h.status_bits)
    drive.hooks.on_controlword(h.on_controlword)
    drive.hooks.on_write(0x6060, h.on_mode)
    drive.hooks.on_sync(h.on_sync)
    on_nmt = drive.on_nmt

    def nmt_with_power_cycle(cmd: int) -> None:
        if cmd == 0x81:
            h.power_cycle(drive)
        on_nmt(cmd)
    drive.on_nmt = nmt_with_power_cycle


if attach not in EXTENSIONS:
    EXTENSIONS.append(attach)

__all__ = ["attach", "SimHoming", "MODE_HOMING", "CW_HOMING_START", "SW_HOMING_ATTAINED", "SW_HOMING_ERROR"]
