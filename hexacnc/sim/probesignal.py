"""The simulated touch-probe input of the simulated drives: the true tool tip against the artefact.

:class:`ProbeSignal` is set as ``SimDrives.probe_signal`` (``hexacnc.daemon.simhost`` does it when the
config names a ``[simulation] truth``): each armed drive (0x60B8 bit 0, :mod:`drivers.touchprobe`) asks
it for the input signal every step - the distance (mm) from the true tool tip to the nearest artefact
sphere's surface (sphere radius + stylus ball radius), ``<= 0`` in contact.  The true pose follows the
drives' readings by Newton steps of the true machine's forward kinematics per SYNC from the last
pose (the readings move by micrometres per step), with the elastic elongation refreshed every 20 ms;
the value is cached per SYNC time, so six drives cost one step.
"""
from __future__ import annotations

import numpy as np

from ..pose import matrix_from_euler

SPHERE_RADIUS_MM = 12.5
STYLUS_RADIUS_MM = 1.0
FORCE_REFRESH_S = 0.02


class ProbeSignal:
    def __init__(self, truth, sim, spheres_mm, radius_mm: float = SPHERE_RADIUS_MM + STYLUS_RADIUS_MM):
        self.truth = truth
        self.sim = sim
        self.spheres = np.asarray(spheres_mm, dtype=float)
        self.radius = float(radius_mm)
        self.ipm = float(sim.increments_per_mm) if sim is not None else 1.0
        self._t = None
        self._v = 1e9
        self._X: np.ndarray | None = None
        self._elong = np.zeros(6)
        self._t_force = -1e9

    def readings_mm(self) -> np.ndarray:
        q = np.empty(6)
        for d in self.sim.drives:
            q[d.strut] = d.pos_inc / self.ipm
        return q

    def distance_mm(self, q: np.ndarray, now: float) -> float:
        tm = self.truth
        if self._X is None:
            self._X = tm.platform_pose_rad(q)
        if now - self._t_force > FORCE_REFRESH_S:
            self._elong = tm.forces_N(self._X) / tm.k
            self._t_force = now
        L = tm.lengths_unloaded(q, np.ones(6)) + self._elong
        X = self._X
        for _ in range(8):                 # one step per SYNC while following; more after a jump
            dX = np.linalg.solve(tm.hx.jacobian_rad(X), L - tm.hx.lengths_rad(X))
            X = X + dX
            if float(np.max(np.abs(dX))) < 1e-7:
                break
        self._X = X
        tip = X[:3] + matrix_from_euler(*X[3:6]) @ tm.tip
        return float(np.min(np.linalg.norm(self.spheres - tip[None], axis=1)) - self.radius)

    def __call__(self, strut: int, now: float) -> float:
        if now != self._t:
            self._t = now
            self._v = self.distance_mm(self.readings_mm(), now)
        return self._v


def attach_probe_signal(sim, truth_path: str) -> ProbeSignal:
    from .instruments import TouchProbe
    from .truth import load_truth
    sig = ProbeSignal(load_truth(truth_path), sim, TouchProbe().spheres)
    sim.probe_signal = sig
    return sig
