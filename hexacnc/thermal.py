"""Thermal growth of the struts: 1-D heat model, exact discretisation, Kalman observer.

Each strut is a rod of length ``L`` cut into ``n`` equal finite volumes
(``[thermal] segments``).  Segment ``j`` has the heat capacity
``C = rho c A dx`` and exchanges heat

* with its neighbours by conduction, conductance ``k A / dx``;
* with the air over its perimeter, conductance ``h P dx`` (input: ambient
  temperature);
* at both ends with the frame through the joint, conductance
  ``1 / (1 / G_end + dx / (2 k A))`` (input: frame temperature);
* and it receives the friction heat of the drive, ``heat_per_speed * |v|`` W
  for a strut speed ``|v|`` in mm/s, spread uniformly along the strut.

That is ``dT/dt = A T + B u`` with ``T`` (n,) in degC and
``u = [|v| (mm/s), T_ambient (degC), T_frame (degC)]``; the strut growth is
``dl = C (T - T_ref)`` in mm with ``C = alpha dx`` per segment
(``T_ref = [thermal] reference_temperature_C``, the calibration temperature).

:func:`discretise` gives the exact zero-order-hold model for a step ``dt``
(matrix exponential of the augmented system).  :class:`ThermalObserver`
runs one steady-state Kalman filter per strut on the probes
(``[thermal] probes``, segment indices; ``probe_noise_K`` standard deviation;
``process_noise_K`` standard deviation of each segment's random walk per
square-root second) and returns the strut length offsets that feed
:meth:`hexacnc.transform.CycleTransform.set_thermal_offsets_mm` (positive =
strut longer; the transform subtracts them from its commands).

:func:`spindle_growth_mm` is the tool growth along the tool axis for a spindle
temperature (``[spindle] growth_mm_per_K`` over ``reference_temperature_C``).

Units: mm, s, W, K/degC at the interface; SI (m) inside the model build.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from .errors import ConfigError, DataError

#: input order of B: strut speed magnitude, ambient temperature, frame temperature
U_SPEED, U_AMBIENT, U_FRAME = 0, 1, 2

#: observer status after a step
STATUS_OK = "ok"                    #: predicted and corrected with the probes
STATUS_PREDICTED = "predicted"      #: a probe read NaN: model prediction only
STATUS_BAD_INPUT = "bad_input"      #: speed / ambient / frame not finite: estimate held


def _thermal_cfg(cfg):
    """Accept a MachineConfig or a ThermalConfig."""
    return getattr(cfg, "thermal", cfg)


@dataclass(frozen=True)
class StrutHeatModel:
    """Continuous state-space heat model of one strut (see module docstring).

    ``A`` (n,n) 1/s, ``B`` (n,3) [K/s per mm/s, 1/s, 1/s], ``C`` (n,) mm/K,
    plus the physical constants used to build it (SI units).
    """
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    length_mm: float
    segments: int
    reference_temperature_C: float
    capacity_J_K: float          #: per segment
    g_axial_W_K: float           #: between neighbouring segments
    g_air_W_K: float             #: per segment to ambient
    g_end_W_K: float             #: end segment to frame (incl. half segment)
    heat_per_speed_W_s_mm: float
    source_profile: np.ndarray   #: (n,) fraction of the heat per segment, sums to 1

    @property
    def n(self) -> int:
        return self.segments

    def steady_state(self, speed_mm_s: float, T_ambient_C: float, T_frame_C: float) -> np.ndarray:
        """Equilibrium temperatures (n,) degC for constant inputs: ``T = -A^-1 B u``."""
        u = np.array([abs(speed_mm_s), T_ambient_C, T_frame_C], dtype=float)
        return -np.linalg.solve(self.A, self.B @ u)

    def growth_mm(self, T_C: np.ndarray) -> np.ndarray:
        """Strut growth in mm for temperature field(s) ``T_C`` (..., n)."""
        return (np.asarray(T_C, dtype=float) - self.reference_temperature_C) @ self.C

    def segment_centres_mm(self) -> np.ndarray:
        dx = self.length_mm / self.segments
        return (np.arange(self.segments) + 0.5) * dx


def strut_heat_model(cfg, length_mm: float, segments: int | None = None,
                     source_profile: Sequence[float] | None = None) -> StrutHeatModel:
    """Build the heat model of one strut of ``length_mm`` from ``[thermal]``.

    ``segments`` overrides ``[thermal] segments`` (the simulator's "true"
    machine uses a finer grid); ``source_profile`` (n,) distributes the friction
    heat along the strut (default: uniform).
    """
    tc = _thermal_cfg(cfg)
    n = int(tc.segments if segments is None else segments)
    if n < 2:
        raise ConfigError(f"[thermal] segments must be at least 2, got {n}")
    if not (math.isfinite(length_mm) and length_mm > 0):
        raise DataError(f"strut length for the heat model must be positive, got {length_mm!r} mm")
    L = length_mm * 1e-3
    dx = L / n
    area = tc.area_mm2 * 1e-6
    perim = tc.perimeter_mm * 1e-3
    kA = tc.conductivity_W_mK * area
    cap = tc.density_kg_m3 * tc.heat_capacity_J_kgK * area * dx
    g_ax = kA / dx
    g_air = tc.convection_W_m2K * perim * dx
    if tc.end_conductance_W_K > 0:
        g_end = 1.0 / (1.0 / tc.end_conductance_W_K + dx / (2.0 * kA))
    else:
        g_end = 0.0
    if source_profile is None:
        prof = np.full(n, 1.0 / n)
    else:
        prof = np.asarray(source_profile, dtype=float)
        if prof.shape != (n,) or np.any(prof < 0) or not np.isfinite(prof).all() or prof.sum() <= 0:
            raise DataError(f"source_profile must be {n} non-negative numbers with a positive sum")
        prof = prof / prof.sum()
    A = np.zeros((n, n))
    B = np.zeros((n, 3))
    for j in range(n):
        if j > 0:
            A[j, j - 1] += g_ax
            A[j, j] -= g_ax
        if j < n - 1:
            A[j, j + 1] += g_ax
            A[j, j] -= g_ax
        A[j, j] -= g_air
        B[j, U_AMBIENT] += g_air
    for j in (0, n - 1):
        A[j, j] -= g_end
        B[j, U_FRAME] += g_end
    B[:, U_SPEED] = tc.heat_per_speed_W_s_mm * prof
    A /= cap
    B /= cap
    C = np.full(n, tc.expansion_per_K * length_mm / n)
    for a in (A, B, C, prof):
        a.setflags(write=False)
    return StrutHeatModel(A=A, B=B, C=C, length_mm=float(length_mm), segments=n,
                          reference_temperature_C=float(tc.reference_temperature_C),
                          capacity_J_K=cap, g_axial_W_K=g_ax, g_air_W_K=g_air, g_end_W_K=g_end,
                          heat_per_speed_W_s_mm=float(tc.heat_per_speed_W_s_mm), source_profile=prof)


def discretise(A: np.ndarray, B: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation: ``x+ = Ad x + Bd u`` over ``dt_s``.

    ``Ad = e^{A dt}``, ``Bd = int_0^dt e^{A s} ds B``, both from one matrix
    exponential of ``[[A, B], [0, 0]] dt``.
    """
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise DataError(f"time step must be positive, got {dt_s!r} s")
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    E = expm(M * dt_s)
    return E[:n, :n].copy(), E[:n, n:].copy()


