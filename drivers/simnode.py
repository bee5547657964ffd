"""One simulated CiA 402 drive node (used by :mod:`drivers.simdrive`), and fault specs.

canopen's ``LocalNode`` answers SDO and NMT and produces the heartbeat; :class:`SimDrive` adds
RPDO application per the SDO-configured mapping, TPDOs on SYNC and on change, the CiA 402 state
machine, software limits, following error and master-heartbeat supervision, fault injection.
"""
from __future__ import annotations

import logging
import struct
import time
from typing import TYPE_CHECKING, Callable

import canopen
from canopen.sdo import SdoAbortedError

from .errors import BusError

from . import cia402
from .simfaults import FaultSpec  # noqa: F401  (re-exported)
from .simhooks import EXTENSIONS, OdHooks
from .simreact import Reactions
from .strutmodel import StrutModel
from .touchprobe import TouchProbe

if TYPE_CHECKING:
    from .simdrive import SimDrives

log = logging.getLogger("hexacnc.simdrive")

_VALUE_RANGE = 0x06090030
_CANNOT_MAP = 0x06040041                #: "object cannot be mapped to the PDO"
#: mechanical lead of the simulated struts (mm per driving-shaft revolution); the factory value of
#: the feed constant 0x6092:1 is set so the default position unit is 1 / [bus] increments_per_mm
SIM_LEAD_MM = 5.0
_DATA_NOT_TRANSFERRED = 0x08000022     #: "because of the present device state"
_PDO_NOT_VALID = 1 << 31
_STRUCT = {0x0002: "b", 0x0003: "h", 0x0004: "i", 0x0005: "B", 0x0006: "H", 0x0007: "I"}
_DUMMIES = set(range(0x0001, 0x0008))


# --------------------------------------------------------------------------------------------
# one drive
# --------------------------------------------------------------------------------------------
class _Tpdo:
    __slots__ = ("cob_id", "trans", "start", "inhibit_s", "event_s", "st", "getters", "started",
                 "countdown", "last_s", "pending", "last_data")

    def __init__(self, cob_id, trans, start, inhibit_s, event_s, st, getters):
        self.cob_id, self.trans, self.start = cob_id, trans, start
        self.inhibit_s, self.event_s, self.st, self.getters = inhibit_s, event_s, st, getters
        self.started, self.countdown, self.last_s, self.pending, self.last_data = False, 0, -1e9, False, None


