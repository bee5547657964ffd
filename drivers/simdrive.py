"""Simulated CiA 402 strut drives: six CANopen nodes built from ``hexapod_drive.eds``.

canopen's ``LocalNode`` answers SDO, NMT and produces the heartbeat; everything else is done
here: RPDOs applied per the SDO-configured mapping (synchronous ones latched until SYNC,
asynchronous ones at once), TPDOs sent on SYNC (transmission type, SYNC counter start value) and
on statusword change (inhibit time, event timer), the CiA 402 state machine
(:mod:`drivers.cia402`), software position limits (0x607D), following error supervision
(0x6065 window, 0x6066 time-out -> EMCY 0x8611 + Fault), consumer heartbeat of the master
(0x1016 -> EMCY 0x8130 + Fault) and fault injection.

Each strut moves through a pluggable model (:class:`StrutModel`): by default
:class:`SecondOrderStrut`, a second-order position loop with velocity feed-forward, velocity and
acceleration limits, stepped once per SYNC by the interpolation period 0x60C2.

Fault injection (manufacturer object 0x2000, or ``--fault`` / ``faults=``):

=========== ====================== =========================================================
 0x2000 sub  spec (``--fault``)     effect
=========== ====================== =========================================================
 1 (+2)      ``N:emcy:CODE@T``       EMCY CODE and Fault, T s after the drive is enabled
 3           ``N:heartbeat@T``       stop producing the heartbeat
 4           ``N:stuck@T``           strut stuck: following error grows -> EMCY 0x8611, Fault
 5           ``N:refuse``            drive refuses transition 4 (stays Switched on)
=========== ====================== =========================================================

``N`` is the node id; via SDO, sub 2 is a delay in ms from the write. Run as a process::

    python -m drivers.simdrive --config F [--interface udp_multicast] [--channel C] [--fault SPEC]...
                               [--model package.module:factory]

It prints ``READY`` on stdout once the nodes have booted and runs until SIGTERM/SIGINT.
In-process (``virtual`` bus, unit tests): ``SimDrives(cfg, buses).start()`` / ``.stop()``.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import can
import canopen
from canopen.sdo import SdoAbortedError

from hexacnc.errors import BusError, ConfigError

from . import EDS_PATH, cia402
from .layout import plan_layout

log = logging.getLogger("hexacnc.simdrive")

_VALUE_RANGE = 0x06090030
_DATA_NOT_TRANSFERRED = 0x08000022     #: "because of the present device state"
_PDO_NOT_VALID = 1 << 31
_STRUCT = {0x0002: "b", 0x0003: "h", 0x0004: "i", 0x0005: "B", 0x0006: "H", 0x0007: "I"}
_DUMMIES = set(range(0x0001, 0x0008))


# --------------------------------------------------------------------------------------------
# strut models
# --------------------------------------------------------------------------------------------
class StrutModel(Protocol):
    """Pluggable strut dynamics. Positions are drive readings in mm (strut length - offset)."""

    velocity_mm_s: float

    def reset(self, position_mm: float) -> None:
        """Put the strut at rest at ``position_mm``."""

    def step(self, target_mm: float, dt_s: float, enabled: bool) -> float:
        """Advance by ``dt_s`` towards ``target_mm`` (drive enabled) or braking to rest
        (disabled); returns the actual position in mm."""


#: factory: (strut index 0..5, MachineConfig or None) -> StrutModel
ModelFactory = Callable[[int, object], StrutModel]


class SecondOrderStrut:
    """Position loop with velocity feed-forward: ``a = wn^2 (xt - x) + 2 zeta wn (vt - v)``.

    ``vt`` is the target's rate (finite difference of successive targets). ``|v| <= vmax``,
    ``|a| <= amax``; disabled: braking at ``amax`` to rest. Sub-stepped so ``wn dt <= 0.2``.
    """

    def __init__(self, natural_hz: float = 60.0, damping: float = 0.9,
                 max_velocity_mm_s: float = 500.0, max_acceleration_mm_s2: float = 20000.0):
        self.wn = 2 * math.pi * natural_hz
        self.zeta = damping
        self.vmax = max_velocity_mm_s
        self.amax = max_acceleration_mm_s2
        self.x = 0.0
        self.velocity_mm_s = 0.0
        self._last_target: float | None = None

    def reset(self, position_mm: float) -> None:
        self.x = float(position_mm)
        self.velocity_mm_s = 0.0
        self._last_target = None

    def step(self, target_mm: float, dt_s: float, enabled: bool) -> float:
        if dt_s <= 0:
            return self.x
        if not enabled:
            self._last_target = None
            v = self.velocity_mm_s
            dv = self.amax * dt_s
            v = 0.0 if abs(v) <= dv else v - math.copysign(dv, v)
            self.x += 0.5 * (v + self.velocity_mm_s) * dt_s
            self.velocity_mm_s = v
            return self.x
        vt = 0.0 if self._last_target is None else (target_mm - self._last_target) / dt_s
        self._last_target = target_mm
        n = max(1, math.ceil(self.wn * dt_s / 0.2))
        h = dt_s / n
        wn2, c = self.wn * self.wn, 2 * self.zeta * self.wn
        x, v = self.x, self.velocity_mm_s
        for k in range(n):
            xt = target_mm - vt * (dt_s - (k + 1) * h)      # target interpolated inside the period
            a = wn2 * (xt - x) + c * (vt - v)
            a = max(-self.amax, min(self.amax, a))
            v = max(-self.vmax, min(self.vmax, v + a * h))
            x += v * h
        self.x, self.velocity_mm_s = x, v
        return x


def default_model_factory(strut: int, cfg) -> StrutModel:
    """Drive limits somewhat above the machine's strut limits, so legitimate motion never saturates."""
    if cfg is None:
        return SecondOrderStrut()
    return SecondOrderStrut(natural_hz=60.0, damping=0.9,
                            max_velocity_mm_s=1.5 * float(cfg.max_velocity_mm_s[strut]),
                            max_acceleration_mm_s2=3.0 * float(cfg.max_acceleration_mm_s2[strut]))


