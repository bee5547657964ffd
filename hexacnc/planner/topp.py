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

import math

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


def isqrt_safe(x: float) -> float:
    return math.sqrt(x) if x > 0 else 0.0


class IncrementalTopp:
    """The forward-backward pass, redone only where a speed limit changed.

    Lowering ``xlim`` on ``[lo, hi]`` changes the controllable bound K at and upstream of the
    change until it meets its old value, and the speeds x from there downstream until they meet
    theirs; everything else is kept.  Results are identical to a full :func:`forward_backward`.
    """

    def __init__(self, h: np.ndarray, c: np.ndarray, e: np.ndarray, d: np.ndarray):
        self.hl = h.tolist()
        self.cl = c.tolist()
        self.el = e.tolist()
        self.dl = d.tolist()
        self.K = None
        self.x = None
        self.xl = None

    def solve(self, xlim: np.ndarray, lo: int = 0, hi: int | None = None) -> np.ndarray:
        xl_new = np.maximum(xlim, 0.0).tolist()
        N = len(xl_new)
        if self.K is None or hi is None:
            self.xl = xl_new
            self.K = [0.0] * N
            self.x = [0.0] * N
            self._backward(N - 1, 0, full=True)
            self._forward(0, N - 1, full=True)
            return np.array(self.x)
        hi = min(N - 1, hi)
        lo = max(0, lo)
        self.xl[lo:hi + 1] = xl_new[lo:hi + 1]
        kfirst, klast = self._backward(hi, lo, full=False)
        if kfirst is not None:
            self._forward(max(0, kfirst - 1), klast, full=False)
        return np.array(self.x)

    def _backward(self, start: int, lo: int, full: bool):
        K, xl, hl, cl, dl = self.K, self.xl, self.hl, self.cl, self.dl
        N = len(K)
        kfirst = klast = None
        if start == N - 1:
            if K[-1] != xl[-1] or full:
                if K[-1] != xl[-1]:
                    kfirst = klast = N - 1
                K[-1] = xl[-1]
            start = N - 2
        for k in range(start, -1, -1):
            xk = xl[k]
            nxt = K[k + 1]
            hk = hl[k]
            if hk <= 0.0:
                xk = xk if xk < nxt else nxt
            else:
                h2 = 2.0 * hk
                ck = cl[k]
                dk = dl[k]
                for i in range(6):
                    coef = 1.0 + h2 * dk[i]
                    if coef > 1e-12:
                        v = (nxt - h2 * ck[i]) / coef
                        if v < xk:
                            xk = v
                if xk < 0.0:
                    xk = 0.0
            if xk != K[k]:
                K[k] = xk
                kfirst = k
                if klast is None:
                    klast = k
            elif not full and k < lo:
                break
        return kfirst, klast

    def _forward(self, start: int, klast: int, full: bool) -> None:
        K, x, hl, el, dl, xl = self.K, self.x, self.hl, self.el, self.dl, self.xl
        N = len(K)
        if start == 0:
            x[0] = K[0] if K[0] < xl[0] else xl[0]
        for k in range(start, N - 1):
            xk = x[k]
            hk = hl[k]
            kn = K[k + 1]
            if hk <= 0.0:
                xn = xk if xk < kn else kn
            else:
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
            if not full and k + 1 > klast and xn == x[k + 1]:
                break
            x[k + 1] = xn

    def solve_ranges(self, xlim: np.ndarray, ranges) -> np.ndarray:
        """Like :meth:`solve` for several disjoint changed ranges ``[(lo, hi), ...]``."""
        if self.K is None:
            return self.solve(xlim)
        xl_new = np.maximum(xlim, 0.0)
        N = len(self.K)
        rs = sorted((max(0, int(a)), min(N - 1, int(b))) for a, b in ranges if b >= a)
        for a, b in rs:
            self.xl[a:b + 1] = xl_new[a:b + 1].tolist()
        changed = []
        for a, b in reversed(rs):
            kf, kl = self._backward(b, a, full=False)
            if kf is not None:
                changed.append((kf, kl))
        reach = -1
        for kf, kl in sorted(changed):
            if kl <= reach:
                continue
            reach = self._forward_to(max(0, kf - 1), kl)
        return np.array(self.x)

    def _forward_to(self, start: int, klast: int) -> int:
        """Forward pass from ``start`` until past ``klast`` and unchanged; returns the last index written."""
        K, x, hl, el, dl, xl = self.K, self.x, self.hl, self.el, self.dl, self.xl
        N = len(K)
        if start == 0:
            x[0] = K[0] if K[0] < xl[0] else xl[0]
        k = start
        for k in range(start, N - 1):
            xk = x[k]
            hk = hl[k]
            kn = K[k + 1]
            if hk <= 0.0:
                xn = xk if xk < kn else kn
            else:
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
            if k + 1 > klast and xn == x[k + 1]:
                return k
            x[k + 1] = xn
        return N - 1
