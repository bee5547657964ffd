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

An exact evaluation (Newton steps of the forward kinematics) costs ~1 ms of numpy on a small machine,
more than a 0.5 ms SYNC: the drives' process then fell behind its bus (a drive's heartbeat lost, the
setpoint ring run empty mid-probe).  Between exact evaluations the distance is taken to first order
in the strut lengths about the last one (its gradient through the inverse Jacobian): the next exact one
comes after ``REFRESH_MM`` of strut travel or ``FORCE_REFRESH_S``; the second-order error over 0.05 mm
(sphere curvature 1/13.5 mm, the kinematics' over ~1 m struts) is below 0.1 um.
"""
from __future__ import annotations

import numpy as np

from ..pose import matrix_from_euler, rate_matrix

SPHERE_RADIUS_MM = 12.5
STYLUS_RADIUS_MM = 1.0
FORCE_REFRESH_S = 0.02
REFRESH_MM = 0.05            #: strut travel (mm) after which the distance is evaluated exactly again
JACOBIAN_REFRESH_MM = 1.0    #: platform travel (mm, rad x 1000) after which the Newton Jacobian is rebuilt
_MM_PER_RAD = np.array([1.0, 1.0, 1.0, 1e3, 1e3, 1e3])


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
        self._Jinv: np.ndarray | None = None      #: inverse Jacobian of the Newton steps (stale by <= 1 mm)
        self._X_J: np.ndarray | None = None
        self._ref: tuple | None = None            #: (L_ref, s_ref, dS/dL, t_ref) of the last exact evaluation

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

    def lengths_mm(self, q: np.ndarray, now: float, extra_mm=None) -> np.ndarray:
        """True strut lengths (mm) at readings ``q``: unloaded + static elastic elongation (+ ``extra_mm``)."""
        tm = self.truth
        if self._X is None:
            self._X = tm.platform_pose_rad(q)
        if now - self._t_force > FORCE_REFRESH_S:
            self._elong = tm.forces_N(self._X) / tm.k
            self._t_force = now
        L = tm.lengths_unloaded(q, np.ones(6)) + self._elong
        return L if extra_mm is None else L + extra_mm

    def distance_mm(self, q: np.ndarray, now: float, extra_mm=None) -> float:
        """Distance (mm) of the true tool tip to the nearest sphere surface at readings ``q``;
        ``extra_mm``: dynamic strut deflection on top of the static elastic elongation.  First order
        about the last exact evaluation while the struts stay within ``REFRESH_MM`` of it."""
        L = self.lengths_mm(q, now, extra_mm)
        ref = self._ref
        if ref is not None and now - ref[3] < FORCE_REFRESH_S:
            dL = L - ref[0]
            if float(np.max(np.abs(dL))) < REFRESH_MM:
                return ref[1] + float(ref[2] @ dL)
        return self.exact_mm(L, now)

    def exact_mm(self, L: np.ndarray, now: float) -> float:
        """Distance (mm) at true strut lengths ``L`` by Newton steps from the last pose; sets the
        reference (value and gradient in ``L``) of the first-order evaluations."""
        tm = self.truth
        X = self._X
        for _ in range(20):                # quasi-Newton while following (one or two steps), Newton after a jump
            if self._Jinv is None or float(np.max(np.abs(X - self._X_J) * _MM_PER_RAD)) > JACOBIAN_REFRESH_MM:
                self._Jinv = np.linalg.inv(tm.hx.jacobian_rad(X))
                self._X_J = X.copy()
            dX = self._Jinv @ (L - tm.hx.lengths_rad(X))
            X = X + dX
            if float(np.max(np.abs(dX))) < 1e-8:
                break
        self._X = X
        arm = matrix_from_euler(*X[3:6]) @ tm.tip          # platform origin to tool tip, base frame
        tip = X[:3] + arm
        d = np.linalg.norm(self.spheres - tip[None], axis=1)
        k = int(np.argmin(d))
        n = (tip - self.spheres[k]) / d[k] if d[k] > 0 else np.zeros(3)
        # d distance / d pose: n along the translation; an angle rate turns the arm at omega = E @ rates,
        # d tip = omega x arm, so d distance / d angles = E^T (arm x n)
        dS_dX = np.concatenate([n, rate_matrix(*X[3:6]).T @ np.cross(arm, n)])
        s = float(d[k] - self.radius)
        self._ref = (L, s, dS_dX @ self._Jinv, now)
        return s

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