# --------------------------------------------------------------------------------------------
# fault specs
# --------------------------------------------------------------------------------------------
@dataclass
class FaultSpec:
    node_id: int
    kind: str             #: emcy | heartbeat | stuck | refuse
    code: int = 0x1000    #: EMCY code (kind emcy)
    delay_s: float = 0.0  #: after the drive first reaches Operation enabled

    KINDS = ("emcy", "heartbeat", "stuck", "refuse")

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """``N:emcy:0x3210@1.5``, ``N:heartbeat@2``, ``N:stuck@0.5``, ``N:refuse``."""
        body, _, delay = text.partition("@")
        parts = body.split(":")
        try:
            node = int(parts[0], 0)
            kind = parts[1]
            if kind not in cls.KINDS:
                raise ValueError(f"kind {kind!r} is not one of {', '.join(cls.KINDS)}")
            code = int(parts[2], 0) if kind == "emcy" and len(parts) > 2 else 0x1000
            if kind != "emcy" and len(parts) > 2 or len(parts) > 3:
                raise ValueError("too many ':' fields")
            d = float(delay) if delay else 0.0
            if not (0 <= d < 1e6) or not (1 <= node <= 127) or not (0 < code <= 0xFFFF):
                raise ValueError("node 1..127, code 1..0xFFFF, delay >= 0")
        except (ValueError, IndexError) as exc:
            raise ConfigError(f"--fault {text!r}: expected NODE:emcy:CODE@S, NODE:heartbeat@S, "
                              f"NODE:stuck@S or NODE:refuse ({exc})") from None
        return cls(node, kind, code, d)


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
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)

    # -- object access ----------------------------------------------------------------------
    def raw(self, index: int, sub: int = 0) -> int:
        """Current value of an object (through the local SDO server: callbacks, store, EDS default)."""
        if isinstance(self.node.object_dictionary[index], canopen.objectdictionary.ODVariable):
            return self.node.sdo[index].raw
        return self.node.sdo[index][sub].raw

    def statusword(self) -> int:
        sw = cia402.STATE_STATUS_BITS[self.state] | cia402.SW_REMOTE
        if self.state in (cia402.READY_TO_SWITCH_ON, cia402.SWITCHED_ON, cia402.OPERATION_ENABLED,
                          cia402.QUICK_STOP_ACTIVE):
            sw |= cia402.SW_VOLTAGE_ENABLED
        if self.state == cia402.OPERATION_ENABLED and self.mode == cia402.MODE_CSP:
            sw |= cia402.SW_DRIVE_FOLLOWS
            if abs(self.ferr_inc) > self.sim_window():
                sw |= cia402.SW_FOLLOWING_ERROR
        if self.internal_limit:
            sw |= cia402.SW_INTERNAL_LIMIT
        if abs(self.model.velocity_mm_s) < 1e-6 and abs(self.ferr_inc) <= 1:
            sw |= cia402.SW_TARGET_REACHED
        return sw

    def sim_window(self) -> int:
        return self._window

    # -- SDO callbacks ----------------------------------------------------------------------
    def _on_read(self, index, subindex, od):
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
        return None

    def _on_write(self, index, subindex, od, data):
        with self.sim.lock:
            value = od.decode_raw(data)
            if index == 0x6040:
                self.apply_controlword(value)
            elif index == 0x6060:
                if value not in (0, cia402.MODE_CSP):
                    raise SdoAbortedError(_VALUE_RANGE)
                if self.state == cia402.OPERATION_ENABLED and value != self.mode:
                    raise SdoAbortedError(_DATA_NOT_TRANSFERRED)
                self.mode = value
            elif index == 0x607A:
                self.target_inc = value
            elif index == 0x2000:
                self._sdo_injection(subindex, value)

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
        prev, self.cw = self.cw, cw
        for _ in range(3):                  # 0x0F from Ready to switch on: transitions 3 then 4
            new, num = cia402.drive_step(self.state, cw, prev)
            if not num:
                break
            if num in (4, 16):
                if self.refuse:
                    log.info("node %d: refusing transition %d (injected)", self.node_id, num)
                    break
                if self.mode != cia402.MODE_CSP:
                    break                   # no mode selected: stays Switched on
                self.demand_inc = self.target_inc = self.pos_inc
                self.latched.pop(0x607A, None)
                self.ferr_time_s = 0.0
                self.model.reset(self.model_position())
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

    def model_position(self) -> float:
        return self.pos_inc / self.k

    def fault(self, code: int) -> None:
        if self.state in (cia402.FAULT, cia402.FAULT_REACTION_ACTIVE):
            return
        self.error_code = code
        reg = 0x01
        cls = code & 0xF000
        reg |= {0x2000: 0x02, 0x3000: 0x04, 0x4000: 0x08, 0x8000: 0x10 if code & 0xFF00 == 0x8100 else 0x20}.get(cls, 0)
        self.error_register = reg
        log.info("node %d: fault %s", self.node_id, cia402.emcy_text(code, reg))
        self.node.emcy.send(code, reg)
        self.state = cia402.FAULT_REACTION_ACTIVE
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

    def _struct(self, mapping, tx: bool):
        fmt = "<"
        objs = []
        for index, sub, bits in mapping:
            if index in _DUMMIES:
                fmt += f"{bits // 8}x"
                if tx:
                    pass
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
            st, objs = self._struct(self._mapping(0x1600 + n), tx=False)
            cb = self._make_rpdo_handler(st, objs, trans <= 240)
            net.subscribe(cob & 0x7FF, cb)
            self.rpdo_subs.append((cob & 0x7FF, cb))
        self.tpdos = []
        for n in range(4):
            cob = self.raw(0x1800 + n, 1)
            if cob & _PDO_NOT_VALID:
                continue
            st, objs = self._struct(self._mapping(0x1A00 + n), tx=True)
            getters = [self._getter(i) for i in objs]
            self.tpdos.append(_Tpdo(cob & 0x7FF, self.raw(0x1800 + n, 2), self.raw(0x1800 + n, 6),
                                    self.raw(0x1800 + n, 3) * 1e-4, self.raw(0x1800 + n, 5) * 1e-3, st, getters))
        self._window = self.raw(0x6065)
        self._ferr_timeout_s = self.raw(0x6066) * 1e-3
        self._limits = (self.raw(0x607D, 1), self.raw(0x607D, 2))
        self._dt_s = self.raw(0x60C2, 1) * 10.0 ** self.raw(0x60C2, 2)
        hb = self.raw(0x1016, 1)
        self._consumer = ((hb >> 16) & 0x7F, (hb & 0xFFFF) * 1e-3)
        if self._consumer[1] > 0:
            sub = (0x700 + self._consumer[0], self.sim._on_master_heartbeat)
            if sub not in self.sim._hb_subs[self.bus_index]:
                net.subscribe(*sub)
                self.sim._hb_subs[self.bus_index].append(sub)
        self.last_status = -1
        self.status_changed()

    def unsubscribe_pdos(self) -> None:
        net = self.sim.networks[self.bus_index]
        for cob, cb in self.rpdo_subs:
            net.unsubscribe(cob, cb)
        self.rpdo_subs = []
        self.tpdos = []

    def _getter(self, index: int) -> Callable[[], int]:
        return {
            0x6041: self.statusword, 0x6064: lambda: self.pos_inc, 0x6061: lambda: self.mode,
            0x6062: lambda: self.demand_inc, 0x60F4: lambda: self.ferr_inc, 0x603F: lambda: self.error_code,
            0x606C: lambda: int(round(self.model.velocity_mm_s * self.k)),
        }.get(index, lambda: 0)

    def _make_rpdo_handler(self, st: struct.Struct, objs: list[int], synchronous: bool):
        def handler(can_id, data, timestamp):
            if len(data) < st.size:
                with self.sim.lock:
                    self.node.emcy.send(0x8210, 0x11)     # PDO not processed due to length error
                return
            values = st.unpack_from(data)
            with self.sim.lock:
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

    def step(self, dt: float, now: float) -> None:
        st = self.state
        enabled = st == cia402.OPERATION_ENABLED
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
        else:
            x = self.model.step(self.pos_inc / self.k, dt, False)
            self.demand_inc = self.pos_inc
        self.pos_inc = int(round(x * self.k))
        self.ferr_inc = self.demand_inc - self.pos_inc if enabled else 0
        if enabled and abs(self.ferr_inc) > self._window:
            self.ferr_time_s += dt
            if self.ferr_time_s > self._ferr_timeout_s:
                self.fault(cia402.EMCY_FOLLOWING_ERROR)
        else:
            self.ferr_time_s = 0.0
        self.settle(now)

    def settle(self, now: float) -> None:
        """Automatic transitions once the strut stands still (12, 14)."""
        if self.state in (cia402.FAULT_REACTION_ACTIVE, cia402.QUICK_STOP_ACTIVE):
            if abs(self.model.velocity_mm_s) < 1e-9 or now - self.last_sync_s > 0.02:
                self.state = cia402.FAULT if self.state == cia402.FAULT_REACTION_ACTIVE \
                    else cia402.SWITCH_ON_DISABLED
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
        if self.node.nmt.state == "OPERATIONAL":
            for tp in self.tpdos:
                if tp.trans >= 254 and ((tp.pending and now - tp.last_s >= tp.inhibit_s)
                                        or (tp.event_s > 0 and now - tp.last_s >= tp.event_s)):
                    self.send_tpdo(tp, now)
            cons_id, cons_s = self._consumer
            if cons_s > 0 and self.master_hb_s is not None and now - self.master_hb_s > cons_s:
                self.master_hb_s = None     # report once, re-armed by the next heartbeat
                if self.state in (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.SWITCHED_ON,
                                  cia402.READY_TO_SWITCH_ON):
                    self.fault(cia402.EMCY_HEARTBEAT)
                else:
                    self.node.emcy.send(cia402.EMCY_HEARTBEAT, 0x11)
        self.settle(now)


