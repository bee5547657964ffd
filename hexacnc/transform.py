"""The per-cycle transform: the hot path between a setpoint and six strut commands.

One call of :meth:`CycleTransform.command` per cycle does, on plain floats and
preallocated lists (no numpy, no per-call containers):

1. rotation from ``a, b, c`` (radians) and the spindle-growth shift of the pose;
2. closed-form inverse kinematics, strut unit vectors, twist-Jacobian rows;
3. strut-length and joint-angle checks (cone half-angle against each joint's
   neutral axis), Jacobian pivot check (near-singular);
4. LU factorisation of the twist Jacobian, strut forces of the carrier weight
   ``J^T f = w`` and the sag elongation ``e = f / k``;
5. physical length = geometric length - sag elongation - thermal growth;
   with a ``[calibration]`` (:mod:`hexacnc.strutmap`) the drive command is the
   drive-scale length whose calibrated reading gives that physical length
   (identity: command = physical length); the command is checked against the
   stroke too (the geometric length always is);
6. last-line guard on the command's velocity and acceleration.

:meth:`CycleTransform.feedback` maps measured lengths to the actual pose:
the measured (drive-scale) length mapped through the calibration, plus the
modelled elongation and growth, gives the geometric length; forward kinematics starts from a quadratic prediction of the
last three solutions and takes Newton steps with the cycle's Jacobian factors,
mapping the angular-velocity part to Euler-angle rates (``E^-1``).

Status values are returned, never raised.  :meth:`describe` turns a status
into text (slow path, for logs and status).
"""
from __future__ import annotations

import math

import numpy as np

from .kinematics import Hexapod
from .pose import rotation_elements

from .cyclecodes import (FK_NOT_CONVERGED, LIMIT_ACCELERATION, LIMIT_CALIBRATION, LIMIT_INPUT,  # noqa: F401
                         LIMIT_JOINT, LIMIT_LENGTH, LIMIT_SINGULAR, LIMIT_VELOCITY, OK)

STATUS_TEXT = {
    OK: "ok",
    LIMIT_LENGTH: "strut length limit",
    LIMIT_JOINT: "joint angle limit",
    LIMIT_VELOCITY: "strut velocity limit",
    LIMIT_ACCELERATION: "strut acceleration limit",
    LIMIT_SINGULAR: "near-singular pose",
    LIMIT_INPUT: "setpoint not finite",
    FK_NOT_CONVERGED: "forward kinematics did not converge",
    LIMIT_CALIBRATION: "calibrated strut map did not invert",
}


