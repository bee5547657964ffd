"""Hexapod kinematics: inverse (closed form), forward (Newton-Raphson), Jacobians.

Conventions (see :mod:`hexacnc.pose`): pose ``[x, y, z, a, b, c]`` in mm and
degrees at the interface; ``R = Rz(c) Ry(b) Rx(a)``; strut vector
``s_i = t + R p_i - b_i``, length ``L_i = |s_i|``, drive reading
``q_i = L_i - strut_offset_i``.

Jacobians here are with respect to ``X = [x, y, z, a, b, c]`` with the angles in
**radians**: ``dL = J @ dX``.  The twist Jacobian ``J_twist`` maps
``[dt, omega]`` (base frame) to ``dL``; ``J = J_twist @ diag(I, E)`` where ``E``
maps Euler rates to angular velocity (:func:`hexacnc.pose.rate_matrix`).
Forward kinematics steps with ``J`` - the correct angle-rate mapping - not with
``J_twist`` as LinuxCNC's genhexkins does.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import KinematicsError
from .pose import (matrices_from_euler, matrix_from_euler, pose_to_deg, pose_to_rad, rate_matrix,
                   rotation_elements_batch)

#: forward-kinematics status values (returned, never raised)
FK_OK = "ok"
FK_MAX_ITERATIONS = "max_iterations"
FK_SINGULAR = "singular"
FK_DIVERGED = "diverged"


@dataclass
class FKResult:
    """Outcome of one forward-kinematics call (failure is a value)."""
    pose: np.ndarray          #: (6,) mm / deg
    iterations: int           #: Newton updates done
    residual_mm: float        #: max |L(pose) - L_measured|
    status: str               #: FK_OK, FK_MAX_ITERATIONS, FK_SINGULAR or FK_DIVERGED
    condition: float          #: scaled Jacobian condition at the solution

    @property
    def ok(self) -> bool:
        return self.status == FK_OK


def strut_lengths_batch(X: np.ndarray, plat: np.ndarray, base: np.ndarray, r=None) -> np.ndarray:
    """Strut lengths (N,6) for platform poses X (N,6) mm/rad - a fast batch inverse kinematics.

    ``r``: :func:`hexacnc.pose.rotation_elements_batch` of ``X[:, 3:]`` if already at hand.  In-place arithmetic in the
    order ``x + r0 px + r1 py + r2 pz - b`` (the same rounding as the plain expression).
    """
    r = rotation_elements_batch(X[:, 3:]) if r is None else r
    N = X.shape[0]
    L = np.empty((N, 6))
    t = np.empty(N)
    acc = np.empty(N)
    sq = np.empty(N)
    for i in range(6):
        px, py, pz = plat[i]
        for c in range(3):
            np.multiply(r[3 * c], px, out=acc)
            np.add(X[:, c], acc, out=acc)
            np.multiply(r[3 * c + 1], py, out=t)
            acc += t
            np.multiply(r[3 * c + 2], pz, out=t)
            acc += t
            acc -= base[i, c]
            if c == 0:
                np.multiply(acc, acc, out=sq)
            else:
                np.multiply(acc, acc, out=t)
                sq += t
        np.sqrt(sq, out=L[:, i])
    return L


class Hexapod:
    """Kinematic model of one hexapod with explicit (possibly calibrated) parameters.

    Build it from a :class:`~hexacnc.config.MachineConfig` or with
    :meth:`from_parameters` for calibration (42 parameters: 18 base, 18 platform,
    6 strut offsets).
    """

    def __init__(self, cfg, base_joints_mm=None, platform_joints_mm=None, strut_offset_mm=None):
        self.cfg = cfg
        self.base = np.array(cfg.base_joints_mm if base_joints_mm is None else base_joints_mm, dtype=float)
        self.plat = np.array(cfg.platform_joints_mm if platform_joints_mm is None else platform_joints_mm,
                             dtype=float)
        self.offset = np.array(cfg.strut_offset_mm if strut_offset_mm is None else strut_offset_mm, dtype=float)
        if self.base.shape != (6, 3) or self.plat.shape != (6, 3) or self.offset.shape != (6,):
            raise KinematicsError("geometry must be 6x3 base joints, 6x3 platform joints and 6 offsets")
        if not (np.all(np.isfinite(self.base)) and np.all(np.isfinite(self.plat))
                and np.all(np.isfinite(self.offset))):
            raise KinematicsError("geometry contains NaN or infinite values")
        self.min_length = np.asarray(cfg.min_length_mm, dtype=float)
        self.max_length = np.asarray(cfg.max_length_mm, dtype=float)
        self.base_axes = np.asarray(cfg.base_axes, dtype=float)
        self.plat_axes = np.asarray(cfg.platform_axes, dtype=float)
        self.max_angle_rad = np.radians(np.asarray(cfg.max_angle_deg, dtype=float))
        self.tol_mm = float(cfg.kinematics.fk_tolerance_mm)
        self.max_iter = int(cfg.kinematics.fk_max_iterations)
        self.max_condition = float(cfg.kinematics.max_condition)
        self.home_rad = pose_to_rad(cfg.home_pose)
        #: characteristic length that makes rotation columns comparable to translation
        self.char_length_mm = max(1.0, float(np.mean(np.linalg.norm(self.plat[:, :2], axis=1))))

    # -- parameters ----------------------------------------------------------
    @classmethod
    def from_parameters(cls, cfg, params: np.ndarray) -> "Hexapod":
        """Model from a 42-vector ``[base (18), platform (18), offsets (6)]`` in mm."""
        p = np.asarray(params, dtype=float)
        if p.shape != (42,):
            raise KinematicsError(f"expected 42 parameters, got shape {p.shape}")
        return cls(cfg, p[:18].reshape(6, 3), p[18:36].reshape(6, 3), p[36:42])

    def parameters(self) -> np.ndarray:
        """The 42 geometric parameters ``[base (18), platform (18), offsets (6)]``."""
        return np.concatenate([self.base.ravel(), self.plat.ravel(), self.offset])

    # -- inverse kinematics ---------------------------------------------------
    def lengths(self, pose) -> np.ndarray:
        """Strut lengths (6,) in mm for one pose (mm/deg)."""
        x = np.asarray(pose, dtype=float)
        if x.shape != (6,) or not np.all(np.isfinite(x)):
            raise KinematicsError(f"pose must be 6 finite numbers [x,y,z,a,b,c], got {x!r}")
        return self.lengths_rad(pose_to_rad(x))

    def lengths_rad(self, X: np.ndarray) -> np.ndarray:
        R = matrix_from_euler(X[3], X[4], X[5])
        s = X[:3] + self.plat @ R.T - self.base
        return np.sqrt(np.einsum("ij,ij->i", s, s))

    def inverse_batch(self, poses) -> np.ndarray:
        """Strut lengths (N,6) for poses (N,6) mm/deg (batch path for planning and fitting)."""
        P = np.asarray(poses, dtype=float)
        if P.ndim != 2 or P.shape[1] != 6:
            raise KinematicsError(f"poses must be an (N,6) array, got shape {P.shape}")
        X = P.copy()
        X[:, 3:] = np.radians(P[:, 3:])
        return strut_lengths_batch(X, self.plat, self.base)

    def strut_vectors_batch(self, poses) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Strut vectors s (N,6,3), lengths (N,6) and rotated platform joints R p (N,6,3)."""
        P = np.asarray(poses, dtype=float)
        R = matrices_from_euler(np.radians(P[:, 3:]))
        rp = np.einsum("nij,kj->nki", R, self.plat)
        s = P[:, None, :3] + rp - self.base[None]
        return s, np.sqrt(np.einsum("nki,nki->nk", s, s)), rp

    def readings(self, pose) -> np.ndarray:
        """Drive readings q (6,) = L - strut_offset for one pose."""
        return self.lengths(pose) - self.offset

    # -- Jacobians --------------------------------------------------------------
    def jacobian_twist_rad(self, X: np.ndarray, point_platform=None) -> np.ndarray:
        """``J_twist`` (6,6): ``dL = J_twist @ [dt, omega]``; ``t`` at ``point_platform``."""
        R = matrix_from_euler(X[3], X[4], X[5])
        rp = self.plat @ R.T
        s = X[:3] + rp - self.base
        u = s / np.linalg.norm(s, axis=1)[:, None]
        arm = rp if point_platform is None else rp - R @ np.asarray(point_platform, dtype=float)
        return np.hstack([u, np.cross(arm, u)])

    def jacobian_rad(self, X: np.ndarray) -> np.ndarray:
        """``J`` (6,6) with ``dL = J @ dX``, X in mm and radians."""
        Jt = self.jacobian_twist_rad(X)
        Jt[:, 3:] = Jt[:, 3:] @ rate_matrix(X[3], X[4], X[5])
        return Jt

    def jacobian(self, pose) -> np.ndarray:
        """``J`` (6,6) at a pose in mm/deg; columns 3..5 per radian."""
        return self.jacobian_rad(pose_to_rad(pose))

    def jacobian_cog(self, pose) -> np.ndarray:
        """``Jd`` (6,6): ``dL = Jd @ [dx_cog, dy_cog, dz_cog, da, db, dc]`` (radians).

        Coordinates are the carrier's centre of gravity (base frame) and the
        Euler angles.
        """
        X = pose_to_rad(pose)
        Jt = self.jacobian_twist_rad(X, self.cfg.center_of_gravity_mm)
        Jt[:, 3:] = Jt[:, 3:] @ rate_matrix(X[3], X[4], X[5])
        return Jt

    def condition_rad(self, X: np.ndarray) -> float:
        """Condition number of ``J_twist`` with rotation columns scaled by a characteristic length."""
        J = self.jacobian_twist_rad(X)
        J[:, 3:] /= self.char_length_mm
        try:
            return float(np.linalg.cond(J))
        except np.linalg.LinAlgError:
            return math.inf

    def condition(self, pose) -> float:
        return self.condition_rad(pose_to_rad(pose))

    # -- forward kinematics -------------------------------------------------------
    def forward(self, lengths, guess=None, tol_mm: float | None = None, max_iter: int | None = None) -> FKResult:
        """Pose (mm/deg) from strut lengths by Newton-Raphson; never raises on failure.

        ``guess``: starting pose (mm/deg), default the home pose.
        """
        L = np.asarray(lengths, dtype=float)
        X0 = self.home_rad.copy() if guess is None else pose_to_rad(guess)
        res = self.forward_rad(L, X0, tol_mm, max_iter)
        return res

    def forward_readings(self, readings, guess=None) -> FKResult:
        return self.forward(np.asarray(readings, dtype=float) + self.offset, guess)

    def forward_rad(self, L: np.ndarray, X: np.ndarray, tol_mm: float | None = None,
                    max_iter: int | None = None) -> FKResult:
        tol = self.tol_mm if tol_mm is None else tol_mm
        nmax = self.max_iter if max_iter is None else max_iter
        if L.shape != (6,) or not np.all(np.isfinite(L)):
            return FKResult(pose_to_deg(X), 0, math.inf, FK_DIVERGED, math.inf)
        X = np.array(X, dtype=float)
        it = 0
        r = L - self.lengths_rad(X)
        res = float(np.max(np.abs(r)))
        while res > tol:
            if it >= nmax:
                return FKResult(pose_to_deg(X), it, res, FK_MAX_ITERATIONS, self.condition_rad(X))
            J = self.jacobian_rad(X)
            try:
                dX = np.linalg.solve(J, r)
            except np.linalg.LinAlgError:
                return FKResult(pose_to_deg(X), it, res, FK_SINGULAR, math.inf)
            X += dX
            it += 1
            r = L - self.lengths_rad(X)
            res = float(np.max(np.abs(r)))
            if not math.isfinite(res) or res > 1e6:
                return FKResult(pose_to_deg(X), it, res, FK_DIVERGED, math.inf)
        cond = self.condition_rad(X)
        status = FK_OK if cond <= self.max_condition else FK_SINGULAR
        return FKResult(pose_to_deg(X), it, res, status, cond)

    # -- joints and limits -----------------------------------------------------------
    def joint_angles(self, pose) -> tuple[np.ndarray, np.ndarray]:
        """Angles (deg) of each strut against its base and platform joint's neutral axis."""
        X = pose_to_rad(pose)
        R = matrix_from_euler(X[3], X[4], X[5])
        s = X[:3] + self.plat @ R.T - self.base
        u = s / np.linalg.norm(s, axis=1)[:, None]
        cb = np.clip(np.einsum("ij,ij->i", u, self.base_axes), -1.0, 1.0)
        up = -(u @ R)  # strut direction from platform joint to base joint, platform frame
        cp = np.clip(np.einsum("ij,ij->i", up, self.plat_axes), -1.0, 1.0)
        return np.degrees(np.arccos(cb)), np.degrees(np.arccos(cp))

    def joint_angles_batch(self, poses) -> tuple[np.ndarray, np.ndarray]:
        """Batch joint angles (N,6) base and (N,6) platform, degrees."""
        P = np.asarray(poses, dtype=float)
        R = matrices_from_euler(np.radians(P[:, 3:]))
        s, L, _ = self.strut_vectors_batch(P)
        u = s / L[..., None]
        cb = np.clip(np.einsum("nki,ki->nk", u, self.base_axes), -1.0, 1.0)
        up = -np.einsum("nki,nij->nkj", u, R)
        cp = np.clip(np.einsum("nkj,kj->nk", up, self.plat_axes), -1.0, 1.0)
        return np.degrees(np.arccos(cb)), np.degrees(np.arccos(cp))

    def limit_violations(self, pose) -> list[str]:
        """Human-readable list of every strut-length and joint-angle limit the pose breaks."""
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            return [f"pose {pose!r} is not 6 finite numbers"]
        out = []
        L = self.lengths(pose)
        for i in range(6):
            if L[i] < self.min_length[i]:
                out.append(f"strut {i + 1} length {L[i]:.4f} mm below min_length_mm {self.min_length[i]:g}")
            elif L[i] > self.max_length[i]:
                out.append(f"strut {i + 1} length {L[i]:.4f} mm above max_length_mm {self.max_length[i]:g}")
        ab, ap = self.joint_angles(pose)
        lim = np.degrees(self.max_angle_rad)
        for i in range(6):
            if ab[i] > lim[i]:
                out.append(f"base joint {i + 1} angle {ab[i]:.3f} deg over max_angle_deg {lim[i]:g}")
            if ap[i] > lim[i]:
                out.append(f"platform joint {i + 1} angle {ap[i]:.3f} deg over max_angle_deg {lim[i]:g}")
        cond = self.condition(pose)
        if not math.isfinite(cond) or cond > self.max_condition:
            out.append(f"near-singular pose: Jacobian condition {cond:.3g} over max_condition {self.max_condition:g}")
        return out

    def check_pose(self, pose) -> None:
        """Raise :class:`KinematicsError` naming every limit the pose breaks."""
        v = self.limit_violations(pose)
        if v:
            raise KinematicsError("; ".join(v))

    def batch_violations(self, poses) -> np.ndarray:
        """Boolean (N,) mask of poses that break a strut-length or joint-angle limit."""
        L = self.inverse_batch(poses)
        ab, ap = self.joint_angles_batch(poses)
        lim = np.degrees(self.max_angle_rad)
        return (np.any(L < self.min_length, axis=1) | np.any(L > self.max_length, axis=1)
                | np.any(ab > lim, axis=1) | np.any(ap > lim, axis=1))