# --------------------------------------------------------------------------------------------
# the six drives
# --------------------------------------------------------------------------------------------
class SimDrives:
    """Six simulated drives on ``buses`` (one bus object per ``[bus] buses``, strut split per layout).

    ``cfg``: MachineConfig; ``model_factory(strut, cfg) -> StrutModel``; ``faults``: FaultSpecs;
    ``start_positions_inc``: initial drive readings (default: the home pose).
    """

    def __init__(self, cfg, buses: can.BusABC | Sequence[can.BusABC], *,
                 model_factory: ModelFactory | None = None, faults: Sequence[FaultSpec] = (),
                 start_positions_inc: Sequence[int] | None = None, eds_path=EDS_PATH):
        if isinstance(buses, can.BusABC):
            buses = [buses]
        self.cfg = cfg
        self.plan = plan_layout(cfg.bus)
        if len(buses) != self.plan.buses:
            raise ValueError(f"SimDrives: {len(buses)} bus objects for [bus] buses = {self.plan.buses}")
        self.buses = list(buses)
        self.lock = threading.RLock()
        self.increments_per_mm = cfg.bus.increments_per_mm
        if start_positions_inc is None:
            from hexacnc.kinematics import Hexapod
            lengths = Hexapod(cfg).lengths(cfg.home_pose)
            start_positions_inc = [round((float(lengths[i]) - float(cfg.strut_offset_mm[i])) *
                                         self.increments_per_mm) for i in range(6)]
        factory = model_factory or default_model_factory
        self.networks = [canopen.Network(b) for b in self.buses]
        self._hb_subs: list[list] = [[] for _ in self.buses]
        self.drives: list[SimDrive] = []
        self.by_node: dict[int, SimDrive] = {}
        for nd in self.plan.nodes:
            od = canopen.import_od(str(eds_path), nd.node_id)
            d = SimDrive(self, nd.index, nd.node_id, nd.bus, factory(nd.index, cfg),
                         int(start_positions_inc[nd.index]), od)
            self.networks[nd.bus].add_node(d.node)
            self.drives.append(d)
            self.by_node[nd.node_id] = d
        for f in faults:
            d = self.by_node.get(f.node_id)
            if d is None:
                raise ConfigError(f"fault {f}: node {f.node_id} is not in [bus] node_ids {list(cfg.bus.node_ids)}")
            if f.kind == "refuse":
                d.refuse = True
            else:
                d.pending_faults.append(f)
        for b, net in enumerate(self.networks):
            net.subscribe(0x000, self._make_nmt_handler(b))
            net.subscribe(0x080, self._make_sync_handler(b))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fd = self.plan.fd

    def _make_nmt_handler(self, b: int):
        drives = [d for d in self.drives if d.bus_index == b]

        def handler(can_id, data, timestamp):
            if len(data) < 2:
                return
            cmd, nid = data[0], data[1]
            with self.lock:
                for d in drives:
                    if nid in (0, d.node_id):
                        try:
                            d.on_nmt(cmd)
                        except Exception:
                            log.exception("node %d NMT 0x%02X", d.node_id, cmd)
        return handler

    def _make_sync_handler(self, b: int):
        drives = [d for d in self.drives if d.bus_index == b]

        def handler(can_id, data, timestamp):
            counter = data[0] if len(data) else 0
            now = time.monotonic()
            with self.lock:
                for d in drives:
                    try:
                        d.on_sync(counter, now)
                    except Exception:
                        log.exception("node %d SYNC", d.node_id)
        return handler

    def _on_master_heartbeat(self, can_id, data, timestamp):
        now = time.monotonic()
        with self.lock:
            for d in self.drives:
                if d._consumer[0] == can_id - 0x700:
                    d.master_hb_s = now

    def send(self, bus_index: int, cob_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                          is_fd=self._fd, bitrate_switch=self._fd)
        try:
            self.buses[bus_index].send(msg)
        except can.CanError as exc:
            log.warning("bus %d: cannot send 0x%03X: %s", bus_index, cob_id, exc)

    def start(self) -> "SimDrives":
        """Attach to the buses, boot every node (boot-up message, pre-operational)."""
        for net in self.networks:
            net.notifier = can.Notifier(net.bus, net.listeners, 0.05)
        with self.lock:
            for d in self.drives:
                d.boot()
        self._thread = threading.Thread(target=self._housekeeping, name="simdrive-housekeeping", daemon=True)
        self._thread.start()
        return self

    def _housekeeping(self) -> None:
        while not self._stop.wait(0.005):
            now = time.monotonic()
            with self.lock:
                for d in self.drives:
                    try:
                        d.housekeeping(now)
                    except Exception:     # keep the simulator alive; log the bug
                        log.exception("node %d housekeeping", d.node_id)

    def stop(self) -> None:
        """Stop heartbeats and listeners; the bus objects stay open (owned by the caller)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        for d in self.drives:
            d.node.nmt.stop_heartbeat()
        for net in self.networks:
            if net.notifier is not None:
                net.notifier.stop(2.0)
                net.notifier = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- inspection (tests) -----------------------------------------------------------------
    def positions_inc(self) -> list[int]:
        with self.lock:
            return [d.pos_inc for d in self.drives]

    def states(self) -> list[int]:
        with self.lock:
            return [d.state for d in self.drives]


# --------------------------------------------------------------------------------------------
# process entry
# --------------------------------------------------------------------------------------------
def spawn(config_path: str | os.PathLike | None, *, interface: str | None = None, channel: str | None = None,
          faults: Sequence[str] = (), ready_timeout_s: float = 20.0, env: dict | None = None,
          extra_args: Sequence[str] = (), model: str | None = None) -> subprocess.Popen:
    """Start ``python -m drivers.simdrive`` and wait for its ``READY`` line; returns the process.

    Stop it with ``proc.terminate(); proc.wait()``. Raises :class:`BusError` if it exits or
    does not get ready in time (its stderr in the message).
    """
    cmd = [sys.executable, "-m", "drivers.simdrive"]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if interface:
        cmd += ["--interface", interface]
    if channel:
        cmd += ["--channel", channel]
    for f in faults:
        cmd += ["--fault", f]
    if model:
        cmd += ["--model", model]
    cmd += list(extra_args)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    e = dict(os.environ if env is None else env)
    e["PYTHONPATH"] = root + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=e)
    deadline = time.monotonic() + ready_timeout_s
    import selectors
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    while time.monotonic() < deadline:
        if sel.select(timeout=0.1):
            line = proc.stdout.readline()
            if line.strip() == "READY":
                sel.close()
                return proc
            if not line and proc.poll() is not None:
                break
    sel.close()
    proc.kill()
    _, err = proc.communicate(timeout=5)
    raise BusError(f"simulated drives did not start ({' '.join(cmd)}): {err.strip()[-2000:]}")


def load_model_factory(spec: str) -> ModelFactory:
    """``"package.module:callable"`` -> the callable (a :data:`ModelFactory`)."""
    import importlib
    mod, _, name = spec.partition(":")
    try:
        obj = getattr(importlib.import_module(mod), name or "model_factory")
    except (ImportError, AttributeError, ValueError) as exc:
        raise ConfigError(f"--model {spec!r}: cannot load the strut model factory: {exc}") from exc
    if not callable(obj):
        raise ConfigError(f"--model {spec!r} is not callable")
    return obj


def main(argv: Sequence[str] | None = None) -> int:
    from hexacnc.config import load_config
    from hexacnc.errors import HexacncError
    from .canbus import open_buses

    ap = argparse.ArgumentParser(prog="python -m drivers.simdrive", description="simulated CiA 402 strut drives")
    ap.add_argument("--config", help="machine description (TOML); default: the embedded default")
    ap.add_argument("--interface", choices=("socketcan", "virtual", "udp_multicast"), help="override [bus] interface")
    ap.add_argument("--channel", help="override [bus] channel")
    ap.add_argument("--fault", action="append", default=[], metavar="SPEC",
                    help="NODE:emcy:CODE@S | NODE:heartbeat@S | NODE:stuck@S | NODE:refuse (S after enable)")
    ap.add_argument("--model", metavar="MODULE:FACTORY",
                    help="strut model factory (strut index, MachineConfig) -> StrutModel; "
                         "default drivers.simdrive:default_model_factory")
    ap.add_argument("--log-level", default="WARNING")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="simdrive %(levelname)s %(message)s")
    try:
        cfg = load_config(args.config)
        if args.interface:
            import dataclasses
            cfg = cfg.replace(bus=dataclasses.replace(cfg.bus, interface=args.interface))
        faults = [FaultSpec.parse(f) for f in args.fault]
        factory = load_model_factory(args.model) if args.model else None
        buses = open_buses(cfg.bus, channel=args.channel)
    except HexacncError as exc:
        print(f"simdrive: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())
    sim = SimDrives(cfg, buses, faults=faults, model_factory=factory)
    try:
        sim.start()
        print("READY", flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        sim.stop()
        for b in buses:
            b.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