class CycleTransform:
    """Per-cycle inverse/forward transform with sag and thermal compensation.

    ``command(x, y, z, a, b, c)`` takes the platform pose in mm and radians.
    Results: ``cmd_mm`` (6 strut commands: drive-scale lengths, strut_offset +
    reading), ``phys_mm`` (physical strut lengths they give: the same list as
    ``cmd_mm`` without calibration), ``length_mm`` (geometric lengths),
    ``sag_mm`` (modelled elongation), ``thermal_mm`` (growth), ``pose_act``
    (mm, rad) after ``feedback``.  Limits: the geometric length, and with a
    calibration also the drive command, against [min_length_mm, max_length_mm].
    """

    def __init__(self, cfg, hexapod: Hexapod | None = None, period_s: float | None = None,
                 velocity_margin: float = 1.02, acceleration_margin: float = 1.05,
                 sag: bool = True, fast: bool = True):
        hx = hexapod if hexapod is not None else Hexapod(cfg)
        self.hx = hx
        self.cfg = cfg
        dt = float(cfg.cycle.period_s if period_s is None else period_s)
        self.dt = dt
        self._b = [tuple(float(v) for v in r) for r in hx.base]
        self._p = [tuple(float(v) for v in r) for r in hx.plat]
        self._ab = [tuple(float(v) for v in r) for r in hx.base_axes]
        self._ap = [tuple(float(v) for v in r) for r in hx.plat_axes]
        self._cos_max = [math.cos(float(v)) for v in hx.max_angle_rad]
        self._lmin = [float(v) for v in hx.min_length]
        self._lmax = [float(v) for v in hx.max_length]
        self._dl_max = [float(v) * dt * velocity_margin for v in cfg.max_velocity_mm_s]
        self._ddl_max = [float(v) * dt * dt * acceleration_margin for v in cfg.max_acceleration_mm_s2]
        self._inv_k = [1.0 / float(v) for v in cfg.stiffness_N_per_mm]
        self.sag_enabled = bool(sag) and cfg.mass_kg > 0.0
        g = [float(v) * 1e-3 for v in cfg.gravity_mm_s2]
        m = float(cfg.mass_kg)
        self._F = (m * g[0], m * g[1], m * g[2])
        self._cog = tuple(float(v) for v in cfg.center_of_gravity_mm)
        self._axis = tuple(float(v) for v in cfg.tool.axis_platform)
        self._tol = float(cfg.kinematics.fk_tolerance_mm)
        self._max_iter = int(cfg.kinematics.fk_max_iterations)
        # pivot ratio below which the Jacobian counts as near-singular
        self._min_pivot = 1.0 / float(cfg.kinematics.max_condition)
        self._scale = 1.0 / hx.char_length_mm
        # preallocated state
        self.length_mm = [0.0] * 6
        self.cmd_mm = [0.0] * 6
        self.sag_mm = [0.0] * 6
        self.thermal_mm = [0.0] * 6
        self.force_N = [0.0] * 6
        self.spindle_growth_mm = 0.0
        from .strutmap import strut_map_from_config
        self.strut_map = strut_map_from_config(cfg)
        self.calibrated = not self.strut_map.identity
        self.phys_mm = [0.0] * 6 if self.calibrated else self.cmd_mm
        self._cal_state = self.strut_map.new_state()
        self._fin = [0.0] * 6
        self._u = [0.0] * 18
        self._J = [0.0] * 36          # twist Jacobian rows, rotation columns scaled by 1/char_length
        self._piv = [0] * 6
        self._w = [0.0] * 6
        self._prev = [0.0] * 6
        self._prev2 = [0.0] * 6
        self._have_prev = 0
        self._Lgeo = [0.0] * 6
        self._r = [0.0] * 6
        self._d = [0.0] * 6
        self.pose_cmd = [0.0] * 6
        self.pose_act = [float(v) for v in hx.home_rad]
        self._last = list(self.pose_act)   # last solution
        self._h1 = list(self.pose_act)     # the one before
        self._h2 = list(self.pose_act)     # and the one before that
        self._nhist = 1
        self.fk_iterations = 0
        self.fk_residual_mm = 0.0
        self.fail_index = -1           #: strut/joint index of the last violation
        self.fail_value = 0.0
        self._factored = False
        self._fast = False
        self.reset_pose(hx.home_rad)
        if fast:
            from .cyclegen import bind_fast_path
            bind_fast_path(self)

    # ------------------------------------------------------------------ setup
    def set_thermal_offsets_mm(self, growth) -> None:
        """Modelled thermal growth of each strut (mm, + = longer); commands subtract it."""
        for i in range(6):
            v = float(growth[i])
            if not math.isfinite(v):
                raise ValueError(f"thermal offset of strut {i + 1} is not finite: {v!r}")
            self.thermal_mm[i] = v

    def set_spindle_growth_mm(self, growth_mm: float) -> None:
        """Tool growth along the platform tool axis (mm); the pose is shifted back by it."""
        if not math.isfinite(growth_mm):
            raise ValueError("spindle growth is not finite")
        self.spindle_growth_mm = float(growth_mm)

    def reset(self, lengths_mm) -> None:
        """Re-seed the velocity/acceleration guard with the current strut command (standstill)."""
        for i in range(6):
            self._prev[i] = float(lengths_mm[i])
            self._prev2[i] = float(lengths_mm[i])
        self._have_prev = 2

    def reset_pose(self, X) -> None:
        """Re-seed the forward-kinematics predictor at pose X (mm, rad)."""
        for i in range(6):
            v = float(X[i])
            self.pose_act[i] = v
            self._last[i] = v
            self._h1[i] = v
            self._h2[i] = v
        self._nhist = 1

    # ------------------------------------------------------------------ hot path
    def command(self, x: float, y: float, z: float, a: float, b: float, c: float) -> int:
        """Strut commands for platform pose (mm, rad). 0 or a limit code; on error cmd_mm is kept.

        Replaced at construction by the generated unrolled version (:mod:`hexacnc.cyclegen`)
        unless ``fast=False``; both compute the same.
        """
        return self._command_generic(x, y, z, a, b, c)

    def feedback(self, lengths_mm) -> int:
        """Actual pose from measured (drive) lengths; result in ``pose_act`` (mm, rad)."""
        return self._feedback_generic(lengths_mm)

    def _command_generic(self, x: float, y: float, z: float, a: float, b: float, c: float) -> int:
        """General path (loops, LU with partial pivoting)."""
        if not (x - x == 0.0 and y - y == 0.0 and z - z == 0.0 and a - a == 0.0 and b - b == 0.0
                and c - c == 0.0):
            return LIMIT_INPUT
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation_elements(a, b, c)
        pc = self.pose_cmd
        pc[0] = x; pc[1] = y; pc[2] = z; pc[3] = a; pc[4] = b; pc[5] = c
        g = self.spindle_growth_mm
        if g != 0.0:
            ax, ay, az = self._axis
            x -= g * (r00 * ax + r01 * ay + r02 * az)
            y -= g * (r10 * ax + r11 * ay + r12 * az)
            z -= g * (r20 * ax + r21 * ay + r22 * az)
        L = self.length_mm
        J = self._J
        sc_ = self._scale
        lmin = self._lmin; lmax = self._lmax; cmax = self._cos_max
        code = OK
        for i in range(6):
            px, py, pz = self._p[i]
            bx, by, bz = self._b[i]
            rx = r00 * px + r01 * py + r02 * pz
            ry = r10 * px + r11 * py + r12 * pz
            rz = r20 * px + r21 * py + r22 * pz
            sx = x + rx - bx; sy = y + ry - by; sz = z + rz - bz
            li = math.sqrt(sx * sx + sy * sy + sz * sz)
            L[i] = li
            ux = sx / li; uy = sy / li; uz = sz / li
            k = 6 * i
            J[k] = ux; J[k + 1] = uy; J[k + 2] = uz
            J[k + 3] = (ry * uz - rz * uy) * sc_
            J[k + 4] = (rz * ux - rx * uz) * sc_
            J[k + 5] = (rx * uy - ry * ux) * sc_
            if code == OK:
                if li < lmin[i] or li > lmax[i]:
                    code = LIMIT_LENGTH; self.fail_index = i; self.fail_value = li
                else:
                    ex, ey, ez = self._ab[i]
                    cosb = ux * ex + uy * ey + uz * ez
                    qx, qy, qz = self._ap[i]
                    # platform axis in base frame; strut direction there is -u
                    cosp = -(ux * (r00 * qx + r01 * qy + r02 * qz) + uy * (r10 * qx + r11 * qy + r12 * qz)
                             + uz * (r20 * qx + r21 * qy + r22 * qz))
                    if cosb < cmax[i]:
                        code = LIMIT_JOINT; self.fail_index = i; self.fail_value = cosb
                    elif cosp < cmax[i]:
                        code = LIMIT_JOINT; self.fail_index = i + 6; self.fail_value = cosp
        if code != OK:
            return code
        if not self._lu():
            self.fail_index = -1
            return LIMIT_SINGULAR
        if self.sag_enabled:
            self._sag_generic(r00, r01, r02, r10, r11, r12, r20, r21, r22)
        return self._guard_generic()

    def _sag_generic(self, r00, r01, r02, r10, r11, r12, r20, r21, r22) -> None:
        """Strut forces of the carrier's weight (J^T f = wrench, factored J) and the sag they cause."""
        # wrench about the platform origin: F and (R cog) x F, rotation rows scaled like J
        sc_ = self._scale
        Fx, Fy, Fz = self._F
        cx, cy, cz = self._cog
        gx = r00 * cx + r01 * cy + r02 * cz
        gy = r10 * cx + r11 * cy + r12 * cz
        gz = r20 * cx + r21 * cy + r22 * cz
        w = self._w
        w[0] = Fx; w[1] = Fy; w[2] = Fz
        w[3] = (gy * Fz - gz * Fy) * sc_
        w[4] = (gz * Fx - gx * Fz) * sc_
        w[5] = (gx * Fy - gy * Fx) * sc_
        self._solve_transposed(w, self.force_N)
        f = self.force_N
        ik = self._inv_k
        sag = self.sag_mm
        for i in range(6):
            sag[i] = f[i] * ik[i]

    def _guard_generic(self) -> int:
        """Commands = length - sag - thermal (through the calibrated map), velocity/acceleration guard."""
        L = self.length_mm
        lmin = self._lmin; lmax = self._lmax
        sag = self.sag_mm
        th = self.thermal_mm
        cmd = self.cmd_mm
        prev = self._prev; prev2 = self._prev2
        fin = self._fin
        for i in range(6):
            fin[i] = L[i] - sag[i] - th[i]
        if self.calibrated:
            ph = self.phys_mm
            for i in range(6):
                ph[i] = fin[i]
            k = self.strut_map.command_inplace(fin, self._cal_state)
            if k >= 0:
                self.fail_index = k; self.fail_value = ph[k]
                return LIMIT_CALIBRATION
            for i in range(6):
                if not lmin[i] <= fin[i] <= lmax[i]:      # NaN never reaches a drive
                    self.fail_index = i + 6; self.fail_value = fin[i]
                    return LIMIT_LENGTH
        if self._have_prev >= 2:
            dlm = self._dl_max; ddlm = self._ddl_max
            for i in range(6):
                v = fin[i]
                d1 = v - prev[i]
                if d1 > dlm[i] or -d1 > dlm[i]:
                    self.fail_index = i; self.fail_value = d1 / self.dt
                    return LIMIT_VELOCITY
                d2 = d1 - (prev[i] - prev2[i])
                if d2 > ddlm[i] or -d2 > ddlm[i]:
                    self.fail_index = i; self.fail_value = d2 / (self.dt * self.dt)
                    return LIMIT_ACCELERATION
        for i in range(6):
            v = fin[i]
            prev2[i] = prev[i]
            prev[i] = v
            cmd[i] = v
        if self._have_prev < 2:
            self._have_prev += 1
        return OK

    def _lu(self) -> bool:
        """In-place LU with partial pivoting of the 6x6 scaled Jacobian in ``_J``."""
        A = self._J
        piv = self._piv
        minp = self._min_pivot
        for i in range(6):
            piv[i] = i
        for k in range(6):
            p = k
            best = abs(A[6 * k + k])
            for r in range(k + 1, 6):
                v = abs(A[6 * r + k])
                if v > best:
                    best = v; p = r
            if best < minp:
                self._factored = False
                return False
            if p != k:
                kk = 6 * k; pp = 6 * p
                for cix in range(6):
                    A[kk + cix], A[pp + cix] = A[pp + cix], A[kk + cix]
                piv[k], piv[p] = piv[p], piv[k]
            kk = 6 * k
            d = A[kk + k]
            for r in range(k + 1, 6):
                rr = 6 * r
                f = A[rr + k] / d
                if f != 0.0:
                    A[rr + k] = f
                    for cix in range(k + 1, 6):
                        A[rr + cix] -= f * A[kk + cix]
                else:
                    A[rr + k] = 0.0
        self._factored = True
        self._fast = False
        return True

    def _solve(self, rhs, out) -> None:
        """Solve ``J x = rhs`` with the factors (scaled columns: out[3:] is omega * char_length)."""
        A = self._J; piv = self._piv
        for i in range(6):
            s = rhs[piv[i]]
            ii = 6 * i
            for j in range(i):
                s -= A[ii + j] * out[j]
            out[i] = s
        for i in range(5, -1, -1):
            ii = 6 * i
            s = out[i]
            for j in range(i + 1, 6):
                s -= A[ii + j] * out[j]
            out[i] = s / A[ii + i]

    def _solve_transposed(self, rhs, out) -> None:
        """Solve ``J^T y = rhs`` (P J = L U  =>  U^T L^T P y = rhs)."""
        A = self._J; piv = self._piv; z = self._d
        for i in range(6):          # U^T z = rhs
            s = rhs[i]
            for j in range(i):
                s -= A[6 * j + i] * z[j]
            z[i] = s / A[6 * i + i]
        for i in range(5, -1, -1):  # L^T v = z
            s = z[i]
            for j in range(i + 1, 6):
                s -= A[6 * j + i] * z[j]
            z[i] = s
        for i in range(6):
            out[piv[i]] = z[i]

    def _lengths_at(self, X, out) -> None:
        x, y, z, a, b, c = X
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation_elements(a, b, c)
        for i in range(6):
            px, py, pz = self._p[i]
            bx, by, bz = self._b[i]
            sx = x + r00 * px + r01 * py + r02 * pz - bx
            sy = y + r10 * px + r11 * py + r12 * pz - by
            sz = z + r20 * px + r21 * py + r22 * pz - bz
            out[i] = math.sqrt(sx * sx + sy * sy + sz * sz)

    def _feedback_generic(self, lengths_mm) -> int:
        if not self._factored:
            return FK_NOT_CONVERGED
        Lg = self._Lgeo
        sag = self.sag_mm; th = self.thermal_mm
        if self.calibrated:
            self.strut_map.strut_from_drive_inplace(lengths_mm, Lg)
            for i in range(6):
                Lg[i] += sag[i] + th[i]
        else:
            for i in range(6):
                Lg[i] = lengths_mm[i] + sag[i] + th[i]
        X = self.pose_act
        last = self._last; h1 = self._h1; h2 = self._h2
        n = self._nhist
        if n >= 3:
            for i in range(6):
                X[i] = 3.0 * last[i] - 3.0 * h1[i] + h2[i]
        elif n == 2:
            for i in range(6):
                X[i] = 2.0 * last[i] - h1[i]
        else:
            for i in range(6):
                X[i] = last[i]
        r = self._r; d = self._d
        tol = self._tol
        sc_ = self._scale
        it = 0
        while True:
            self._lengths_at(X, r)
            res = 0.0
            for i in range(6):
                e = Lg[i] - r[i]
                r[i] = e
                if e > res:
                    res = e
                elif -e > res:
                    res = -e
            if res <= tol or it >= self._max_iter or res != res:
                break
            self._solve(r, d)
            # d = [dt, omega * char_length]; Euler rates from omega: E^-1
            ox = d[3] * sc_; oy = d[4] * sc_; oz = d[5] * sc_
            bb = X[4]; cc_ = X[5]
            cbv = math.cos(bb); sbv = math.sin(bb); ccv = math.cos(cc_); scv = math.sin(cc_)
            da = (ccv * ox + scv * oy) / cbv
            X[0] += d[0]; X[1] += d[1]; X[2] += d[2]
            X[3] += da
            X[4] += -scv * ox + ccv * oy
            X[5] += oz + sbv * da
            it += 1
        self.fk_iterations = it
        self.fk_residual_mm = res
        if not res <= tol:
            # keep the last good solution and restart the predictor from it
            for i in range(6):
                X[i] = last[i]
            self._nhist = 1
            return FK_NOT_CONVERGED
        for i in range(6):
            h2[i] = h1[i]
            h1[i] = last[i]
            last[i] = X[i]
        if n < 3:
            self._nhist = n + 1
        return OK

    # ------------------------------------------------------------------ slow path
    def describe(self, code: int) -> str:
        """Text for a status code, naming the strut or joint (slow path)."""
        text = STATUS_TEXT.get(code, f"status {code}")
        i = self.fail_index
        if code == LIMIT_LENGTH and i >= 6:
            return (f"{text}: strut {i - 5} drive command {self.fail_value:.4f} mm (calibrated) outside "
                    f"[{self._lmin[i - 6]:g}, {self._lmax[i - 6]:g}] mm")
        if code == LIMIT_CALIBRATION and i >= 0:
            return f"{text}: strut {i + 1} at physical length {self.fail_value:.4f} mm"
        if code == LIMIT_LENGTH and i >= 0:
            return (f"{text}: strut {i + 1} length {self.fail_value:.4f} mm outside "
                    f"[{self._lmin[i]:g}, {self._lmax[i]:g}] mm")
        if code == LIMIT_JOINT and i >= 0:
            which = "base" if i < 6 else "platform"
            j = i % 6
            ang = math.degrees(math.acos(max(-1.0, min(1.0, self.fail_value))))
            return (f"{text}: {which} joint {j + 1} at {ang:.3f} deg over "
                    f"max_angle_deg {math.degrees(math.acos(self._cos_max[j])):g}")
        if code == LIMIT_VELOCITY and i >= 0:
            return (f"{text}: strut {i + 1} at {self.fail_value:.1f} mm/s over "
                    f"max_velocity_mm_s {self.cfg.max_velocity_mm_s[i]:g}")
        if code == LIMIT_ACCELERATION and i >= 0:
            return (f"{text}: strut {i + 1} at {self.fail_value:.0f} mm/s^2 over "
                    f"max_acceleration_mm_s2 {self.cfg.max_acceleration_mm_s2[i]:g}")
        if code == FK_NOT_CONVERGED:
            return f"{text}: residual {self.fk_residual_mm:.3g} mm after {self.fk_iterations} iterations"
        return text

    def pose_act_deg(self) -> list[float]:
        p = self.pose_act
        return [p[0], p[1], p[2], math.degrees(p[3]), math.degrees(p[4]), math.degrees(p[5])]


def as_array(values) -> np.ndarray:
    """Copy a preallocated list into a new numpy array (slow path helper)."""
    return np.array(values, dtype=float)
