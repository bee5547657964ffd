"""Measurement of the setpoint table: strut velocity, acceleration and jerk utilisation per sample (step 5
of the method in :mod:`hexacnc.planner.plan`).  Interval bounds everywhere; where a bound exceeds a
threshold, the model (interpolated grid derivatives) or the exact inverse kinematics at the cycle period.
"""
from __future__ import annotations

import numpy as np

from .profile import ETA

#: s step of the central differences (mm or deg)
FD_STEP = 0.01
#: samples per chunk of the exact measurement (bounds its memory)
EXACT_CHUNK = 50_000
#: model utilisations (v, a, j) above which a model pass measures the sample exactly: the plan's
#: violation thresholds (velocity 0.9995, acceleration and jerk ETA), 1e-9 lower
CONFIRM = (0.9995 * (1 - 1e-9), ETA * (1 - 1e-9), ETA * (1 - 1e-9))


def _path_rates(s_f: np.ndarray, dt: float):
    """s_dot, s_ddot, s_dddot of the table by central differences (zero at the ends)."""
    N = s_f.shape[0]
    sd = np.zeros(N)
    sdd = np.zeros(N)
    sddd = np.zeros(N)
    if N >= 4:
        sd[1:-1] = (s_f[2:] - s_f[:-2]) / (2 * dt)
        sdd[1:-1] = (s_f[2:] - 2 * s_f[1:-1] + s_f[:-2]) / (dt * dt)
        sddd[1:-2] = (s_f[3:] - 3 * s_f[2:-1] + 3 * s_f[1:-2] - s_f[:-3]) / dt ** 3
        sddd[2:-1] = np.where(np.abs(sddd[1:-2]) > np.abs(sddd[2:-1]), sddd[1:-2], sddd[2:-1])
    return sd, sdd, sddd


class _Bounds:
    """Per grid interval maxima of |L'|, |L''|, |L'''| over the struts, scaled by each limit.

    Over a sample in interval g the model utilisations are bounded by
    ``uv <= Bv |s_dot|``, ``ua <= Ba2 s_dot^2 + Ba1 |s_ddot|``,
    ``uj <= Bj3 |s_dot|^3 + Bj2 |s_dot s_ddot| + Bj1 |s_dddot|`` (triangle inequality; the model
    interpolates linearly between the interval's end points, so their maximum bounds it).
    """

    def __init__(self, Lp, Lpp, Lppp, vmax, amax, jmax):
        def both(a, lim):
            m = _rowmax(a, lim)
            out = np.maximum(m[:-1], m[1:])
            return np.concatenate([out, out[-1:]])
        aLp, aLpp, aLppp = np.abs(Lp), np.abs(Lpp), np.abs(Lppp)
        #: the grid derivatives and their steps to the next point (for the interpolated model)
        self.L = (Lp, Lpp, Lppp)
        self.dL = tuple(np.diff(a, axis=0) for a in self.L)
        self.v = both(aLp, vmax)
        self.a1 = both(aLp, amax)
        self.a2 = both(aLpp, amax)
        self.j1 = both(aLp, jmax)
        self.j2 = 3.0 * both(aLpp, jmax)
        self.j3 = both(aLppp, jmax)

    def at(self, g, sd, sdd, sddd, extras: bool = True):
        """Bounds per sample; ``extras=False`` skips the governor ratios (va, ajr, vjr: returned as None)."""
        asd, asdd, asddd = np.abs(sd), np.abs(sdd), np.abs(sddd)
        sd2 = asd * asd
        bv, ba1, ba2, bj1, bj2, bj3 = (a[g] for a in (self.v, self.a1, self.a2, self.j1, self.j2, self.j3))
        uv = bv * asd
        ua = ba2 * sd2 + ba1 * asdd
        uj = bj3 * sd2 * asd + bj2 * asd * asdd + bj1 * asddd
        if not extras:
            return uv, ua, uj, None, None, None
        va = ba1 * asd
        ajr = (bj2 / 3.0) * sd2 + bj1 * asdd
        vjr = bj1 * asd
        return uv, ua, uj, va, ajr, vjr


