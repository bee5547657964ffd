"""Path pieces' shared primitives: piece kinds, the quintic Hermite piece and the G64 P distance.

Used by the path builder (:mod:`hexacnc.planner.path`) and the CAM smoothing
(:mod:`hexacnc.planner.smooth`), neither of which imports the other's internals.
A quintic piece's coefficients are ``[P0, V0, A0, A1, V1, P1]`` (6 each, pose mm/rad) in its
parameter ``w`` in [0, 1].
"""
from __future__ import annotations

import numpy as np

#: piece kinds
LINE, ARC, BLEND, SPLINE = 0, 1, 2, 3
#: coefficients per piece
NCOEF = 36


def quintic(w: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Quintic Hermite blend at w (broadcast against c[..., :6]); c[..., :36] = [P0, V0, A0, A1, V1, P1]."""
    w2 = w * w
    w3 = w2 * w
    w4 = w3 * w
    w5 = w4 * w
    return ((1 - 10 * w3 + 15 * w4 - 6 * w5) * c[..., 0:6] + (w - 6 * w3 + 8 * w4 - 3 * w5) * c[..., 6:12]
            + (0.5 * w2 - 1.5 * w3 + 1.5 * w4 - 0.5 * w5) * c[..., 12:18]
            + (0.5 * w3 - w4 + 0.5 * w5) * c[..., 18:24] + (-4 * w3 + 7 * w4 - 3 * w5) * c[..., 24:30]
            + (10 * w3 - 15 * w4 + 6 * w5) * c[..., 30:36])


def quintic_derivs(w: np.ndarray, c: np.ndarray):
    """First and second derivatives in ``w`` of the quintic Hermite pieces ``c`` (n, 36) at w (n,)."""
    w = w[:, None]
    w2 = w * w
    w3 = w2 * w
    w4 = w3 * w
    seg = [c[:, 6 * i:6 * i + 6] for i in range(6)]
    d1 = ((-30 * w2 + 60 * w3 - 30 * w4) * seg[0] + (1 - 18 * w2 + 32 * w3 - 15 * w4) * seg[1]
          + (w - 4.5 * w2 + 6 * w3 - 2.5 * w4) * seg[2] + (1.5 * w2 - 4 * w3 + 2.5 * w4) * seg[3]
          + (-12 * w2 + 28 * w3 - 15 * w4) * seg[4] + (30 * w2 - 60 * w3 + 30 * w4) * seg[5])
    d2 = ((-60 * w + 180 * w2 - 120 * w3) * seg[0] + (-36 * w + 96 * w2 - 60 * w3) * seg[1]
          + (1 - 9 * w + 18 * w2 - 10 * w3) * seg[2] + (3 * w - 12 * w2 + 10 * w3) * seg[3]
          + (-24 * w + 84 * w2 - 60 * w3) * seg[4] + (60 * w - 180 * w2 + 120 * w3) * seg[5])
    return d1, d2


def pose_deviation(diff: np.ndarray) -> np.ndarray:
    """The path-tolerance distance of pose differences ``diff`` (..., 6) mm/rad: the larger of the
    x, y, z distance (mm) and the a, b, c distance (deg), as G64 P reads them."""
    return np.maximum(np.linalg.norm(diff[..., :3], axis=-1), np.linalg.norm(np.degrees(diff[..., 3:]), axis=-1))


