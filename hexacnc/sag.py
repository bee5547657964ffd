"""Elastic sag: strut forces from the carrier's weight, compressions and compensation.

Sign conventions: strut force ``f_i`` in N, **tension positive** (a strut in
tension pulls the platform towards its base joint).  The wrench acting on the
carrier (gravity of carrier + payload, plus an optional extra wrench) balances
the strut forces: ``J_twist^T f = w`` with ``w = [F (N), M (N mm)]`` about the
platform origin in the base frame.  A strut of stiffness ``k_i`` (N/mm) under
``f_i`` gets longer by ``e_i = f_i / k_i`` (mm).

First order (the seed paper's ``dX = Jd^-1 c^-1 J'^-T m g``):
the pose deviation at the centre of gravity is ``Jd^-1 e``;
compensation commands ``L - e`` so that the loaded strut reaches ``L``.

:func:`exact_equilibrium` solves the nonlinear spring equilibrium to measure how
far the first-order model is from it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kinematics import Hexapod
from .pose import matrix_from_euler, pose_to_deg, pose_to_rad


def gravity_wrench(hx: Hexapod, X: np.ndarray, payload_kg: float = 0.0, payload_point_mm=None,
                   extra_wrench=None) -> np.ndarray:
    """Wrench (6,) [N, N mm] on the carrier about the platform origin, base frame.

    ``X`` in mm/rad.  The payload sits at ``payload_point_mm`` (platform frame,
    default: the tool tip ``[tool] tip_platform_mm``).
    """
    cfg = hx.cfg
    g = np.asarray(cfg.gravity_mm_s2, dtype=float) * 1e-3   # m/s^2
    R = matrix_from_euler(X[3], X[4], X[5])
    F = cfg.mass_kg * g
    M = np.cross(R @ np.asarray(cfg.center_of_gravity_mm, dtype=float), F)
    if payload_kg:
        pp = np.asarray(cfg.tool.tip_platform_mm if payload_point_mm is None else payload_point_mm, dtype=float)
        Fp = payload_kg * g
        F = F + Fp
        M = M + np.cross(R @ pp, Fp)
    w = np.concatenate([F, M])
    if extra_wrench is not None:
        w = w + np.asarray(extra_wrench, dtype=float)
    return w


def strut_forces_N(hx: Hexapod, pose, payload_kg: float = 0.0, payload_point_mm=None,
                   extra_wrench=None) -> np.ndarray:
    """Static strut forces (6,) in N, tension positive, at a pose (mm/deg)."""
    X = pose_to_rad(pose)
    Jt = hx.jacobian_twist_rad(X)
    w = gravity_wrench(hx, X, payload_kg, payload_point_mm, extra_wrench)
    return np.linalg.solve(Jt.T, w)


def sag_elongation_mm(hx: Hexapod, pose, **load) -> np.ndarray:
    """Strut elongation ``e = f / k`` (6,) in mm (negative: compressed)."""
    return strut_forces_N(hx, pose, **load) / np.asarray(hx.cfg.stiffness_N_per_mm, dtype=float)


def sag_compensation_mm(hx: Hexapod, pose, **load) -> np.ndarray:
    """Offsets (6,) to add to the commanded strut lengths: ``-e``."""
    return -sag_elongation_mm(hx, pose, **load)


@dataclass
class EquilibriumResult:
    pose: np.ndarray          #: (6,) mm/deg, platform origin
    forces_N: np.ndarray      #: (6,)
    iterations: int
    residual_N: float


def exact_equilibrium(hx: Hexapod, rest_lengths_mm, guess, payload_kg: float = 0.0,
                      extra_wrench=None, tol_N: float = 1e-9, max_iter: int = 50) -> EquilibriumResult:
    """Nonlinear static equilibrium of the carrier on six linear springs.

    Struts of rest length ``rest_lengths_mm`` and stiffness ``[struts]
    stiffness_N_per_mm``; Newton on ``J_twist(X)^T f(X) - w(X) = 0`` with
    ``f_i = k_i (L_i(X) - rest_i)`` and a central-difference Jacobian.
    """
    k = np.asarray(hx.cfg.stiffness_N_per_mm, dtype=float)
    L0 = np.asarray(rest_lengths_mm, dtype=float)
    X = pose_to_rad(guess)

    def residual(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = k * (hx.lengths_rad(X) - L0)
        Jt = hx.jacobian_twist_rad(X)
        w = gravity_wrench(hx, X, payload_kg, None, extra_wrench)
        # strut forces act on the carrier as -f_i u_i; balance: -J^T f + w = 0
        Et = np.eye(6)
        Et[3:, 3:] = _rate(X)
        return Et.T @ (w - Jt.T @ f), f

    it = 0
    g, f = residual(X)
    scale = max(1.0, float(np.max(np.abs(g))))
    while float(np.max(np.abs(g))) > tol_N * scale and it < max_iter:
        H = np.empty((6, 6))
        for j in range(6):
            h = 1e-7 if j < 3 else 1e-10
            Xp = X.copy()
            Xp[j] += h
            Xm = X.copy()
            Xm[j] -= h
            H[:, j] = (residual(Xp)[0] - residual(Xm)[0]) / (2 * h)
        X = X - np.linalg.solve(H, g)
        g, f = residual(X)
        it += 1
    return EquilibriumResult(pose_to_deg(X), f, it, float(np.max(np.abs(g))))


def _rate(X: np.ndarray) -> np.ndarray:
    from .pose import rate_matrix
    return rate_matrix(X[3], X[4], X[5])


def first_order_error(hx: Hexapod, poses, payload_kg: float = 0.0) -> dict:
    """How far the first-order sag model is from the exact equilibrium over ``poses``.

    For each pose: rest lengths = nominal IK (uncompensated command); the exact
    equilibrium pose minus the nominal pose is compared with the first-order
    deviation.  Returns maxima in mm (position of the platform origin) and deg.
    """
    pos_err, ang_err, pos_sag, ang_sag = [], [], [], []
    for pose in np.asarray(poses, dtype=float):
        L0 = hx.lengths(pose)
        eq = exact_equilibrium(hx, L0, pose, payload_kg)
        exact = eq.pose - pose
        X = pose_to_rad(pose)
        e = (strut_forces_N(hx, pose, payload_kg) / np.asarray(hx.cfg.stiffness_N_per_mm, dtype=float))
        first = np.linalg.solve(hx.jacobian_rad(X), e)    # platform origin, radians
        first[3:] = np.degrees(first[3:])
        pos_err.append(float(np.linalg.norm(exact[:3] - first[:3])))
        ang_err.append(float(np.max(np.abs(exact[3:] - first[3:]))))
        pos_sag.append(float(np.linalg.norm(exact[:3])))
        ang_sag.append(float(np.max(np.abs(exact[3:]))))
    return {
        "poses": len(pos_err),
        "max_sag_position_mm": max(pos_sag) if pos_sag else math.nan,
        "max_sag_orientation_deg": max(ang_sag) if ang_sag else math.nan,
        "max_first_order_error_position_mm": max(pos_err) if pos_err else math.nan,
        "max_first_order_error_orientation_deg": max(ang_err) if ang_err else math.nan,
    }
