"""The forward-backward TOPP pass of :mod:`hexacnc.planner.topp`, solved by wavefronts in numpy.

Both passes are chains: the backward pass sets ``K[k] = g_k(K[k+1])`` from ``K[N-1] = xlim[N-1]``, the
forward pass ``x[k+1] = f_k(x[k])`` from ``x[0] = min(K[0], xlim[0])``; each chain has exactly one
solution.  Instead of walking it point by point in Python, every equation is evaluated at once
(numpy, the same floating-point operations as :func:`~hexacnc.planner.topp.forward_backward`), then
only the equations whose input changed are evaluated again, until nothing changes.  When that stops
every equation holds, so the result is the chain's solution, bit for bit the sequential one.  The
number of rounds is the longest run of points whose value is set by its neighbour (acceleration-
bound stretches: ~100-200 on the corpus), each round a few vector operations on that front.

After :meth:`WavefrontTopp.solve`, ``solve_ranges`` starts the fronts from the changed speed
limits only; the result equals a full :func:`~hexacnc.planner.topp.forward_backward` (tested).
"""
from __future__ import annotations

import numpy as np

from .topp import _BIG


def accel_coefficients(Lp: np.ndarray, Lpp: np.ndarray, amax: np.ndarray):
    """:func:`hexacnc.planner.topp.accel_coefficients`, bit for bit, strut by strut and pair by pair
    on (N,) columns (no (N,6,6) temporaries: ~100 MB less memory traffic on 3D_Chips).

    Lp, Lpp: (N,6); amax: (6,).  Returns c, e, d (N,6) (``c_i + d_i x <= u <= e_i + d_i x``) and
    x_mvc (N,), the largest x for which every pair of those bounds still overlaps.
    """
    N = Lp.shape[0]
    e = np.empty((N, 6))
    d = np.empty((N, 6))
    x_mvc = np.full(N, _BIG)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(6):
            l1 = Lp[:, i]
            l2 = Lpp[:, i]
            a = np.abs(l1)
            small = a < 1e-12
            inv = np.where(small, 0.0, 1.0 / np.where(small, 1.0, l1))
            d[:, i] = np.where(small, 0.0, -l2 * inv)
            e[:, i] = np.where(small, _BIG, amax[i] / np.where(small, 1.0, a))
            # a strut that does not move along the path: |L''| x <= A
            np.minimum(x_mvc, np.where(small & (np.abs(l2) > 1e-15), amax[i] / np.abs(l2), _BIG), out=x_mvc)
        c = -e
        dc = [d[:, i].copy() for i in range(6)]
        ec = [e[:, i].copy() for i in range(6)]
        cc = [c[:, i].copy() for i in range(6)]
        for i in range(6):
            for j in range(6):
                if i == j:
                    continue
                # lower bound of i below upper bound of j: (d_i - d_j) x <= e_j - c_i
                den = dc[i] - dc[j]
                ok = den > 1e-15
                np.minimum(x_mvc, np.where(ok, (ec[j] - cc[i]) / np.where(ok, den, 1.0), _BIG), out=x_mvc)
    return c, e, d, x_mvc