def probe_matrix(n: int, probes: Sequence[int]) -> np.ndarray:
    """Output matrix H (p, n) picking the probed segments."""
    probes = [int(p) for p in probes]
    if not probes:
        raise ConfigError("[thermal] probes: at least one probe is needed")
    if len(set(probes)) != len(probes):
        raise ConfigError(f"[thermal] probes: duplicate segment index in {probes}")
    for p in probes:
        if not 0 <= p < n:
            raise ConfigError(f"[thermal] probes: segment {p} outside 0..{n - 1}")
    H = np.zeros((len(probes), n))
    for i, p in enumerate(probes):
        H[i, p] = 1.0
    return H


def observability(A: np.ndarray, H: np.ndarray) -> dict:
    """PBH observability of ``(A, H)``: per mode, how strongly the probes see it.

    Returns ``{"observable": bool, "min_visibility": float, "time_constants_s": [...],
    "visibility": [...]}`` where the visibility of a mode is ``|H v| / |v|_inf`` of
    its eigenvector (A of a strut is similar to a symmetric matrix, so its modes are
    real).  A mode with visibility below 1e-9 is unobservable.
    """
    w, V = np.linalg.eig(A)
    w = w.real
    V = V.real
    order = np.argsort(-w)  # slowest first
    vis = []
    for k in order:
        v = V[:, k] / np.max(np.abs(V[:, k]))
        vis.append(float(np.linalg.norm(H @ v)))
    vis_a = np.array(vis)
    return {"observable": bool(np.all(vis_a > 1e-9)), "min_visibility": float(vis_a.min()),
            "time_constants_s": [float(-1.0 / w[k]) for k in order], "visibility": vis}


