"""Strut forces for the simulated drives' torque and current actual values (0x6077 / 0x6078).

:class:`StrutLoad` is the host function ``sim.strut_force_N(strut, positions_mm, velocity_mm_s,
acceleration_mm_s2) -> N`` that :mod:`drivers.simtorque` calls on an SDO read (``drivers`` knows no
kinematics).  Force of strut ``i`` (N, tension positive, the convention of :mod:`hexacnc.sag` and
:mod:`hexacnc.calib.healthsim`):

* static load: the gravity wrench of the carrier (its ``mass_kg`` and ``center_of_gravity_mm``; a true
  machine's payload is merged in by :meth:`hexacnc.sim.truth.TrueMachine.plant_config`) through the
  pose found by forward kinematics of the six drive readings (:func:`hexacnc.sag.strut_forces_N`);
* inertia: ``mass_kg / 6 * a_i`` with ``a_i`` the strut model's acceleration (a lumped, diagonal
  approximation of the carrier's mass reflected onto each strut; the Jacobian coupling is left out);
* friction: Coulomb ``coulomb_N * sign(v_i)`` while moving plus viscous ``viscous_N_s_per_mm * v_i``
  (none at rest: a resting drive reads the static load only).

The pose is re-solved only when a reading moved by more than ``refresh_mm`` (forward kinematics costs
~0.1 ms; reads come at a few tens of Hz).
"""
from __future__ import annotations

import threading

import numpy as np

from ..kinematics import Hexapod
from ..sag import strut_forces_N

__all__ = ["StrutLoad", "attach_strut_load"]


class StrutLoad:
    def __init__(self, cfg, coulomb_N: float = 20.0, viscous_N_s_per_mm: float = 0.5, refresh_mm: float = 1e-3):
        self.hx = Hexapod(cfg)
        self.moving_kg = float(cfg.mass_kg) / 6.0
        self.coulomb_N = float(coulomb_N)
        self.viscous = float(viscous_N_s_per_mm)
        self.refresh_mm = float(refresh_mm)
        self._q: np.ndarray | None = None
        self._pose = np.asarray(cfg.home_pose, dtype=float)
        self._f = np.zeros(6)
        self._lock = threading.Lock()

    def static_N(self, positions_mm) -> np.ndarray:
        """(6,) static strut forces (N) at the drive readings ``positions_mm`` (cached)."""
        q = np.asarray(positions_mm, dtype=float)
        with self._lock:
            if self._q is None or float(np.max(np.abs(q - self._q))) > self.refresh_mm:
                res = self.hx.forward_readings(q, guess=self._pose)
                if res.ok:
                    self._pose = np.asarray(res.pose, dtype=float)
                    self._f = strut_forces_N(self.hx, self._pose)
                    self._q = q
            return self._f

    def __call__(self, strut: int, positions_mm, velocity_mm_s: float, acceleration_mm_s2: float) -> float:
        v = float(velocity_mm_s)
        fr = self.coulomb_N * (1.0 if v > 1e-3 else -1.0 if v < -1e-3 else 0.0) + self.viscous * v
        return float(self.static_N(positions_mm)[strut]) + self.moving_kg * acceleration_mm_s2 * 1e-3 + fr


def attach_strut_load(sim, cfg) -> StrutLoad:
    """Give the simulated drives ``sim`` (:class:`drivers.simdrive.SimDrives`) the strut load of ``cfg``
    (the plant's configuration: a true machine's, with its payload)."""
    load = StrutLoad(cfg)
    sim.strut_force_N = load
    return load
