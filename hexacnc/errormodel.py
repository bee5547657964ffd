"""Kinematic error model: sensitivity to the 42 geometric parameters.

Parameter vector ``theta`` (42,), mm:
``[b_1x, b_1y, b_1z, ..., b_6z (18, base frame), p_1x, ..., p_6z (18, platform frame), o_1..o_6 (6, strut offsets)]``.

The predicted drive reading of strut i at pose X is ``q_i = |t + R p_i - b_i| - o_i``.

* :func:`reading_parameter_jacobian` gives ``dq/dtheta`` at a fixed pose (N,6,42):
  ``dq_i/db_i = -u_i``, ``dq_i/dp_i = R^T u_i``, ``dq_i/do_i = -1``.
* :func:`pose_sensitivity` gives ``dX/dtheta`` at fixed readings (6,42):
  from ``J dX + dq/dtheta dtheta = 0``, ``dX/dtheta = -J^-1 dq/dtheta``
  (angles of X in radians unless ``degrees=True``).
"""
from __future__ import annotations

import numpy as np

from .kinematics import Hexapod
from .pose import matrices_from_euler, pose_to_rad

N_PARAMS = 42

#: human-readable parameter names, in order
PARAM_NAMES: tuple[str, ...] = tuple(
    [f"base{i + 1}_{ax}" for i in range(6) for ax in "xyz"]
    + [f"platform{i + 1}_{ax}" for i in range(6) for ax in "xyz"]
    + [f"offset{i + 1}" for i in range(6)]
)


def reading_parameter_jacobian(hx: Hexapod, poses) -> np.ndarray:
    """``dq/dtheta`` (N,6,42) for poses (N,6) mm/deg (or one pose (6,) -> (6,42))."""
    P = np.asarray(poses, dtype=float)
    single = P.ndim == 1
    if single:
        P = P[None]
    s, L, _ = hx.strut_vectors_batch(P)
    u = s / L[..., None]                                   # (N,6,3) base frame
    R = matrices_from_euler(np.radians(P[:, 3:]))          # (N,3,3)
    u_plat = np.einsum("nij,nki->nkj", R, u)               # R^T u_i  (N,6,3)
    n = P.shape[0]
    G = np.zeros((n, 6, N_PARAMS))
    for i in range(6):
        G[:, i, 3 * i:3 * i + 3] = -u[:, i]
        G[:, i, 18 + 3 * i:18 + 3 * i + 3] = u_plat[:, i]
        G[:, i, 36 + i] = -1.0
    return G[0] if single else G


#: alias documented in docs/architecture.md (same quantity: the residual r = q_pred - q_meas)
strut_parameter_jacobian = reading_parameter_jacobian


def pose_sensitivity(hx: Hexapod, pose, degrees: bool = False) -> np.ndarray:
    """``dX/dtheta`` (6,42) at fixed drive readings; rows x,y,z (mm) and a,b,c (rad or deg)."""
    pose = np.asarray(pose, dtype=float)
    J = hx.jacobian_rad(pose_to_rad(pose))
    G = reading_parameter_jacobian(hx, pose)
    S = -np.linalg.solve(J, G)
    if degrees:
        S[3:] = np.degrees(S[3:])
    return S


def pose_sensitivity_numeric(hx: Hexapod, pose, step_mm: float = 1e-5) -> np.ndarray:
    """Finite-difference check of :func:`pose_sensitivity` (central differences, radians)."""
    pose = np.asarray(pose, dtype=float)
    q = hx.readings(pose)
    theta = hx.parameters()
    S = np.empty((6, N_PARAMS))
    for k in range(N_PARAMS):
        out = []
        for sgn in (1.0, -1.0):
            th = theta.copy()
            th[k] += sgn * step_mm
            h = Hexapod.from_parameters(hx.cfg, th)
            r = h.forward(q + h.offset, guess=pose, tol_mm=1e-12, max_iter=50)
            out.append(pose_to_rad(r.pose))
        S[:, k] = (out[0] - out[1]) / (2 * step_mm)
    return S