class WavefrontTopp:
    """Forward-backward pass on x = s_dot^2 (see :mod:`hexacnc.planner.topp`), redone where limits change.

    h (N-1,) grid spacing (0 at duplicated junction points); c, e, d (N,6) the acceleration bounds
    ``c_i + d_i x <= u <= e_i + d_i x`` from :func:`~hexacnc.planner.topp.accel_coefficients`.
    """

    def __init__(self, h: np.ndarray, c: np.ndarray, e: np.ndarray, d: np.ndarray):
        h = np.asarray(h, dtype=float)
        self.N = h.shape[0] + 1
        self.pos = h > 0.0
        h2 = 2.0 * h
        self.h2 = h2
        # backward: (nxt - 2h c_i) / (1 + 2h d_i) where 1 + 2h d_i > 1e-12 (else no bound);
        # at h = 0 this is nxt itself: K = min(xlim, nxt), as in the sequential pass
        self.bnum = h2[:, None] * c[:-1]
        coef = 1.0 + h2[:, None] * d[:-1]
        self.bok = bok = coef > 1e-12
        # no bound where 1 + 2h d_i <= 1e-12: (nxt + inf) / 1 = inf, with no mask to gather in each round
        self.bnum[~bok] = -np.inf
        self.bden = np.where(bok, coef, 1.0)
        self.e = np.ascontiguousarray(e[:-1])
        self.d = np.ascontiguousarray(d[:-1])
        self.K = None
        self.x = None
        self.xl = None

    # -- one round of each chain on the index set k (equations for K[k] / x[k+1]) -------------------
    def _g(self, k: np.ndarray) -> np.ndarray:
        nxt = self.K[k + 1]
        with np.errstate(invalid="ignore", over="ignore"):
            v = (nxt[:, None] - self.bnum[k]) / self.bden[k]
        # at h = 0 the result min(xl, nxt) is >= 0 already: the clamp is a no-op there
        return np.maximum(np.minimum(self.xl[k], v.min(axis=1)), 0.0)

    def _f(self, k: np.ndarray) -> np.ndarray:
        xk = self.x[k]
        kn = self.K[k + 1]
        h2 = self.h2[k]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            u = (kn - xk) / h2
            u = np.minimum(u, (self.e[k] + self.d[k] * xk[:, None]).min(axis=1))
            xn = np.minimum(np.maximum(xk + h2 * u, 0.0), kn)
        return np.where(self.pos[k], xn, np.minimum(xk, kn))

    def _backward(self, k: np.ndarray) -> np.ndarray:
        """Settle K from the equations k; returns the indices whose K changed."""
        changed = []
        K = self.K
        while k.size:
            new = self._g(k)
            ch = new != K[k]
            k = k[ch]
            K[k] = new[ch]
            changed.append(k)
            k = k - 1
            k = k[k >= 0]
        return np.concatenate(changed) if changed else np.zeros(0, dtype=np.int64)

    def _forward(self, k: np.ndarray) -> None:
        x = self.x
        last = self.N - 2
        while k.size:
            new = self._f(k)
            ch = new != x[k + 1]
            k = k[ch]
            x[k + 1] = new[ch]
            k = k + 1
            k = k[k <= last]

    # -- public ---------------------------------------------------------------------------------------
    def solve(self, xlim: np.ndarray) -> np.ndarray:
        """x (N,) for the limits xlim (N,), from scratch."""
        N = self.N
        self.xl = np.maximum(np.asarray(xlim, dtype=float), 0.0)
        self.K = self.xl.copy()
        if N >= 2:
            self._backward(np.arange(N - 1))
        self.x = self.K.copy()
        self.x[0] = min(self.K[0], self.xl[0])
        if N >= 2:
            self._forward(np.arange(N - 1))
        return self.x.copy()

    def set_bound(self, col: int, idx: np.ndarray, bound: np.ndarray) -> None:
        """Set row ``col`` of the acceleration bounds, one with ``d = 0``, to ``-bound <= u <= bound`` at the
        grid points idx; follow with :meth:`solve_ranges` over them with ``bounds_changed=True``."""
        idx = idx[idx < self.N - 1]
        self.bnum[idx, col] = self.h2[idx] * -bound[idx]        # d = 0: 1 + 2h d > 1e-12, a bound
        self.e[idx, col] = bound[idx]

    def solve_ranges(self, xlim: np.ndarray, ranges, bounds_changed: bool = False) -> np.ndarray:
        """x after the limits changed on the grid ranges ``[(lo, hi), ...]`` (inclusive); the same
        result as :meth:`solve` on the new limits.  ``bounds_changed``: the acceleration bounds changed
        there too (:meth:`set_bound`), so the forward equations there are evaluated again as well."""
        if self.K is None:
            return self.solve(xlim)
        N = self.N
        xl_new = np.maximum(np.asarray(xlim, dtype=float), 0.0)
        rs = [(max(0, int(a)), min(N - 1, int(b))) for a, b in ranges if b >= a]
        if not rs:
            return self.x.copy()
        # the union of the ranges, sorted (a difference array: no sort of possibly overlapping ranges)
        mark = np.zeros(N + 1, dtype=np.int64)
        ra = np.array(rs, dtype=np.int64)
        np.add.at(mark, ra[:, 0], 1)
        np.add.at(mark, ra[:, 1] + 1, -1)
        idx = np.nonzero(np.cumsum(mark[:-1]) > 0)[0]
        self.xl[idx] = xl_new[idx]
        kch = []
        if idx[-1] == N - 1 and self.K[-1] != self.xl[-1]:
            self.K[-1] = self.xl[-1]
            kch.append(np.array([N - 1]))
        kch.append(self._backward(idx[idx < N - 1]))
        kch = np.concatenate(kch)
        front = [kch[kch >= 1] - 1]                     # equations x[k+1] = f(x[k], K[k+1])
        if bounds_changed:
            front.append(idx)
        x0 = min(self.K[0], self.xl[0])
        if x0 != self.x[0]:
            self.x[0] = x0
            front.append(np.array([0]))
        k = np.unique(np.concatenate(front))
        if N >= 2 and k.size:
            self._forward(k[k <= N - 2])
        return self.x.copy()
