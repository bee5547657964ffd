"""Time-optimal path parameterisation on a grid (forward-backward pass on x = s_dot^2).

Constraints at grid point k (struts i = 1..6, ``a = L'_i``, ``b = L''_i``):

* ``x_k <= xlim_k`` (feed, strut velocity, angular velocity, curvature jerk, MVC),
* ``|b x + a u| <= A_i`` with ``u = s_ddot`` constant on ``[s_k, s_k+1]`` and
  ``x_k+1 = x_k + 2 h u`` (TOPP-RA's zero-order scheme).

Backward pass: the largest ``x_k`` from which the end (and every stop) can still
be reached; forward pass: the greatest acceleration that stays inside it.
Pure Python on floats (sequential by nature); constant factors precomputed.
"""
from __future__ import annotations

import numpy as np

_BIG = 1e300


def accel_coefficients(Lp: np.ndarray, Lpp: np.ndarray, amax: np.ndarray):
    """Linear bounds ``c_i + d x <= u <= e_i + d x`` per point and strut, plus the x bound they imply.

    Lp, Lpp: (N,6); amax: (6,).  Returns c, e, d (N,6) and x_mvc (N,).
    """
    a = np.abs(Lp)
    small = a < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(small, 0.0, 1.0 / np.where(small, 1.0, Lp))
        d = -Lpp * inv
        e = np.where(small, _BIG, amax[None, :] / np.where(small, 1.0, a))
        c = -e
        d = np.where(small, 0.0, d)
        # struts that do not move along the path: |b| x <= A
        xs = np.where(small & (np.abs(Lpp) > 1e-15), amax[None, :] / np.abs(Lpp), _BIG)
        x_mvc = np.min(xs, axis=1)
        # lo_i(x) <= hi_j(x):  (d_i - d_j) x <= e_j - c_i
        num = e[:, None, :] - c[:, :, None]
        den = d[:, :, None] - d[:, None, :]
        r = np.where(den > 1e-15, num / np.where(den > 1e-15, den, 1.0), _BIG)
    x_mvc = np.minimum(x_mvc, r.reshape(r.shape[0], -1).min(axis=1))
    return c, e, d, x_mvc


def forward_backward(h, xlim: np.ndarray, c, e, d) -> np.ndarray:
    """x = s_dot^2 at the N grid points; h (N-1,) spacing (0 at duplicated junction points).

    ``xlim[0]`` and ``xlim[-1]`` should be 0 (start and end at rest); stops are
    points with ``xlim = 0``.  h, c, e, d may be given as lists (``.tolist()``,
    to convert them once when the pass repeats).
    """
    N = xlim.shape[0]
    cl = c if isinstance(c, list) else c.tolist()
    el = e if isinstance(e, list) else e.tolist()
    dl = d if isinstance(d, list) else d.tolist()
    hl = h if isinstance(h, list) else h.tolist()
    xl = np.maximum(xlim, 0.0).tolist()
    K = [0.0] * N
    K[-1] = xl[-1]
    for k in range(N - 2, -1, -1):
        xk = xl[k]
        nxt = K[k + 1]
        hk = hl[k]
        if hk <= 0.0:
            K[k] = xk if xk < nxt else nxt
            continue
        h2 = 2.0 * hk
        ck = cl[k]
        dk = dl[k]
        for i in range(6):
            # x + 2h (c_i + d_i x) <= nxt
            coef = 1.0 + h2 * dk[i]
            rhs = nxt - h2 * ck[i]
            if coef > 1e-12:
                v = rhs / coef
                if v < xk:
                    xk = v
            elif rhs < 0.0 and coef < -1e-12:
                pass  # lower bound on x only; ignored (x >= 0 handles it conservatively below)
        if xk < 0.0:
            xk = 0.0
        K[k] = xk
    x = [0.0] * N
    x[0] = min(K[0], xl[0])
    for k in range(N - 1):
        xk = x[k]
        hk = hl[k]
        kn = K[k + 1]
        if hk <= 0.0:
            x[k + 1] = xk if xk < kn else kn
            continue
        ek = el[k]
        dk = dl[k]
        u = (kn - xk) / (2.0 * hk)
        for i in range(6):
            v = ek[i] + dk[i] * xk
            if v < u:
                u = v
        xn = xk + 2.0 * hk * u
        if xn < 0.0:
            xn = 0.0
        elif xn > kn:
            xn = kn
        x[k + 1] = xn
    return np.array(x)


def interval_times(h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Duration of each interval (constant s_ddot): ``2 h / (sqrt(x_k) + sqrt(x_k+1))``."""
    v = np.sqrt(np.maximum(x, 0.0))
    vs = v[:-1] + v[1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = np.where(h > 0, 2.0 * h / vs, 0.0)
    if not np.all(np.isfinite(dt)):
        k = int(np.nonzero(~np.isfinite(dt))[0][0])
        raise FloatingPointError(f"zero speed over a path interval at grid point {k}")
    return dt
