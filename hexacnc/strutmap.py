"""Calibrated reading-to-length map of each strut (the ``[calibration]`` section).

A strut's physical length from its drive reading ``q`` (mm)::

    L_i(q) = strut_offset_i + s_i * q + sum_{k=1..d} c_ik * P_k(t),   t = (q - center_i) / half_i

``s_i`` is ``[calibration] strut_scale`` (dimensionless gain of the reading),
``c_ik`` the Legendre coefficients ``strut_nonlinearity_mm`` (mm; ``P_1`` is a
gain term too), ``center_i``/``half_i`` the reference reading and half range of
``t`` (``strut_nonlinearity_center_mm``, ``strut_nonlinearity_half_range_mm``).
This is the map ``hexacnc diagnose`` fits for ``strut_scale`` and
``strut_nonlinearity`` (:mod:`hexacnc.calib.model`).  Identity: ``s = 1``, no ``c``.

The bus layer converts a *drive-scale length* ``D = strut_offset + q`` to
increments.  So the cycle's command for a wanted physical length ``L`` is
``D = strut_offset + g^-1(L - strut_offset)`` with ``g(q) = L(q) - strut_offset``,
and feedback maps ``D`` back with ``L(D - strut_offset)``.

Inside, each strut's map is a power series in ``t``, ``G(t) = sum_k A_k t^k``
(the ``s q`` term folded in), so ``L = o + G(t)``.  The inverse is Newton in
``t``, warm-started from the previous solution; it stops once a step is below
``step_tol_t``, chosen from the map's curvature so that the error left after
that step is below 1e-13 mm (quadratic convergence: ``e' <= K e^2``).
A map whose slope leaves [0.5, 2] over the stroke (plus 10 %) is rejected at load.
"""
from __future__ import annotations

import math

import numpy as np

#: allowed slope dL/dq of a calibrated map over the stroke
SLOPE_MIN = 0.5
SLOPE_MAX = 2.0
#: the map is checked over the configured reading stroke extended by this fraction on each side
STROKE_MARGIN = 0.10
#: error left after the last Newton step, mm (bound, from the map's curvature)
RESIDUAL_MM = 1e-13
#: Newton iterations before the inverse counts as failed
MAX_ITER = 30


