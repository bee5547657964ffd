"""Path-limit checks on the planning grid: strut lengths, joint angles and Jacobian condition.

Step 2 of the method in :mod:`hexacnc.planner.plan`: the limits are checked at the grid's samples,
shrunk by the sampling bounds of :func:`~hexacnc.planner.path.sample_spacing`; the first violation is a
:class:`~hexacnc.errors.PlanError` naming line and limit.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import PlanError
from ..kinematics import Hexapod
from . import path as P


def _strut_geometry(X: np.ndarray, hx: Hexapod):
    """Per strut k (lists of 6): unit vectors ``u[k]`` (3 arrays (N,)), lengths ``L`` (N,6), the joint-angle
    cosines ``cb``, ``cp`` (N,6) and the Jacobian (N,6,6) rows ``[u, (R p_k) x u / char_length]``
    for platform poses X (N,6) mm/rad.  Component-wise on (N,) arrays: no (N,6,3) temporaries."""
    r = P.rot_elems(X[:, 3:])
    N = X.shape[0]
    L = np.empty((N, 6))
    cb = np.empty((N, 6))
    cp = np.empty((N, 6))
    Jt = np.empty((6, 6, N))                  # strut, column, pose: contiguous writes
    cl = 1.0 / hx.char_length_mm
    for k in range(6):
        px, py, pz = hx.plat[k]
        ax, ay, az = hx.plat_axes[k]
        rx = r[0] * px + r[1] * py + r[2] * pz
        ry = r[3] * px + r[4] * py + r[5] * pz
        rz = r[6] * px + r[7] * py + r[8] * pz
        sx = X[:, 0] + rx - hx.base[k, 0]
        sy = X[:, 1] + ry - hx.base[k, 1]
        sz = X[:, 2] + rz - hx.base[k, 2]
        lk = np.sqrt(sx * sx + sy * sy + sz * sz)
        L[:, k] = lk
        inv = 1.0 / lk
        ux, uy, uz = sx * inv, sy * inv, sz * inv
        bx, by, bz = hx.base_axes[k]
        cb[:, k] = ux * bx + uy * by + uz * bz
        # platform joint: -u . (R a_k)
        cp[:, k] = -(ux * (r[0] * ax + r[1] * ay + r[2] * az) + uy * (r[3] * ax + r[4] * ay + r[5] * az)
                     + uz * (r[6] * ax + r[7] * ay + r[8] * az))
        Jk = Jt[k]
        Jk[0] = ux
        Jk[1] = uy
        Jk[2] = uz
        Jk[3] = (ry * uz - rz * uy) * cl
        Jk[4] = (rz * ux - rx * uz) * cl
        Jk[5] = (rx * uy - ry * ux) * cl
    np.clip(cb, -1.0, 1.0, out=cb)
    np.clip(cp, -1.0, 1.0, out=cp)
    return L, cb, cp, Jt.transpose(2, 0, 1)


def condition_numbers(J: np.ndarray, limit: float) -> np.ndarray:
    """Spectral condition numbers of the square matrices J (N,n,n) where they may exceed ``limit``.

    With singular values s_1 >= .. >= s_n, ``|det J| = prod s_i``, ``s_1^2 <= F^2 = ||J||_F^2`` and
    (AM-GM) ``prod_{i<n} s_i^2 <= (F^2 / (n-1))^(n-1)``, so
    ``cond = s_1 / s_n = s_1 prod_{i<n} s_i / |det J| <= F^n / ((n-1)^((n-1)/2) |det J|)``.
    Where this bound is at most ``limit`` it is returned (the pose passes either way); elsewhere the
    exact value from the eigenvalues of ``J^T J`` (inf where singular).
    """
    n = J.shape[-1]
    F2 = np.einsum("nij,nij->n", J, J)
    with np.errstate(all="ignore"):
        det = np.abs(np.linalg.det(J))
        out = F2 ** (0.5 * n) / ((n - 1) ** (0.5 * (n - 1)) * det)
    todo = np.nonzero(~(out <= limit))[0]           # NaN / inf included
    if todo.size:
        Jt = J[todo]
        with np.errstate(all="ignore"):
            ev = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", Jt, Jt))      # singular values squared
            c = np.sqrt(ev[:, -1] / np.maximum(ev[:, 0], 1e-300))
        out[todo] = np.where(ev[:, 0] > 0, c, np.inf)
    return out


def _check_limits(path: P.Path, hx: Hexapod, cfg, sg, pidx, Xg, lmarg, amarg):
    """Strut lengths and joint angles on the grid with the limits shrunk by the sampling bounds.

    Returns (min joint margin deg, min length margin mm); raises PlanError at the first violation.
    """
    L, cb, cp, J = _strut_geometry(Xg, hx)
    ab = np.arccos(cb)
    ap = np.arccos(cp)
    lm = lmarg[pidx][:, None]
    am = amarg[pidx][:, None]
    lo = L - lm - hx.min_length[None]
    hi = hx.max_length[None] - (L + lm)
    amax = hx.max_angle_rad[None]
    jb = amax - (ab + am)
    jp = amax - (ap + am)
    # singularity (checked at the samples; a cheap upper bound, exact values only where it is inconclusive)
    cond = condition_numbers(J, hx.max_condition)
    bad = (np.any(lo < 0, axis=1) | np.any(hi < 0, axis=1) | np.any(jb < 0, axis=1) | np.any(jp < 0, axis=1)
           | ~np.isfinite(cond) | (cond > hx.max_condition))
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        m = int(pidx[k])
        line = int(path.line[m])
        tip = path.tip(np.array([m]), np.array([sg[k]]))[0]
        where = (f"at tool tip [{tip[0]:.3f}, {tip[1]:.3f}, {tip[2]:.3f}] mm, "
                 f"[{math.degrees(tip[3]):.3f}, {math.degrees(tip[4]):.3f}, {math.degrees(tip[5]):.3f}] deg")
        for i in range(6):
            if lo[k, i] < 0:
                raise PlanError(f"strut {i + 1} length {L[k, i]:.4f} mm (+-{lm[k, 0]:.4g} mm sampling bound) "
                                f"below min_length_mm {hx.min_length[i]:g} {where}", line=line,
                                limit=f"strut {i + 1} min_length_mm")
            if hi[k, i] < 0:
                raise PlanError(f"strut {i + 1} length {L[k, i]:.4f} mm (+-{lm[k, 0]:.4g} mm sampling bound) "
                                f"above max_length_mm {hx.max_length[i]:g} {where}", line=line,
                                limit=f"strut {i + 1} max_length_mm")
        for i in range(6):
            lim = math.degrees(hx.max_angle_rad[i])
            if jb[k, i] < 0:
                raise PlanError(f"base joint {i + 1} angle {math.degrees(ab[k, i]):.4f} deg "
                                f"(+{math.degrees(am[k, 0]):.4g} deg sampling bound) over max_angle_deg {lim:g} "
                                f"{where}", line=line, limit=f"base joint {i + 1} max_angle_deg")
            if jp[k, i] < 0:
                raise PlanError(f"platform joint {i + 1} angle {math.degrees(ap[k, i]):.4f} deg "
                                f"(+{math.degrees(am[k, 0]):.4g} deg sampling bound) over max_angle_deg {lim:g} "
                                f"{where}", line=line, limit=f"platform joint {i + 1} max_angle_deg")
        raise PlanError(f"near-singular pose: Jacobian condition {cond[k]:.4g} over max_condition "
                        f"{hx.max_condition:g} {where}", line=line, limit="max_condition")
    jm = float(np.degrees(min(jb.min(), jp.min()))) if jb.size else math.nan
    lmm = float(min(lo.min(), hi.min())) if lo.size else math.nan
    return jm, lmm
