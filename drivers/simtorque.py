"""Torque and current actual values of the simulated drives (CiA 402 0x6077 / 0x6078).

Registered in :data:`drivers.simhooks.EXTENSIONS` (imported by :mod:`drivers.simdrive`); a drive whose
description lacks 0x6077 gets nothing (an SDO read of it aborts, as on a real drive without it).

Per SYNC step the strut's acceleration is tracked from the model's velocity.  An SDO read of 0x6077
asks the host's force function ``sim.strut_force_N(strut, positions_mm, velocity_mm_s,
acceleration_mm_s2) -> N`` (tension positive; the host computes the carrier's static load through the
pose, inertia and friction, :mod:`hexacnc.sim.torque`; ``drivers`` knows no kinematics), else uses
:func:`default_force_N` (friction and a lumped moving mass only).  The force becomes a torque through the
lead ``SIM_LEAD_MM`` of the screw, then per mille of the rated torque 0x6076 (mN m); the current is the
torque over the torque constant ``rated torque / rated current`` (0x6075, mA), so both read the same
per-mille value here.  Values saturate at the INTEGER16 range.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

from . import cia402, simhooks

if TYPE_CHECKING:
    from .simnode import SimDrive

LEAD_MM = 5.0                    #: screw lead (mm per revolution), as drivers.simnode.SIM_LEAD_MM
DEFAULT_MOVING_KG = 5.0          #: lumped moving mass per strut without a host force function
DEFAULT_COULOMB_N = 20.0
DEFAULT_VISCOUS_N_S_PER_MM = 0.5
_POWERED = (cia402.OPERATION_ENABLED, cia402.QUICK_STOP_ACTIVE, cia402.FAULT_REACTION_ACTIVE)


def default_force_N(velocity_mm_s: float, acceleration_mm_s2: float) -> float:
    """Strut force without a host model: lumped inertia and friction, no static load."""
    fr = DEFAULT_COULOMB_N * (1.0 if velocity_mm_s > 1e-3 else -1.0 if velocity_mm_s < -1e-3 else 0.0)
    return DEFAULT_MOVING_KG * acceleration_mm_s2 * 1e-3 + fr + DEFAULT_VISCOUS_N_S_PER_MM * velocity_mm_s


def force_to_permille(force_N: float, rated_torque_mNm: int) -> int:
    """Per mille of the rated torque for a strut force through the screw lead (INTEGER16, saturated)."""
    torque_mNm = force_N * LEAD_MM / (2.0 * math.pi)        # N * mm / rev -> N mm -> mN m
    v = int(round(1000.0 * torque_mNm / max(1, rated_torque_mNm)))
    return max(-32768, min(32767, v))


class TorqueState:
    """Acceleration tracking and the 0x6077 / 0x6078 answers of one drive."""

    __slots__ = ("drive", "v_last", "t_last", "accel_mm_s2")

    def __init__(self, drive: "SimDrive"):
        self.drive = drive
        self.v_last = 0.0
        self.t_last = 0.0
        self.accel_mm_s2 = 0.0

    def track(self, drive: "SimDrive", now_s: float) -> None:
        v = float(drive.model.velocity_mm_s)
        dt = now_s - self.t_last
        if self.t_last and 1e-5 < dt < 0.05:
            a = (v - self.v_last) / dt
            self.accel_mm_s2 += 0.3 * (a - self.accel_mm_s2)     # light low-pass over sync jitter
        else:
            self.accel_mm_s2 = 0.0
        self.v_last, self.t_last = v, now_s

    def force_N(self) -> float:
        d = self.drive
        sim = d.sim
        if d.state not in _POWERED:
            return 0.0
        v = float(d.model.velocity_mm_s)
        fn = getattr(sim, "strut_force_N", None)
        if fn is None:
            return default_force_N(v, self.accel_mm_s2)
        with sim.lock:
            pos = [x.pos_inc / x.k for x in sim.drives]
        return float(fn(d.strut, pos, v, self.accel_mm_s2))

    def torque_permille(self, sub: int = 0) -> int:
        return force_to_permille(self.force_N(), self.drive.raw_or(0x6076, 0, 1000))

    def current_permille(self, sub: int = 0) -> int:
        d = self.drive
        t = self.torque_permille()
        rated_t, rated_i = d.raw_or(0x6076, 0, 1000), d.raw_or(0x6075, 0, 1000)
        kt = rated_t / max(1, rated_i)               # torque constant, mN m per mA
        i_mA = t * rated_t / 1000.0 / kt
        return max(-32768, min(32767, int(round(1000.0 * i_mA / max(1, rated_i)))))


def attach(drive: "SimDrive") -> None:
    """Give ``drive`` 0x6077 / 0x6078 when its object dictionary has them."""
    if 0x6077 not in drive.node.object_dictionary:
        return
    st = TorqueState(drive)
    drive.torque_state = st
    drive.hooks.on_sync(st.track)
    drive.hooks.on_read(0x6077, st.torque_permille)
    if 0x6078 in drive.node.object_dictionary:
        drive.hooks.on_read(0x6078, st.current_permille)


simhooks.EXTENSIONS.append(attach)