def _strut_lengths_home(cfg) -> np.ndarray:
    from .kinematics import Hexapod
    return Hexapod(cfg).lengths(cfg.home_pose)


class ThermalObserver:
    """Steady-state Kalman filter per strut on a few temperature probes.

    ``ThermalObserver(cfg, dt_s)`` with ``cfg`` a MachineConfig (strut lengths at
    the home pose set each strut's model) - or a ThermalConfig plus
    ``lengths_mm`` (6,).  Call :meth:`update` every ``dt_s`` (e.g. 0.1 s); it
    returns the strut growth estimate ``offsets_mm`` (6,) in mm, also kept as the
    attribute of that name, ready for ``CycleTransform.set_thermal_offsets_mm``.

    ``T_est`` (6, n) is the estimated temperature field in degC; the estimate
    starts at ``T0_C`` (default the reference temperature) or at :meth:`reset`.
    ``heat_scale`` scales the model's heat input (1.0: as configured).
    ``status`` after each step: ``"ok"``, ``"predicted"`` (a probe read NaN) or
    ``"bad_input"`` (non-finite speed/ambient/frame: estimate held).
    """

    def __init__(self, cfg, dt_s: float, lengths_mm: Sequence[float] | None = None,
                 T0_C: float | None = None, heat_scale: float = 1.0):
        tc = _thermal_cfg(cfg)
        self.cfg = tc
        self.dt_s = float(dt_s)
        if lengths_mm is None:
            if tc is cfg:
                raise ConfigError("ThermalObserver needs a MachineConfig or lengths_mm for the 6 struts")
            lengths_mm = _strut_lengths_home(cfg)
        lengths = np.asarray(lengths_mm, dtype=float)
        if lengths.shape != (6,) or not np.all(np.isfinite(lengths)) or np.any(lengths <= 0):
            raise DataError(f"lengths_mm must be 6 positive numbers, got {lengths!r}")
        self.models = [strut_heat_model(tc, float(L)) for L in lengths]
        n = self.n = tc.segments
        self.probes = tuple(int(p) for p in tc.probes)
        H = probe_matrix(n, self.probes)
        p = H.shape[0]
        Ad = np.empty((6, n, n))
        Bd = np.empty((6, n, 3))
        K = np.empty((6, n, p))
        Cm = np.empty((6, n))
        Q = (tc.process_noise_K ** 2) * self.dt_s * np.eye(n)
        R = (tc.probe_noise_K ** 2) * np.eye(p)
        self.observability = []
        for i, m in enumerate(self.models):
            a, b = discretise(m.A, m.B, self.dt_s)
            b = b.copy()
            b[:, U_SPEED] *= heat_scale
            obs = observability(m.A, H)
            self.observability.append(obs)
            if not obs["observable"]:
                raise ConfigError(f"[thermal] probes {list(self.probes)}: strut {i + 1} temperature field is "
                                  f"not observable (a mode with time constant "
                                  f"{obs['time_constants_s'][int(np.argmin(obs['visibility']))]:.3g} s is invisible)")
            # steady-state a-priori covariance P, gain K = P H' (H P H' + R)^-1
            P = solve_discrete_are(a.T, H.T, Q, R)
            K[i] = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
            Ad[i], Bd[i], Cm[i] = a, b, m.C
        self.H = H
        self.Ad, self.Bd, self.K, self.C = Ad, Bd, K, Cm
        self.T_ref = tc.reference_temperature_C
        self._pidx = np.array(self.probes)
        self.T_est = np.full((6, n), self.T_ref if T0_C is None else float(T0_C))
        self.offsets_mm = np.zeros(6)
        self.status = STATUS_OK
        self._u = np.empty((6, 3))
        self._compute_offsets()

    # ------------------------------------------------------------------
    def reset(self, T_C) -> None:
        """Set the estimate: one temperature for all, (6,) per strut or (6, n) per segment."""
        T = np.asarray(T_C, dtype=float)
        if T.ndim == 1 and T.shape == (6,):
            T = T[:, None]
        self.T_est[:] = np.broadcast_to(T, self.T_est.shape)
        self._compute_offsets()

    def _compute_offsets(self) -> None:
        self.offsets_mm = np.einsum("ij,ij->i", self.T_est - self.T_ref, self.C)

    def predict_only(self, speed_mm_s, T_ambient_C: float, T_frame_C: float) -> np.ndarray:
        """Advance the model without a measurement (probe dropout); returns offsets_mm.

        Non-finite inputs leave the estimate unchanged (``status`` says so).
        """
        v = np.asarray(speed_mm_s, dtype=float)
        if v.shape != (6,):
            raise DataError(f"speed_mm_s must have 6 values, got shape {v.shape}")
        if not (np.all(np.isfinite(v)) and math.isfinite(T_ambient_C) and math.isfinite(T_frame_C)):
            self.status = STATUS_BAD_INPUT
            return self.offsets_mm
        self.status = STATUS_PREDICTED
        u = self._u
        u[:, U_SPEED] = np.abs(v)
        u[:, U_AMBIENT] = T_ambient_C
        u[:, U_FRAME] = T_frame_C
        self.T_est = np.einsum("ijk,ik->ij", self.Ad, self.T_est) + np.einsum("ijk,ik->ij", self.Bd, u)
        self._compute_offsets()
        return self.offsets_mm

    def update(self, speed_mm_s, T_ambient_C: float, T_frame_C: float, probes_C) -> np.ndarray:
        """One filter step over ``dt_s``.

        ``speed_mm_s`` (6,) mean strut speed over the last step (sign ignored),
        ``T_ambient_C``, ``T_frame_C`` scalars, ``probes_C`` (6, n_probes) probe
        readings at the end of the step.  Returns ``offsets_mm`` (6,).
        """
        y = np.asarray(probes_C, dtype=float)
        if y.shape != (6, len(self.probes)):
            raise DataError(f"probes_C must have shape (6, {len(self.probes)}), got {y.shape}")
        self.predict_only(speed_mm_s, T_ambient_C, T_frame_C)
        if self.status == STATUS_BAD_INPUT:
            return self.offsets_mm
        innov = y - self.T_est[:, self._pidx]
        if not np.all(np.isfinite(innov)):
            return self.offsets_mm  # keep the prediction when a probe reads NaN (status: predicted)
        self.T_est += np.einsum("ijk,ik->ij", self.K, innov)
        self.status = STATUS_OK
        self._compute_offsets()
        return self.offsets_mm


def spindle_growth_mm(T_spindle_C: float, cfg) -> float:
    """Tool growth (mm) along the tool axis at spindle temperature ``T_spindle_C``.

    ``cfg``: MachineConfig or SpindleConfig; linear in the temperature over
    ``[spindle] reference_temperature_C`` (negative below it).
    """
    sc = getattr(cfg, "spindle", cfg)
    T = float(T_spindle_C)
    if not math.isfinite(T):
        raise DataError(f"spindle temperature is not finite: {T_spindle_C!r}")
    return sc.growth_mm_per_K * (T - sc.reference_temperature_C)


def thermal_observer(cfg, dt_s: float = 0.1, **kw) -> ThermalObserver:
    """Factory: the observer the daemon runs at ``1 / dt_s`` Hz."""
    return ThermalObserver(cfg, dt_s, **kw)
