"""The simulated touch-probe input of the simulated drives: the true tool tip against the artefact.

:class:`ProbeSignal` is set as ``SimDrives.probe_signal`` (``hexacnc.daemon.simhost`` does it when the
config names a ``[simulation] truth``): each armed drive (0x60B8 bit 0, :mod:`drivers.touchprobe`) asks
it for the input signal every step - the distance (mm) from the true tool tip to the nearest artefact
sphere's surface (sphere radius + stylus ball radius), ``<= 0`` in contact.  The true pose follows the
drives' readings by Newton steps of the true machine's forward kinematics per SYNC from the last
pose (the readings move by micrometres per step), with the elastic elongation refreshed every 20 ms;
the value is cached per drive step (counted by a per-step hook, :meth:`ProbeSignal.count_step`), so
six drives cost one evaluation per SYNC, and all six see the readings of one instant (a drive behind
by k steps carried k steps forward by its velocity).
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
        self.period_s = float(getattr(getattr(getattr(sim, "cfg", None), "cycle", None), "period_s", 0.0005))
        self.steps = [0] * 6              #: SYNC steps of each drive (hook count_step)
        self._by_step: dict[int, float] = {}
        self._X: np.ndarray | None = None
        self._elong = np.zeros(6)
        self._t_force = -1e9

    def count_step(self, drive, now: float) -> None:
        """Per-step hook of every simulated drive (``drive.hooks.sync``): its steps counted."""
        self.steps[drive.strut] += 1

    def readings_mm(self, caller: int | None = None) -> np.ndarray:
        """Every drive's reading at the step the ``caller`` drive has just made: the drives step
        one after the other, bus by bus, so a drive behind by ``k`` steps (its step count) is
        carried ``k`` steps forward by its velocity - all six at one instant of the drives' common
        clock, as one probe wire reaches them all."""
        q = np.empty(6)
        n = self.steps[caller] + 1 if caller is not None else None
        for d in self.sim.drives:
            x = d.pos_inc / self.ipm
            if n is not None and d.strut != caller:
                k = n - self.steps[d.strut]
                if 0 < k < 64:
                    x += float(getattr(getattr(d, "model", None), "velocity_mm_s", 0.0)) * self.period_s * k
            q[d.strut] = x
        return q

    def deflection_mm(self) -> np.ndarray | None:
        """The drives' dynamic elastic deflection (coupled strut model of the true machine), or None."""
        out = np.zeros(6)
        for d in self.sim.drives:
            v = getattr(getattr(d, "model", None), "deflection_mm", None)
            if v is None:
                return None
            out[d.strut] = v
        return out

    def distance_mm(self, q: np.ndarray, now: float, extra_mm=None) -> float:
        """Distance (mm) of the true tool tip to the nearest sphere surface at readings ``q``;
        ``extra_mm``: dynamic strut deflection on top of the static elastic elongation."""
        tm = self.truth
        if self._X is None:
            self._X = tm.platform_pose_rad(q)
        if now - self._t_force > FORCE_REFRESH_S:
            self._elong = tm.forces_N(self._X) / tm.k
            self._t_force = now
        L = tm.lengths_unloaded(q, np.ones(6)) + self._elong
        if extra_mm is not None:
            L = L + extra_mm
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
        n = self.steps[strut] + 1
        v = self._by_step.get(n)
        if v is None:
            v = self._by_step[n] = self.distance_mm(self.readings_mm(strut), now, self.deflection_mm())
            if len(self._by_step) > 64:
                self._by_step.pop(next(iter(self._by_step)))
        return v


def artefact_spheres_mm(seed: int = 0) -> np.ndarray:
    """Where the artefact's spheres really are: nominal places plus their calibration error (seeded;
    ``hexacnc run`` uses seed 0 for the daemon's instruments and the drives' probe input alike)."""
    from .instruments import TouchProbe
    art = TouchProbe(seed)
    return art.spheres + art.sphere_error


def attach_probe_signal(sim, truth) -> ProbeSignal:
    """``truth``: a :class:`~hexacnc.sim.truth.TrueMachine` or the path of its file."""
    from .truth import load_truth
    tm = load_truth(truth) if isinstance(truth, (str, bytes)) or hasattr(truth, "__fspath__") else truth
    sig = ProbeSignal(tm, sim, artefact_spheres_mm(0))
    for d in sim.drives:
        d.hooks.sync.append(sig.count_step)
    sim.probe_signal = sig
    return sig