class ForwardTracker:
    """Warm-started forward kinematics for a stream of readings (one per cycle).

    The starting point is a quadratic extrapolation of the last three solutions
    (linear after two), so at 2 kHz a single Newton update usually reaches 1 nm.
    """

    def __init__(self, hexapod: Hexapod, start_pose=None):
        self.hx = hexapod
        X = hexapod.home_rad.copy() if start_pose is None else pose_to_rad(start_pose)
        self.hist = [X.copy()]
        self.iterations_total = 0
        self.calls = 0
        self.max_iterations = 0

    def predict(self) -> np.ndarray:
        h = self.hist
        if len(h) >= 3:
            return 3.0 * h[-1] - 3.0 * h[-2] + h[-3]
        if len(h) == 2:
            return 2.0 * h[-1] - h[-2]
        return h[-1].copy()

    def track(self, lengths) -> FKResult:
        res = self.hx.forward_rad(np.asarray(lengths, dtype=float), self.predict())
        if res.status in (FK_OK, FK_SINGULAR):
            self.hist.append(pose_to_rad(res.pose))
            if len(self.hist) > 3:
                del self.hist[0]
        else:  # restart the predictor from the last good pose
            self.hist = self.hist[-1:]
        self.calls += 1
        self.iterations_total += res.iterations
        self.max_iterations = max(self.max_iterations, res.iterations)
        return res

    @property
    def mean_iterations(self) -> float:
        return self.iterations_total / self.calls if self.calls else 0.0