def _rowmax(M: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """``(M / lim).max(axis=1)`` for M (n,6), column by column (a 6-wide row reduction is slow)."""
    T = M / lim
    out = T[:, 0].copy()
    for i in range(1, T.shape[1]):
        np.maximum(out, T[:, i], out=out)
    return out


def _near_junctions(sg: np.ndarray, s_f: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Table samples within 4 cycles of a piece junction while moving (curvature steps are not in the
    interval bounds): indices, may repeat."""
    N = s_f.shape[0]
    jn = np.nonzero(np.diff(sg) == 0)[0]
    if jn.size == 0 or N < 2:
        return np.zeros(0, dtype=np.int64)
    gi = np.searchsorted(s_f, sg[jn])
    near = (gi[:, None] + np.arange(-4, 5)[None, :]).ravel()
    near = near[(near >= 0) & (near < N)]
    return near[np.abs(sd[near]) > 0]


def _on_short_pieces(path, s_f: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Moving table samples on pieces shorter than the central differences' stencil (4 FD_STEP): the
    grid derivatives do not resolve such a piece (a tiny blend's polynomial evaluated beyond its
    ends), so its interval bounds need not bound it: indices, may repeat."""
    short = np.nonzero(path.slen < 4 * FD_STEP)[0]
    if short.size == 0 or s_f.shape[0] < 2:
        return np.zeros(0, dtype=np.int64)
    a = np.searchsorted(s_f, path.s0[short], side="left")
    b = np.searchsorted(s_f, path.s0[short] + path.slen[short], side="right")
    cnt = np.maximum(b - a, 0)
    idx = np.repeat(a, cnt) + (np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    return idx[np.abs(sd[idx]) > 0]


def _screen_intervals(sg, s_f, sd, sdd, sddd, bounds: "_Bounds", thr):
    """Samples whose interval bound exceeds a threshold of ``thr`` = (v, a, j), found grid interval by
    grid interval: the bound of interval g with the largest |s_dot|, |s_ddot|, |s_dddot| of its
    samples (same arithmetic, each factor at least the sample's: at least every sample's bound)
    selects the intervals whose samples are then bounded one by one.

    Returns (sample indices, their grid intervals, their bounds uv, ua, uj): exactly the samples
    with a per-sample bound above ``thr``.
    """
    N = s_f.shape[0]
    start = np.searchsorted(s_f, sg[:-1], side="left")          # first sample of each interval
    end = np.empty_like(start)
    end[:-1] = start[1:]
    end[-1] = N                                                  # the end point belongs to the last one
    occ = np.nonzero(end > start)[0]
    asd, asdd, asddd = np.abs(sd), np.abs(sdd), np.abs(sddd)
    m1, m2, m3 = (np.maximum.reduceat(a, start[occ]) for a in (asd, asdd, asddd))
    uv, ua, uj, _, _, _ = bounds.at(occ, m1, m2, m3, extras=False)
    flag = occ[(uv > thr[0]) | (ua > thr[1]) | (uj > thr[2])]
    if flag.size == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0), np.zeros(0), np.zeros(0)
    cnt = end[flag] - start[flag]
    g = np.repeat(flag, cnt)
    idx = np.arange(g.shape[0]) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(start[flag], cnt)
    uv, ua, uj, _, _, _ = bounds.at(g, sd[idx], sdd[idx], sddd[idx], extras=False)
    keep = (uv > thr[0]) | (ua > thr[1]) | (uj > thr[2])
    return idx[keep], g[keep], uv[keep], ua[keep], uj[keep]


def _measure_fast(path, hx, sg, Lp, Lpp, Lppp, bounds: "_Bounds", s_f, dt, vmax, amax, jmax, exact: bool,
                  screen):
    """Utilisation per sample: interval bounds everywhere; where a bound exceeds ``screen`` the model
    (``exact=False``: interpolated grid derivatives) or the exact inverse kinematics (``exact=True``:
    finite differences at dt, also at every moving sample within 4 cycles of a piece junction, whose
    stencil spans the curvature step, and on every piece shorter than 4 FD_STEP, which the grid
    derivatives do not resolve) replaces it.

    ``screen``: one number, or (velocity, acceleration, jerk) thresholds.
    Returns uv, ua, uj, va, ajr, vjr (per sample; va, ajr, vjr None unless exact) and the number of
    samples evaluated in detail.
    """
    N = s_f.shape[0]
    sd, sdd, sddd = _path_rates(s_f, dt)
    if not exact:
        # only samples above the thresholds matter (the others cannot violate): the rest stay 0
        idx, gg, *b = _screen_intervals(sg, s_f, sd, sdd, sddd, bounds, screen)
        res = [np.zeros(N) for _ in range(3)] + [None] * 3
        for r, v in zip(res, b):
            r[idx] = v
        if idx.size == 0:
            return (*res, 0)
        s = s_f[idx]
        # a sample that arrives at a stop lies on the next piece's first grid point, but its rates come
        # from the piece it arrives on: model it at that piece's end point
        arrive = ((gg >= 2) & (s == sg[gg]) & (sg[np.maximum(gg - 1, 0)] == s)
                  & (s_f[np.maximum(idx - 1, 0)] < s))
        gg = np.where(arrive, gg - 2, gg)
        hh = sg[gg + 1] - sg[gg]
        w = np.where(hh > 0, (s - sg[gg]) / np.where(hh > 0, hh, 1.0), 0.0)[:, None]
        L0, dL = bounds.L, bounds.dL
        l1 = L0[0][gg] + dL[0][gg] * w
        l2 = L0[1][gg] + dL[1][gg] * w
        l3 = L0[2][gg] + dL[2][gg] * w
        v1, v2, v3 = sd[idx][:, None], sdd[idx][:, None], sddd[idx][:, None]
        V = np.abs(l1 * v1)
        A = np.abs(l2 * (v1 * v1) + l1 * v2)
        Jk = np.abs(l3 * (v1 * v1 * v1) + 3 * l2 * (v1 * v2) + l1 * v3)
        res[0][idx] = _rowmax(V, vmax)
        res[1][idx] = _rowmax(A, amax)
        res[2][idx] = _rowmax(Jk, jmax)
        n_model = idx.size
        # the model only screens: a sample it puts over a threshold is measured exactly before it slows
        # the plan down (the model overestimates on corner blends: 0.975 jerk where the table has 0.74,
        # and the tightening that followed made twelve 0.85 mm moves slower than twelve 0.88 mm ones)
        over = (res[0][idx] > CONFIRM[0]) | (res[1][idx] > CONFIRM[1]) | (res[2][idx] > CONFIRM[2])
        idx = idx[over]
        if idx.size == 0:
            return (*res, n_model)
        for r in res[:3]:
            r[idx] = 0.0
    else:
        g = np.clip(np.searchsorted(sg, s_f, side="right") - 1, 0, sg.shape[0] - 2)
        res = list(bounds.at(g, sd, sdd, sddd, extras=True))      # governor ratios for the final table
        need = (res[0] > screen) | (res[1] > screen) | (res[2] > screen)
        need[_near_junctions(sg, s_f, sd)] = True
        need[_on_short_pieces(path, s_f, sd)] = True
        idx = np.nonzero(need)[0]
        if idx.size == 0:
            return (*res, 0)
        n_model = 0
    # exact: inverse kinematics on the needed samples with the 2 neighbours either side their
    # differences use (velocity k-1..k+1, acceleration k-1..k+1, jerk k-2..k+2)
    mask = np.zeros(N, dtype=bool)
    for o in range(-2, 3):
        mask[np.clip(idx + o, 0, N - 1)] = True
    ext = np.nonzero(mask)[0]
    chunk = EXACT_CHUNK
    for c0 in range(0, ext.size, chunk):
        e0 = max(0, c0 - 4)                             # 4 more either side: whole stencils
        e = ext[e0:c0 + chunk + 4]
        s = s_f[e]
        _, L = path.platform_struts(path.piece_at(s), s, hx.plat, hx.base)
        n = e.shape[0]
        if n < 2:
            continue
        cont = (np.diff(e) == 1)[:, None]               # consecutive samples
        V = np.zeros((n, 6))
        v = np.where(cont, np.abs(np.diff(L, axis=0)) / dt, 0.0)         # between samples k, k+1
        V[1:] = v
        V[:-1] = np.maximum(V[:-1], v)
        A = np.zeros((n, 6))
        J = np.zeros((n, 6))
        if n > 3:
            ok2 = cont[1:] & cont[:-1]
            ok3 = ok2[1:] & cont[2:]
            A[1:-1] = np.where(ok2, np.abs(L[2:] - 2 * L[1:-1] + L[:-2]) / (dt * dt), 0.0)       # at k+1
            jk = np.where(ok3, np.abs(L[3:] - 3 * L[2:-1] + 3 * L[1:-2] - L[:-3]) / dt ** 3, 0.0)  # k+1..k+2
            J[1:-2] = jk
            J[2:-1] = np.maximum(J[2:-1], jk)
        # keep only the needed samples (their whole stencil is present)
        own = np.zeros(n, dtype=bool)
        own[c0 - e0:c0 - e0 + chunk] = True
        keep = np.nonzero(own & np.isin(e, idx, assume_unique=True))[0]
        V, A, J = V[keep], A[keep], J[keep]
        ek = e[keep]
        for arr, M, lim in zip(res, (V, A, J, V, A, V), (vmax, amax, jmax, amax, jmax, jmax)):
            if arr is not None:             # the model pass has no governor ratios
                arr[ek] = _rowmax(M, lim)
    return (*res, n_model + idx.size)