class SimDrive:
    """One simulated CiA 402 drive (all methods called with the owning :class:`SimDrives` lock held)."""

    def __init__(self, sim: "SimDrives", strut: int, node_id: int, bus_index: int, model: StrutModel,
                 start_inc: int, od):
        self.sim = sim
        self.strut = strut
        self.node_id = node_id
        self.bus_index = bus_index
        self.model = model
        self.node = canopen.LocalNode(node_id, od)
        self.k = sim.increments_per_mm
        self.state = cia402.SWITCH_ON_DISABLED
        self.cw = 0
        self.mode = 0
        self.pos_inc = start_inc
        self.demand_inc = start_inc
        self.target_inc = start_inc
        self.latched: dict[int, int] = {}
        self.ferr_inc = 0
        self.ferr_time_s = 0.0
        self.internal_limit = False
        self.error_code = 0
        self.error_register = 0
        self.ever_enabled_s: float | None = None
        self.injections = 0
        self.refuse = False
        self.silent = False
        self.scheduled: list[tuple[float, str, int]] = []    #: (due monotonic s, kind, code)
        self.pending_faults: list[FaultSpec] = []           #: armed at first enable
        self.master_hb_s: float | None = None
        self.last_sync_s = 0.0
        self.rpdo_subs: list[tuple[int, Callable]] = []
        self.tpdos: list[_Tpdo] = []
        self.last_status = -1
        self.stuck = False
        self._window = 10000
        self._ferr_timeout_s = 0.01
        self._limits = (-(1 << 31), (1 << 31) - 1)
        self._dt_s = 0.0005
        self._consumer = (0, 0.0)
        self.model.reset(start_inc / self.k)
        self.hooks = OdHooks()
        #: modes of operation accepted by 0x6060 -> True when the mode follows 0x607A (extensions add theirs)
        self.modes: dict[int, bool] = {0: True, cia402.MODE_CSP: True}
        #: modes the drive switches between while Operation enabled (extensions, e.g. homing: {6, 8})
        self.switch_modes: set[int] = set()
        self.react = Reactions(self)
        self.dummies = frozenset(getattr(sim, "dummies", frozenset(range(1, 8))))
        self.disabling = False              #: transition 5 asked, ramping down first (0x605C = 1)
        self._ip_index_range = (od[0x60C2][2].min, od[0x60C2][2].max) if 0x60C2 in od else (None, None)
        if 0x6092 in od:                    # factory feed constant: default units = 1 / increments_per_mm
            od[0x6092][1].default = int(round(self.k * SIM_LEAD_MM))
        self.touch = TouchProbe()             #: 0x60B8-0x60BB; input from ``sim.probe_signal(strut, now)``
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        for ext in EXTENSIONS:
            ext(self)

    def raw_or(self, index: int, sub: int, default: int) -> int:
        """Value of an object, ``default`` when this drive's description lacks it."""
        od = self.node.object_dictionary
        if index not in od:
            return default
        if not isinstance(od[index], canopen.objectdictionary.ODVariable) and sub not in od[index]:
            return default
        return self.raw(index, sub)

    def model_amax(self) -> float:
        return float(getattr(self.model, "amax", 20000.0))

    # -- object access ----------------------------------------------------------------------
    def raw(self, index: int, sub: int = 0) -> int:
        """Current value of an object (through the local SDO server: callbacks, store, EDS default)."""
        if isinstance(self.node.object_dictionary[index], canopen.objectdictionary.ODVariable):
            return self.node.sdo[index].raw
        return self.node.sdo[index][sub].raw

    def statusword(self) -> int:
        sw = cia402.drive_statusword(self.state)
        if self.state == cia402.OPERATION_ENABLED and self.mode == cia402.MODE_CSP:
            sw |= cia402.SW_DRIVE_FOLLOWS
            if abs(self.ferr_inc) > self._window:
                sw |= cia402.SW_FOLLOWING_ERROR
        if self.internal_limit:
            sw |= cia402.SW_INTERNAL_LIMIT
        # bit 10 (target reached) is reserved in cyclic synchronous position mode: left clear, so
        # the statusword (and its TPDO2 event) changes only with the state and the CSP flags
        for fn in self.hooks.status:        # mode-specific bits (e.g. homing: 10, 12, 13)
            sw |= fn(self)
        return sw

    # -- SDO callbacks ----------------------------------------------------------------------
    def _on_read(self, index, subindex, od):
        hook = self.hooks.read.get(index)
        if hook is not None:
            v = hook(subindex)
            if v is not None:
                return v
        if index == 0x6041:
            return self.statusword()
        if index == 0x6064:
            return self.pos_inc
        if index == 0x6061:
            return self.mode
        if index == 0x6060:
            return self.mode
        if index == 0x6040:
            return self.cw
        if index == 0x6062:
            return self.demand_inc
        if index == 0x606C:
            return int(round(self.model.velocity_mm_s * self.k))
        if index == 0x60F4:
            return self.ferr_inc
        if index == 0x603F:
            return self.error_code
        if index == 0x1001:
            return self.error_register
        if index == 0x607A:
            return self.target_inc
        if index == 0x2000 and subindex == 6:
            return self.injections
        if 0x60B8 <= index <= 0x60BB:
            tp = self.touch
            return (tp.function, tp.status, tp.pos_value, tp.neg_value)[index - 0x60B8]
        return None

    def _on_write(self, index, subindex, od, data):
        with self.sim.lock:
            value = od.decode_raw(data)
            if index == 0x6040:
                self.apply_controlword(value)
            elif index == 0x6060:
                if value not in self.modes:
                    raise SdoAbortedError(_VALUE_RANGE)
                if self.state == cia402.OPERATION_ENABLED and value != self.mode and not (
                        value in self.switch_modes and self.mode in self.switch_modes):
                    raise SdoAbortedError(_DATA_NOT_TRANSFERRED)
                self.mode = value
            elif index == 0x607A:
                self.target_inc = value
            elif index == 0x2000:
                self._sdo_injection(subindex, value)
            elif index == 0x60C2 and subindex == 2:
                lo, hi = self._ip_index_range
                if (lo is not None and value < lo) or (hi is not None and value > hi):
                    raise SdoAbortedError(_VALUE_RANGE)     # e.g. strict: only -3 (whole ms)
            elif 0x1600 <= index <= 0x17FF and subindex >= 1 and value:
                obj = value >> 16
                if obj < 0x20 and obj not in self.dummies:
                    raise SdoAbortedError(_CANNOT_MAP)      # dummy not allowed by [DummyUsage]
            elif index == 0x60B8:
                self.touch.write_function(value)
            for fn in self.hooks.write.get(index, ()):
                fn(subindex, value)

    def _sdo_injection(self, sub: int, value: int) -> None:
        now = time.monotonic()
        delay = self.node.data_store.get(0x2000, {}).get(2)
        delay_s = (int.from_bytes(delay, "little") if delay else 0) / 1000.0
        if sub == 1 and value:
            self.scheduled.append((now + delay_s, "emcy", value))
        elif sub == 3 and value:
            self.scheduled.append((now + delay_s, "heartbeat", 0))
        elif sub == 3:
            self.silent = False
        elif sub == 4:
            if value:
                self.scheduled.append((now + delay_s, "stuck", 0))
            else:
                self._set_stuck(False)
        elif sub == 5:
            self.refuse = bool(value)

    def _set_stuck(self, on: bool) -> None:
        self.stuck = on

    def apply_injection(self, kind: str, code: int) -> None:
        self.injections += 1
        log.info("node %d: injecting %s %s", self.node_id, kind, f"0x{code:04X}" if code else "")
        if kind == "emcy":
            self.fault(code)
        elif kind == "heartbeat":
            self.silent = True
            self.node.nmt.stop_heartbeat()
        elif kind == "stuck":
            self._set_stuck(True)
        elif kind == "refuse":
            self.refuse = True

    # -- state machine ----------------------------------------------------------------------
    def apply_controlword(self, cw: int) -> None:
        for fn in self.hooks.controlword:
            fn(self, cw)
        prev, self.cw = self.cw, cw
        now = time.monotonic()
        for _ in range(3):                  # 0x0F from Ready to switch on: transitions 3 then 4
            new, num = cia402.drive_step(self.state, cw, prev)
            if not num:
                break
            if self.disabling:              # ramping down for transition 5: no other command
                break
            if num == 5 and self.react.disable_operation(now):
                self.disabling = True       # stays Operation enabled until the ramp ends
                break
            if num == 11:
                self.state = new
                self.react.quick_stop_option(now, "quick stop (controlword bit 2)")
                break
            if num in (8, 9, 12):
                self.react.ramp = None
            if num in (4, 16):
                if self.refuse:
                    log.info("node %d: refusing transition %d (injected)", self.node_id, num)
                    break
                if self.mode != cia402.MODE_CSP:
                    break                   # no mode selected: stays Switched on
                self.demand_inc = self.target_inc = self.pos_inc
                self.react.fill_demands(self.pos_inc / self.k)
                self.latched.pop(0x607A, None)
                self.ferr_time_s = 0.0
                self.model.reset(self.pos_inc / self.k)
                if self.ever_enabled_s is None:
                    self.ever_enabled_s = time.monotonic()
                    for f in self.pending_faults:
                        self.scheduled.append((self.ever_enabled_s + f.delay_s, f.kind, f.code))
                    self.pending_faults = []
            if num == cia402.T_FAULT_RESET:
                self.error_code = 0
                self.error_register = 0
                self.node.emcy.reset()
            self.state = new
            prev = cw
        self.status_changed()

    def fault(self, code: int, send_emcy: bool = True) -> None:
        if self.state in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE):
            return
        was_moving = self.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE)
        self.error_code = code
        reg = 0x01
        cls = code & 0xF000
        reg |= {0x2000: 0x02, 0x3000: 0x04, 0x4000: 0x08, 0x8000: 0x10 if code & 0xFF00 == 0x8100 else 0x20}.get(cls, 0)
        self.error_register = reg
        log.info("node %d: fault %s", self.node_id, cia402.emcy_text(code, reg))
        if send_emcy:
            self.node.emcy.send(code, reg)
        self.state = cia402.FAULT_REACTION_ACTIVE
        self.disabling = False
        if was_moving:
            self.react.fault_reaction(time.monotonic())
        else:
            self.react.ramp = None
        self.status_changed()

    # -- NMT --------------------------------------------------------------------------------
    def on_nmt(self, cmd: int) -> None:
        if cmd in (0x81, 0x82):
            self.unsubscribe_pdos()
            self.node.nmt.stop_heartbeat()
            if cmd == 0x81:
                self.node.data_store.clear()
                if self.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.SWITCHED_ON,
                                  cia402.READY_TO_SWITCH_ON):
                    self.state = cia402.SWITCH_ON_DISABLED
                self.mode = 0
                self.cw = 0
            else:
                for idx in [i for i in self.node.data_store if 0x1000 <= i < 0x2000]:
                    del self.node.data_store[idx]
            self.master_hb_s = None
            self.react.ramp = None
            self.disabling = False
            self.boot()
        elif cmd == 0x01:
            self.configure_pdos()
        elif cmd in (0x02, 0x80):
            if self.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE):
                self.fault(0x8100)          # lost the PDO communication while enabled
            self.unsubscribe_pdos()

    def boot(self) -> None:
        self.node.nmt._state = 0
        self.node.nmt.send_command(0x81)    # boot-up message
        self.node.nmt.send_command(0x80)    # pre-operational; heartbeat per 0x1017
        if self.silent:
            self.node.nmt.stop_heartbeat()
        self.last_status = -1

    # -- PDO configuration --------------------------------------------------------------------
    def _mapping(self, map_index: int) -> list[tuple[int, int, int]]:
        n = self.raw(map_index, 0)
        out = []
        for s in range(1, n + 1):
            v = self.raw(map_index, s)
            out.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
        return out

    def _struct(self, mapping):
        fmt = "<"
        objs = []
        for index, sub, bits in mapping:
            if index in _DUMMIES:
                fmt += f"{bits // 8}x"      # skip (RPDO) / zero bytes (TPDO)
                continue
            od = self.node.object_dictionary[index]
            if not isinstance(od, canopen.objectdictionary.ODVariable):
                od = od[sub]
            code = _STRUCT.get(od.data_type)
            if code is None or struct.calcsize(code) * 8 != bits:
                raise BusError(f"node {self.node_id}: cannot map 0x{index:04X}:{sub:02X} with {bits} bits")
            fmt += code
            objs.append(index)
        return struct.Struct(fmt), objs

    def configure_pdos(self) -> None:
        """Entering NMT OPERATIONAL: read the PDO configuration from the object dictionary."""
        self.unsubscribe_pdos()
        net = self.sim.networks[self.bus_index]
        for n in range(4):
            cob = self.raw(0x1400 + n, 1)
            if cob & _PDO_NOT_VALID:
                continue
            trans = self.raw(0x1400 + n, 2)
            st, objs = self._struct(self._mapping(0x1600 + n))
            cb = self._make_rpdo_handler(st, objs, trans <= 240)
            net.subscribe(cob & 0x7FF, cb)
            self.rpdo_subs.append((cob & 0x7FF, cb))
        self.tpdos = []
        for n in range(4):
            cob = self.raw(0x1800 + n, 1)
            if cob & _PDO_NOT_VALID:
                continue
            st, objs = self._struct(self._mapping(0x1A00 + n))
            getters = [self._getter(i) for i in objs]
            self.tpdos.append(_Tpdo(cob & 0x7FF, self.raw(0x1800 + n, 2), self.raw(0x1800 + n, 6),
                                    self.raw(0x1800 + n, 3) * 1e-4, self.raw(0x1800 + n, 5) * 1e-3, st, getters))
        self._window = self.raw(0x6065)
        self._ferr_timeout_s = self.raw(0x6066) * 1e-3
        self._limits = (self.raw(0x607D, 1), self.raw(0x607D, 2))
        self._dt_s = self.raw(0x60C2, 1) * 10.0 ** self.raw(0x60C2, 2)
        self._set_units()
        self.react.configure()
        hb = self.raw(0x1016, 1)
        self._consumer = ((hb >> 16) & 0x7F, (hb & 0xFFFF) * 1e-3)
        if self._consumer[1] > 0:
            sub = (0x700 + self._consumer[0], self.sim._on_master_heartbeat)
            if sub not in self.sim._hb_subs[self.bus_index]:
                net.subscribe(*sub)
                self.sim._hb_subs[self.bus_index].append(sub)
        self.last_status = -1
        self.status_changed()

    def _set_units(self) -> None:
        """Position units per mm from the feed constant 0x6092 (SIM_LEAD_MM per shaft revolution);
        the strut stays where it is, its reading is rescaled."""
        feed, revs = self.raw_or(0x6092, 1, 0), self.raw_or(0x6092, 2, 0)
        if feed <= 0 or revs <= 0:
            return
        k = feed / revs / SIM_LEAD_MM
        if abs(k - self.k) > 1e-12 * k:
            x = self.pos_inc / self.k
            log.info("node %d: position units %g per mm (0x6092 %d/%d, lead %g mm)", self.node_id, k, feed, revs,
                     SIM_LEAD_MM)
            self.k = k
            self.pos_inc = self.demand_inc = self.target_inc = int(round(x * k))

    def unsubscribe_pdos(self) -> None:
        net = self.sim.networks[self.bus_index]
        for cob, cb in self.rpdo_subs:
            net.unsubscribe(cob, cb)
        self.rpdo_subs = []
        self.tpdos = []

    def _getter(self, index: int) -> Callable[[], int]:
        return {            # other objects: an extension's read hook (e.g. 0x6077, drivers/simtorque), else 0
            0x6041: self.statusword, 0x6064: lambda: self.pos_inc, 0x6061: lambda: self.mode,
            0x6062: lambda: self.demand_inc, 0x60F4: lambda: self.ferr_inc, 0x603F: lambda: self.error_code,
            0x606C: lambda: int(round(self.model.velocity_mm_s * self.k)),
        }.get(index, lambda: self.hooks.read.get(index, lambda sub: 0)(0) or 0)

    def _make_rpdo_handler(self, st: struct.Struct, objs: list[int], synchronous: bool):
        def handler(can_id, data, timestamp):
            if len(data) < st.size:
                with self.sim.lock:
                    self.node.emcy.send(0x8210, 0x11)     # PDO not processed due to length error
                return
            values = st.unpack_from(data)
            with self.sim.lock:
                self.react.rpdo_received(time.monotonic())
                try:
                    for obj, v in zip(objs, values):
                        if synchronous:
                            self.latched[obj] = v
                        else:
                            self.apply_object(obj, v)
                except Exception:   # never let a bug kill the bus listener
                    log.exception("node %d RPDO 0x%03X", self.node_id, can_id)
        return handler

    def apply_object(self, obj: int, v: int) -> None:
        if obj == 0x6040:
            if v != self.cw:
                self.apply_controlword(v)
        elif obj == 0x607A:
            if self.modes.get(self.mode, True):     # e.g. homing mode ignores the cyclic target
                self.target_inc = v
        elif obj == 0x6060:
            if v in (0, cia402.MODE_CSP) and self.state != cia402.OPERATION_ENABLED:
                self.mode = v

    # -- cycle ------------------------------------------------------------------------------
    def on_sync(self, counter: int, now: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        self.last_sync_s = now
        if self.latched:
            for obj, v in self.latched.items():
                self.apply_object(obj, v)
            self.latched.clear()
        self.step(self._dt_s, now)
        for tp in self.tpdos:
            if tp.trans == 0 or tp.trans > 240:
                continue
            if not tp.started:
                if tp.start and counter != tp.start:
                    continue
                tp.started, tp.countdown = True, 0
            if tp.countdown == 0:
                self.send_tpdo(tp, now)
                tp.countdown = tp.trans - 1
            else:
                tp.countdown -= 1
        self.status_changed(now)
        for tp in self.tpdos:           # statusword changes held back by the inhibit time
            if tp.pending and now - tp.last_s >= tp.inhibit_s:
                self.send_tpdo(tp, now)

    def step(self, dt: float, now: float, own_clock: bool = False) -> None:
        """One interpolation period: follow the target (Operation enabled), a stop ramp (quick stop,
        fault reaction, disable operation) or coast/brake (power stage off)."""
        st = self.state
        enabled = st == cia402.OPERATION_ENABLED and not self.disabling
        ramp = self.react.ramp
        if not own_clock:
            self.react.last_step_s = now
        if enabled:
            lo, hi = self._limits
            t = self.target_inc
            self.internal_limit = not (lo <= t <= hi)
            self.demand_inc = min(hi, max(lo, t))
            if self.stuck:              # injected: the strut does not move whatever the demand
                x = self.pos_inc / self.k
                self.model.reset(x)
            else:
                x = self.model.step(self.demand_inc / self.k, dt, True)
        elif ramp is not None:
            demand_mm = self.react.ramp_demand(dt)
            self.demand_inc = int(round(demand_mm * self.k))
            x = self.model.step(demand_mm, dt, True)
        else:
            x = self.model.step(self.pos_inc / self.k, dt, False)
            self.demand_inc = self.pos_inc
        self.pos_inc = int(round(x * self.k))
        self.react.track_demand(self.demand_inc / self.k)
        if self.touch.function & 1:
            sig = getattr(self.sim, "probe_signal", None)
            if sig is not None:
                self.touch.sample(self.pos_inc, sig(self.strut, now))
        self.ferr_inc = self.demand_inc - self.pos_inc if enabled else 0
        if enabled and abs(self.ferr_inc) > self._window:
            self.ferr_time_s += dt
            if self.ferr_time_s > self._ferr_timeout_s:
                self.fault(cia402.EMCY_FOLLOWING_ERROR)
        else:
            self.ferr_time_s = 0.0
        for fn in self.hooks.sync:
            fn(self, now)
        self.settle(now)

    def settle(self, now: float) -> None:
        """Automatic transitions once the strut stands still: 12 (quick stop per 0x605A), 14 (fault
        reaction done), the end of transition 5 (disable operation per 0x605C)."""
        ramp = self.react.ramp
        if ramp is not None:
            if not ramp.done or abs(self.model.velocity_mm_s) > 1e-3:
                return
            self.react.ramp = None
            self.react.note(now, f"stopped at {self.pos_inc / self.k:.4f} mm")
            if self.disabling:
                self.disabling = False
                self.state = cia402.SWITCHED_ON
            elif ramp.then is not None and self.state in (cia402.QUICK_STOP_ACTIVE, cia402.FAULT_REACTION_ACTIVE):
                self.state = ramp.then
            self.status_changed(now)
            return
        if self.state == cia402.FAULT_REACTION_ACTIVE:
            if abs(self.model.velocity_mm_s) < 1e-9 or now - self.last_sync_s > 0.02:
                self.state = cia402.FAULT
                self.status_changed(now)

    def send_tpdo(self, tp: _Tpdo, now: float) -> None:
        data = tp.st.pack(*[g() for g in tp.getters])
        tp.last_s = now
        tp.pending = False
        tp.last_data = data
        self.sim.send(self.bus_index, tp.cob_id, data)

    def status_changed(self, now: float | None = None) -> None:
        sw = self.statusword()
        if sw == self.last_status:
            return
        self.last_status = sw
        if self.node.nmt.state != "OPERATIONAL":
            return
        t = time.monotonic() if now is None else now
        for tp in self.tpdos:
            if tp.trans >= 254:
                if t - tp.last_s >= tp.inhibit_s:
                    self.send_tpdo(tp, t)
                else:
                    tp.pending = True

    def housekeeping(self, now: float) -> None:
        due = [s for s in self.scheduled if s[0] <= now]
        if due:
            self.scheduled = [s for s in self.scheduled if s[0] > now]
            for _, kind, code in due:
                self.apply_injection(kind, code)
        if self.silent and self.node.nmt._send_task is not None:
            self.node.nmt.stop_heartbeat()
        self.master_hb_s = self.react.excuse_own_stall(now, self.master_hb_s)
        if self.node.nmt.state == "OPERATIONAL":
            for tp in self.tpdos:
                if tp.trans >= 254 and ((tp.pending and now - tp.last_s >= tp.inhibit_s)
                                        or (tp.event_s > 0 and now - tp.last_s >= tp.event_s)):
                    self.send_tpdo(tp, now)
            cons_id, cons_s = self._consumer
            if cons_s > 0 and self.master_hb_s is not None and now - self.master_hb_s > cons_s:
                self.master_hb_s = None     # report once, re-armed by the next heartbeat
                self.react.comm_loss(cia402.EMCY_HEARTBEAT, now, f"master heartbeat missing for {cons_s * 1e3:g} ms "
                                     "(0x1016)")
        self.react.supervise(now)
        if self.react.ramp is None:
            self.settle(now)