class StrutMap:
    """Per-strut reading-to-length maps; ``identity`` when nothing is calibrated.

    Batch methods take (N,6) or (6,) arrays (mm); :meth:`command_inplace` and
    :meth:`strut_from_drive_inplace` are the general per-cycle routines on lists.
    """

    def __init__(self, cal, strut_offset_mm, reading_min_mm, reading_max_mm):
        self.scale = np.array(cal.strut_scale, dtype=float)
        self.coef = np.array(cal.strut_nonlinearity_mm, dtype=float).reshape(6, -1)
        self.center = np.array(cal.strut_nonlinearity_center_mm, dtype=float)
        self.half = np.array(cal.strut_nonlinearity_half_range_mm, dtype=float)
        self.offset = np.array(strut_offset_mm, dtype=float)
        self.identity = bool(np.all(self.scale == 1.0) and not np.any(self.coef != 0.0))
        self.degree = int(self.coef.shape[1])
        #: power-series coefficients A (6, n) of G(t), lowest order first, s*q folded in
        A = np.zeros((6, max(self.degree, 1) + 1))
        for i in range(6):
            p = np.polynomial.legendre.leg2poly(np.r_[0.0, self.coef[i]]) if self.degree else np.zeros(1)
            A[i, :len(p)] += p
            A[i, 0] += self.scale[i] * self.center[i]
            A[i, 1] += self.scale[i] * self.half[i]
        while A.shape[1] > 2 and not np.any(A[:, -1] != 0.0):
            A = A[:, :-1]
        self.A = A
        #: derivative coefficients dG/dt
        self.B = (A[:, 1:] * np.arange(1, A.shape[1])[None]).copy()
        self.linear = A.shape[1] <= 2
        lo = np.asarray(reading_min_mm, dtype=float)
        hi = np.asarray(reading_max_mm, dtype=float)
        m = STROKE_MARGIN * (hi - lo)
        self.reading_lo = lo - m
        self.reading_hi = hi + m
        # curvature bound K = max|G''| / (2 min G') in t, over the checked range
        t = self._grid_t()
        Gp = np.stack([np.polynomial.polynomial.polyval(t[i], self.B[i]) for i in range(6)])
        if self.linear:
            K = np.zeros(6)
        else:
            C = self.B[:, 1:] * np.arange(1, self.B.shape[1])[None]
            Gpp = np.stack([np.polynomial.polynomial.polyval(t[i], C[i]) for i in range(6)])
            K = np.max(np.abs(Gpp), axis=1) / (2.0 * np.maximum(np.min(Gp, axis=1), 1e-12))
        #: Newton stops after a step below this (in t), per strut
        # error left after a step dt (in t): K dt^2 in t, at most SLOPE_MAX * half * K dt^2 in mm
        self.step_tol_t = np.array([min(1e-3, math.sqrt(RESIDUAL_MM / (SLOPE_MAX * K[i] * self.half[i])))
                                    if K[i] > 0 else 1e-3 for i in range(6)])
        self._Al = [[float(v) for v in r] for r in self.A]
        self._Bl = [[float(v) for v in r] for r in self.B]
        self._o = [float(v) for v in self.offset]
        self._c = [float(v) for v in self.center]
        self._h = [float(v) for v in self.half]
        self._ih = [1.0 / float(v) for v in self.half]
        self._tol = [float(v) for v in self.step_tol_t]

    # ------------------------------------------------------------------ checks
    def _grid_t(self, n: int = 801) -> np.ndarray:
        q = np.linspace(self.reading_lo, self.reading_hi, n).T          # (6, n)
        return (q - self.center[:, None]) / self.half[:, None]

    def slope_violation(self) -> tuple[int, float, float] | None:
        """(strut index, reading mm, slope) of the worst slope outside [SLOPE_MIN, SLOPE_MAX], or None."""
        t = self._grid_t()
        worst = None
        for i in range(6):
            slope = np.polynomial.polynomial.polyval(t[i], self.B[i]) / self.half[i]
            bad = (slope < SLOPE_MIN) | (slope > SLOPE_MAX) | ~np.isfinite(slope)
            if bad.any():
                k = int(np.argmax(np.where(bad, np.abs(np.log(np.clip(np.abs(slope), 1e-300, None))), -1.0)))
                q = float(self.center[i] + t[i, k] * self.half[i])
                if worst is None:
                    worst = (i, q, float(slope[k]))
        return worst

    # ------------------------------------------------------------------ batch (numpy)
    def strut_from_drive(self, drive_mm) -> np.ndarray:
        """Physical strut lengths from drive-scale lengths ``D = strut_offset + q`` (mm), (...,6)."""
        D = np.asarray(drive_mm, dtype=float)
        if self.identity:
            return D.copy()
        t = (D - self.offset - self.center) / self.half
        out = np.empty_like(t)
        for i in range(6):
            out[..., i] = self.offset[i] + np.polynomial.polynomial.polyval(t[..., i], self.A[i])
        return out

    def drive_from_strut(self, length_mm) -> np.ndarray:
        """Drive-scale lengths for physical strut lengths (mm), (...,6): the exact inverse (Newton)."""
        L = np.asarray(length_mm, dtype=float)
        if self.identity:
            return L.copy()
        e = L - self.offset
        t = np.empty_like(e)
        for i in range(6):
            ei = e[..., i]
            ti = (ei - self.A[i, 0]) / self.A[i, 1]
            for _ in range(MAX_ITER):
                G = np.polynomial.polynomial.polyval(ti, self.A[i])
                Gp = np.polynomial.polynomial.polyval(ti, self.B[i])
                dt = (ei - G) / Gp
                ti = ti + dt
                if np.all(np.abs(dt) < self.step_tol_t[i]):
                    break
            else:
                raise ArithmeticError(f"strut {i + 1}: calibrated map did not invert")
            t[..., i] = ti
        return self.offset + self.center + t * self.half

    # ------------------------------------------------------------------ per cycle (lists)
    def new_state(self) -> list[float]:
        """Warm-start state for the per-cycle inverse: per strut ``a, g`` with the next guess
        ``t = a + v * g`` for physical length ``v`` (g: 1/slope dt/dv at the last solution), 12 floats."""
        st = [0.0] * 12
        for i in range(6):
            A = self._Al[i]
            st[2 * i + 1] = 1.0 / A[1]
            st[2 * i] = -(self._o[i] + A[0]) / A[1]
        return st

    def solve_t(self, i: int, v: float, t: float) -> tuple[float, float]:
        """Newton in t for strut ``i``'s physical length ``v`` from guess ``t``: (t, dG/dt); t is NaN
        when it does not converge within :data:`MAX_ITER` steps."""
        A = self._Al[i]; B = self._Bl[i]
        e = v - self._o[i]
        tol = self._tol[i]
        Gp = 1.0
        restarted = False
        for _ in range(MAX_ITER):
            G = A[-1]
            for j in range(len(A) - 2, -1, -1):
                G = G * t + A[j]
            Gp = B[-1]
            for j in range(len(B) - 2, -1, -1):
                Gp = Gp * t + B[j]
            if not Gp > 0.0:            # outside the checked range (or NaN): restart once from the linear guess
                if restarted:
                    break
                restarted = True
                t = (e - A[0]) / A[1]
                continue
            dt = (e - G) / Gp
            t += dt
            if -tol < dt < tol:
                return t, Gp
            if dt != dt:
                break
        return math.nan, Gp

    def command_inplace(self, vals, state) -> int:
        """Physical lengths in ``vals`` -> drive-scale lengths, in place; -1, or the failing strut."""
        for i in range(6):
            A = self._Al[i]
            v = vals[i]
            if len(A) == 2:
                t = (v - self._o[i] - A[0]) / A[1]
            else:
                k = 2 * i
                t, Gp = self.solve_t(i, v, state[k] + v * state[k + 1])
                if t != t:
                    st = self.new_state()
                    state[k] = st[k]; state[k + 1] = st[k + 1]
                    return i
                g = 1.0 / Gp
                state[k] = t - v * g; state[k + 1] = g
            vals[i] = self._o[i] + self._c[i] + t * self._h[i]
        return -1

    def strut_from_drive_inplace(self, drive, out) -> None:
        """Physical lengths ``out`` from drive-scale lengths ``drive`` (lists of 6)."""
        for i in range(6):
            A = self._Al[i]
            t = (drive[i] - self._o[i] - self._c[i]) * self._ih[i]
            G = A[-1]
            for j in range(len(A) - 2, -1, -1):
                G = G * t + A[j]
            out[i] = self._o[i] + G


def strut_map_from_config(cfg) -> StrutMap:
    """Factory: the machine's map from ``cfg.calibration`` and its stroke in readings."""
    off = np.asarray(cfg.strut_offset_mm, dtype=float)
    return StrutMap(cfg.calibration, off, np.asarray(cfg.min_length_mm) - off, np.asarray(cfg.max_length_mm) - off)
