"""Rotations and pose conventions.

Pose ``[x, y, z, a, b, c]``: x, y, z in mm, a, b, c in degrees at every
interface, radians inside.  ``R = Rz(c) @ Ry(b) @ Rx(a)``; a platform point
``p`` maps to the base frame as ``t + R @ p``.

Angular velocity ``omega`` (base frame) and Euler rates are related by
``omega = E(a, b, c) @ [da, db, dc]`` with
``E = [Rz(c) Ry(b) e_x, Rz(c) e_y, e_z]``; E is singular at ``b = +-90 deg``.
"""
from __future__ import annotations

import math

import numpy as np

_HALF_PI = 0.5 * math.pi


#: the rotation ``Rz(c) Ry(b) Rx(a)`` as Python statements over ``ca, sa, cb, sb, cc, sc`` (cosines and
#: sines of a, b, c) defining ``r00 .. r22``: the one expansion that generated code
#: (:mod:`hexacnc.cyclegen`) inlines; :func:`rotation_elements` evaluates the same expressions.
ROTATION_STATEMENTS = (
    "r00 = cc * cb; r01 = cc * sb * sa - sc * ca; r02 = cc * sb * ca + sc * sa",
    "r10 = sc * cb; r11 = sc * sb * sa + cc * ca; r12 = sc * sb * ca - cc * sa",
    "r20 = -sb; r21 = cb * sa; r22 = cb * ca",
)


def _elements(ca, sa, cb, sb, cc, sc):
    """The nine elements of ``Rz(c) Ry(b) Rx(a)`` (row-major) from cosines and sines (floats or arrays)."""
    return (cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa,
            sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa,
            -sb, cb * sa, cb * ca)


def rotation_elements(a_rad: float, b_rad: float, c_rad: float) -> tuple:
    """``(r00, r01, r02, r10, r11, r12, r20, r21, r22)`` of ``Rz(c) Ry(b) Rx(a)``: plain floats."""
    return _elements(math.cos(a_rad), math.sin(a_rad), math.cos(b_rad), math.sin(b_rad),
                     math.cos(c_rad), math.sin(c_rad))


def rotation_elements_batch(abc_rad: np.ndarray) -> tuple:
    """Batch :func:`rotation_elements`: ``abc_rad`` (N,3) radians -> nine (N,) arrays (row-major)."""
    a, b, c = abc_rad[:, 0], abc_rad[:, 1], abc_rad[:, 2]
    return _elements(np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c))


def matrix_from_euler(a_rad: float, b_rad: float, c_rad: float) -> np.ndarray:
    """Rotation matrix (3,3) ``Rz(c) @ Ry(b) @ Rx(a)``."""
    return np.array(rotation_elements(a_rad, b_rad, c_rad)).reshape(3, 3)


def matrices_from_euler(abc_rad: np.ndarray) -> np.ndarray:
    """Batch version: ``abc_rad`` (N,3) radians -> (N,3,3)."""
    abc = np.asarray(abc_rad, dtype=float)
    R = np.empty((abc.shape[0], 9))
    for k, e in enumerate(rotation_elements_batch(abc)):
        R[:, k] = e
    return R.reshape(-1, 3, 3)


def euler_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`matrix_from_euler`; b in [-90, 90] deg (radians out)."""
    sb = -float(R[2, 0])
    sb = 1.0 if sb > 1.0 else (-1.0 if sb < -1.0 else sb)
    b = math.asin(sb)
    if abs(sb) < 1.0 - 1e-12:
        a = math.atan2(float(R[2, 1]), float(R[2, 2]))
        c = math.atan2(float(R[1, 0]), float(R[0, 0]))
    else:  # gimbal lock: put everything into c
        a = 0.0
        c = math.atan2(-float(R[0, 1]), float(R[1, 1]))
    return a, b, c


def rate_matrix(a_rad: float, b_rad: float, c_rad: float) -> np.ndarray:
    """E (3,3) with ``omega_base = E @ [da, db, dc]`` (radians)."""
    cb, sb = math.cos(b_rad), math.sin(b_rad)
    cc, sc = math.cos(c_rad), math.sin(c_rad)
    return np.array([[cc * cb, -sc, 0.0],
                     [sc * cb, cc, 0.0],
                     [-sb, 0.0, 1.0]])


def rate_matrices(abc_rad: np.ndarray) -> np.ndarray:
    """Batch :func:`rate_matrix`: ``abc_rad`` (N,3) radians -> (N,3,3) E with omega = E @ abc_rates."""
    abc = np.asarray(abc_rad, dtype=float)
    b, c = abc[:, 1], abc[:, 2]
    cb, sb, cc, sc = np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    E = np.zeros((abc.shape[0], 3, 3))
    E[:, 0, 0] = cc * cb
    E[:, 0, 1] = -sc
    E[:, 1, 0] = sc * cb
    E[:, 1, 1] = cc
    E[:, 2, 0] = -sb
    E[:, 2, 2] = 1.0
    return E


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` -> rotation matrix (3,3)."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(qx, qy, qz, qw)`` with qw >= 0."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rotation_angle_between(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (radians) of the rotation ``R1.T @ R2``."""
    c = (np.trace(np.asarray(R1).T @ np.asarray(R2)) - 1.0) * 0.5
    return math.acos(max(-1.0, min(1.0, float(c))))


def matrix_from_axis_angle(axis, angle_rad: float) -> np.ndarray:
    """Rotation (3,3) by ``angle_rad`` about ``axis`` (any length, not zero)."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    K = skew(k)
    return np.eye(3) + math.sin(angle_rad) * K + (1.0 - math.cos(angle_rad)) * (K @ K)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(v) @ w == cross(v, w)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def pose_to_rad(pose_deg) -> np.ndarray:
    """``[x,y,z,a,b,c]`` mm/deg -> mm/rad (new array)."""
    p = np.array(pose_deg, dtype=float)
    p[..., 3:] = np.radians(p[..., 3:])
    return p


def pose_to_deg(pose_rad) -> np.ndarray:
    """``[x,y,z,a,b,c]`` mm/rad -> mm/deg (new array)."""
    p = np.array(pose_rad, dtype=float)
    p[..., 3:] = np.degrees(p[..., 3:])
    return p
