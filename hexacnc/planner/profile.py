"""Speed profile and jerk filter: the path-acceleration cap, the plateaus at speed peaks, the raw profile s(t)
at the cycle period and its moving average (steps 3-4 of the method in :mod:`hexacnc.planner.plan`; the
spreading of limits over the filter's reach is :mod:`hexacnc.planner.spread`).
"""
from __future__ import annotations

import math

import numpy as np


#: fraction of the acceleration and jerk limits the nominal plan may use
ETA = 0.95
#: share of the jerk limit the acceleration cap leaves to the filter and curvature terms together
RHO_CAP = 1.0
#: bisection steps of the peak caps (level resolution 2^-n of the peak's height above its valleys)
CAP_BISECT = 14
#: halvings of the peak level before the bisection on a hill between two stops (a level 2^-60 of the peak)
CAP_HALVINGS = 60


def _accel_cap(Lp, Lpp, Lppp, x, jmax, w) -> np.ndarray:
    """Path acceleration bound (N,) for the raw profile: a change of the raw path acceleration u by du
    reaches the struts through the moving average of width ``w`` as jerk ``|L'_i| du / w``, on top of
    ``3 |L''_i| s_dot |u| + |L'''_i| s_dot^3``.  With du <= |u| (reversals are kept out of the window)
    their sum stays within ``RHO_CAP ETA j_i`` at speeds up to ``sqrt(x)`` where
    ``|u| <= (RHO_CAP ETA j_i - |L'''_i| s_dot^3) / (|L'_i| / w + 3 |L''_i| s_dot)``, at least 5 % of it."""
    v = np.sqrt(np.maximum(x, 0.0))
    v3 = v * v * v
    v3x = 3.0 * v
    cap = np.full(x.shape[0], 1e12)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for i in range(Lp.shape[1]):                  # column by column: no (N,6) temporaries
            J = RHO_CAP * ETA * float(jmax[i])
            num = np.maximum(J - np.abs(Lppp[:, i]) * v3, 0.05 * J)
            den = np.abs(Lp[:, i]) * (1.0 / w) + np.abs(Lpp[:, i]) * v3x
            np.minimum(cap, np.where(den > 1e-300, num / np.maximum(den, 1e-300), np.inf), out=cap)
    return cap


def _cap_speed(e, d, ecap) -> np.ndarray:
    """Speed limit (N,) at which some strut's lower acceleration bound ``e_i + d_i x`` (columns of e, d)
    falls below ``-ecap`` (N,): ``min_i (e_i + ecap) / |d_i|`` over the struts with ``|d_i| > 1e-15``."""
    xcap = np.full(e.shape[0], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(e.shape[1]):
            ad = np.abs(d[:, i])
            ok = ad > 1e-15
            np.minimum(xcap, np.where(ok, (e[:, i] + ecap) / np.where(ok, ad, 1.0), np.inf), out=xcap)
    return xcap


def _with_accel_cap(c, e, d, ecap):
    """The acceleration bounds with one more row ``-ecap <= u <= ecap`` and the speed limit (N,) at which
    some strut's bound leaves that range (``c_i + d_i x <= ecap`` and ``e_i + d_i x >= -ecap``)."""
    N, m = c.shape
    xcap = _cap_speed(e, d, ecap)
    c7 = np.empty((N, m + 1))
    e7 = np.empty((N, m + 1))
    d7 = np.zeros((N, m + 1))
    c7[:, :m] = c
    c7[:, m] = -ecap
    e7[:, :m] = e
    e7[:, m] = ecap
    d7[:, :m] = d
    return c7, e7, d7, xcap


class RampBounds:
    """The path-acceleration bounds of the TOPP pass per grid interval, ``max_k(c_k + d_k x) <= u <=
    min_k(e_k + d_k x)`` at the interval's first point (where the forward and backward passes evaluate
    them, the acceleration cap among them: :func:`spread_cap`), read from a
    :class:`~hexacnc.planner.toppvec.WavefrontTopp` on the intervals asked for only: the ramps into and
    out of a capped plateau, which end at the cap inside their interval."""

    def __init__(self, topp, off: int = 0):
        self.t, self.off = topp, off

    def shifted(self, a0: int) -> "RampBounds":
        """The same bounds for a grid range starting at point ``a0``."""
        return RampBounds(self.t, self.off + int(a0))

    def up(self, k: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """Largest path acceleration on the intervals k starting at speed^2 x0."""
        t, k = self.t, k + self.off
        with np.errstate(invalid="ignore", over="ignore"):
            u = (t.e[k] + t.d[k] * x0[:, None]).min(axis=1)
        return u

    def table(self, x: np.ndarray, idx: np.ndarray) -> tuple:
        """For the bisection of the peak caps, on the intervals idx of the range (x: its speeds^2; the
        other entries are left unset): the largest acceleration from the first point, and the
        deceleration bounds' rows C + D x (a decel bound at any level: ``-max(C + D L2)``)."""
        t, n = self.t, x.shape[0] - 1
        k = idx + self.off
        ur = np.empty(n)
        ur[idx] = self.up(idx, x[idx])
        C = np.empty((n, t.d.shape[1]))
        D = np.empty((n, t.d.shape[1]))
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            C[idx] = np.where(t.bok[k], t.bnum[k] / t.h2[k][:, None], -np.inf)
        D[idx] = t.d[k]
        return ur, C, D

    def down(self, k: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """Largest path deceleration (positive) on the intervals k (h > 0) starting at speed^2 x0."""
        t, k = self.t, k + self.off
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            lo = t.bnum[k] / t.h2[k][:, None] + t.d[k] * x0[:, None]
            dec = -np.where(t.bok[k], lo, -np.inf).max(axis=1)
        return dec


def _ramp_times(h, xa, xb, ur, uf) -> np.ndarray:
    """Durations of intervals of length h from speed^2 xa to xb: a ramp at ``ur`` (rising, > 0) then the
    end speed, or the start speed then a ramp at ``uf`` (falling, > 0), else constant acceleration (the
    ramp is never slower than that)."""
    va = np.sqrt(np.maximum(xa, 0.0))
    vb = np.sqrt(np.maximum(xb, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(h > 0, 2.0 * h / (va + vb), 0.0)
        lin = np.abs(xb - xa) / (2.0 * np.where(h > 0, h, 1.0))
        r = (ur > 0) & (xb > xa) & (h > 0)
        if r.any():
            u = np.maximum(ur[r], lin[r])
            t[r] = (vb[r] - va[r]) / u + (h[r] - (xb[r] - xa[r]) / (2 * u)) / vb[r]
        f = (uf > 0) & (xa > xb) & (h > 0)
        if f.any():
            u = np.maximum(uf[f], lin[f])
            t[f] = (h[f] - (xa[f] - xb[f]) / (2 * u)) / va[f] + (va[f] - vb[f]) / u
    return t


def ramp_kinks(h, x, caps, ramps, limit=None):
    """Ramp accelerations (N-1,) into (``ur``) and out of (``uf``) every capped point: a rising interval
    that ends at its end point's cap ramps at the largest acceleration of the TOPP bounds, then holds the
    cap; a falling one that starts at its start point's cap holds it, then ramps down at the largest
    deceleration.  That is ``min(x(s), cap)`` with the plateau's ends inside the intervals, where the
    uncapped ramp crosses the cap (a plateau from grid point to grid point made its ramps, and the
    move's time, shrink as the move grew).  With ``limit`` (the speed limits TOPP solved on, x units) a
    flat top at the limits (a point at its limit whose neighbours are no faster) is entered and left the
    same way where the limit at the interval's other end is at least as high, or that end is a rest: the
    top of a feed-limited move ramped at constant acceleration over its first interval when it sat at the
    limit, but at the largest one when a plateau cap a rounding lower held it, so a longer move planned up
    to 8 cycles shorter."""
    n = h.shape[0]
    ur = np.zeros(n)
    uf = np.zeros(n)
    if ramps is None or caps is None or n == 0:
        return ur, uf
    capped = np.isfinite(caps) & (x >= caps * (1 - 1e-12))
    into, out = capped[1:], capped[:-1]
    if limit is not None:
        at = x >= limit * (1 - 1e-12)
        top = np.zeros(x.shape[0], dtype=bool)           # a flat top: at the limit, the neighbours no higher
        top[1:-1] = at[1:-1] & (x[:-2] <= x[1:-1]) & (x[2:] <= x[1:-1])
        into = into | (top[1:] & ((limit[:-1] >= x[1:]) | (x[:-1] <= 0.0)))
        out = out | (top[:-1] & ((limit[1:] >= x[:-1]) | (x[1:] <= 0.0)))
    pos = h > 0
    k = np.nonzero(pos & (x[1:] > x[:-1]) & into)[0]
    if k.size:
        ur[k] = np.maximum(ramps.up(k, x[k]), 0.0)
    k = np.nonzero(pos & (x[:-1] > x[1:]) & out)[0]
    if k.size:
        uf[k] = np.maximum(ramps.down(k, x[k]), 0.0)
    return ur, uf


def _cap_peaks(h: np.ndarray, x: np.ndarray, w: float, ramps: RampBounds | None = None):
    """Speed caps (x units, per grid point; inf where none) that give every speed peak of the profile x
    a plateau of at least ``w`` seconds, so that a moving average of width ``w`` never holds an
    acceleration reversal; and the hill number of each grid point.

    A hill runs from one local minimum of x to the next; its cap is the highest level L (bisection)
    whose plateau lasts at least w at speed L: with ``ramps`` (:class:`RampBounds`) from where the ramp
    into it at the largest acceleration crosses L to where the ramp out of it at the largest deceleration
    leaves L (inside the grid intervals: :func:`ramp_kinks`, what the raw profile then runs); without,
    from the first grid point at or above L on the way up to the last one on the way down.
    """
    N = x.shape[0]
    if N < 3:
        return np.full(N, np.inf), np.zeros(N, dtype=np.int64)
    v = np.sqrt(np.maximum(x, 0.0))
    S = np.concatenate([[0.0], np.cumsum(h)])
    dv = np.diff(v)
    tol = 1e-12 * (1.0 + np.abs(v[1:]))
    sgn = np.where(dv > tol, 1, np.where(dv < -tol, -1, 0))
    # direction of each interval, flat ones taking the previous direction (leading flats: rising)
    last = np.maximum.accumulate(np.where(sgn != 0, np.arange(N - 1), -1))
    cs = np.where(last >= 0, sgn[np.maximum(last, 0)], 1)
    # a hill starts at each grid point where the direction turns from falling to rising
    start = np.zeros(N, dtype=np.int64)
    start[1:-1] = (cs[:-1] < 0) & (cs[1:] > 0)
    hill = np.cumsum(start)
    H = int(hill[-1]) + 1
    hs = np.concatenate([[0], np.nonzero(start)[0]])            # first grid point of each hill
    he = np.concatenate([hs[1:], [N - 1]])                       # its last (the next hill's first)
    vpk = np.maximum.reduceat(v, hs)
    g = np.arange(N)
    at_pk = v == vpk[hill]
    pk = np.minimum.reduceat(np.where(at_pk, g, N), hs)          # first and last grid point at the peak
    pk_last = np.maximum.reduceat(np.where(at_pk, g, -1), hs)
    scale = float(v.max()) * 1.0001 + 1e-9
    ri = np.nonzero(g <= pk[hill])[0]                            # rising parts, in order
    key_r = hill[ri] + v[ri] / scale                             # non-decreasing
    fi = np.nonzero(g >= pk_last[hill])[0][::-1]                 # falling parts, backwards
    key_f = (H - 1 - hill[fi]) + v[fi] / scale                   # non-decreasing

    def long_enough(hid, L):
        """The plateau at level L (between the crossings of L) lasts at least w at speed L."""
        a = ri[np.minimum(np.searchsorted(key_r, hid + L / scale, side="left"), ri.size - 1)]
        b = fi[np.minimum(np.searchsorted(key_f, (H - 1 - hid) + L / scale, side="left"), fi.size - 1)]
        s_a = S[a]
        s_b = S[b]
        if rt is not None:
            s_a, s_b = _crossings(h, x, rt, a, b, hs[hid], L * L, s_a, s_b)
        return s_b - s_a >= w * L

    rt = None
    cap = np.full(H, np.inf)
    hid = np.arange(H)
    hid = hid[(vpk > 0) & ~long_enough(hid, vpk)]           # the others have their plateau already
    if ramps is not None and hid.size:
        # the ramps only lengthen a plateau: the hills short on the grid's points, measured at the crossings
        cnt = he[hid] - hs[hid]
        st = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        idx = np.repeat(hs[hid] - st, cnt) + np.arange(int(cnt.sum()))
        rt = ramps.table(x, idx[idx < N - 1])
        hid = hid[~long_enough(hid, vpk[hid])]
    if hid.size:
        v_lo = np.minimum(np.maximum(v[hs[hid]], v[he[hid]]), vpk[hid])
        short = ~long_enough(hid, v_lo)
        # a hill too short for a plateau above its higher valley is flattened to that valley (it joins
        # its neighbour); between two stops it gets the highest plateau it can hold
        lo = np.where(short & (v_lo > 0), v_lo, np.where(short, 0.0, v_lo))
        hi = np.where(short & (v_lo > 0), v_lo, vpk[hid])
        # a hill between two stops: halve down to a level that fits first, so that the bisection's
        # resolution is relative to the plateau's level, not to the peak's (a tiny move from rest to
        # rest otherwise gets a plateau level with a coarse error: its duration jitters with its length)
        zero = v_lo <= 0
        if zero.any():
            z = np.nonzero(zero)[0]
            lev = hi[z].copy()
            fit = np.zeros(z.size, dtype=bool)
            for _ in range(CAP_HALVINGS):
                fit |= long_enough(hid[z], lev)
                if fit.all():
                    break
                lev = np.where(fit, lev, 0.5 * lev)
            lo[z] = np.where(fit, lev, 0.0)
            hi[z] = np.where(fit, np.minimum(2.0 * lev, hi[z]), lev)
        for _ in range(CAP_BISECT):
            mid = 0.5 * (lo + hi)
            ok = long_enough(hid, mid)
            lo = np.where(ok, mid, lo)
            hi = np.where(ok, hi, mid)
        cap[hid] = np.where(lo > 0, lo, np.inf)        # no plateau possible on the grid: left to the checks
        # a hill whose plateau takes longer than running it flat at its higher valley is flattened
        # instead (tiny moves between slow corners: a plateau of w each would cost w per move)
        flat = np.full(H, np.inf)
        flat[hid] = np.where((v_lo > 0) & (lo > 0), v_lo, np.inf)
        slower = np.isfinite(flat) & (_hill_times(h, x, hill, H, cap, ramps) > _hill_times(h, x, hill, H, flat, ramps))
        cap[slower] = flat[slower]
    return cap[hill] ** 2, hill


def _crossings(h, x, rt, a, b, first, L2, s_a, s_b):
    """Where the ramps (``rt``: :meth:`RampBounds.table`) cross the level L2 (speed^2): into the first
    point ``a`` at or above it from the point before (unless ``a`` is its hill's ``first``), and out of the
    last one ``b`` to the next; a ramp is never slower than reaching the level at the grid point, as
    :func:`ramp_kinks` runs it.  (Masks, no index lists: a bisection step on a few hills is all overhead.)"""
    N = x.shape[0]
    ur, C, D = rt
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        k = np.maximum(a - 1, 0)
        hk = h[k]
        rise = np.maximum(L2 - x[k], 0.0)
        u = np.maximum(ur[k], rise / (2 * hk))
        s_a = np.where((a > first) & (hk > 0), s_a - hk + np.minimum(hk, rise / (2 * u)), s_a)
        k = np.minimum(b, N - 2)
        hk = h[k]
        fall = np.maximum(L2 - x[k + 1], 0.0)
        u = np.maximum(-(C[k] + D[k] * L2[:, None]).max(axis=1), fall / (2 * hk))
        d = np.where(u > 0, fall / (2 * u), hk)
        s_b = np.where((b < N - 1) & (hk > 0), s_b + hk - np.minimum(hk, d), s_b)
    return s_a, s_b


def _hill_times(h: np.ndarray, x: np.ndarray, hill: np.ndarray, H: int, level: np.ndarray,
                ramps: RampBounds | None = None) -> np.ndarray:
    """Time (H,) over each hill of the grid profile ``x`` (speed^2) with speeds capped at the hill's
    ``level`` (inf: not capped); constant path acceleration between grid points, or with ``ramps`` the
    ramps into and out of the cap that :func:`ramp_kinks` gives the raw profile."""
    lev = level[hill]
    xc = np.minimum(x, lev * lev)
    ur, uf = ramp_kinks(h, xc, lev * lev, ramps)
    t = _ramp_times(h, xc[:-1], xc[1:], ur, uf)
    return np.bincount(hill[:-1], weights=t, minlength=H)


def _cap_round(h, x, w, spans=None, max_spans: int = 64, ramps: RampBounds | None = None):
    """One round of peak caps on the whole profile (``spans`` None) or on grid ranges that start and end
    at a valley.  Returns (mask of the grid points of the hills that need a cap, caps (N,) valid there),
    or (None, None) when every peak has its plateau."""
    N = x.shape[0]
    if spans is None or len(spans) > max_spans:
        spans = [(0, N - 1)]
    region = np.zeros(N, dtype=bool)
    cap = np.full(N, np.inf)
    for a0, a1 in spans:
        if a1 <= a0:
            continue
        c, hill = _cap_peaks(h[a0:a1], x[a0:a1 + 1], w, None if ramps is None else ramps.shifted(a0))
        more = c < x[a0:a1 + 1] * (1 - 1e-9)
        if more.any():
            hm = np.zeros(int(hill[-1]) + 1, dtype=bool)
            hm[hill[more]] = True
            sub = hm[hill]
            region[a0:a1 + 1] |= sub
            cap[a0:a1 + 1] = np.where(sub, c, cap[a0:a1 + 1])
    return (region, cap) if region.any() else (None, None)


def _runs(mask: np.ndarray) -> list:
    """Inclusive (first, last) index pairs of the runs of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0].tolist(), (np.nonzero(d == -1)[0] - 1).tolist()))


def _sample_profile(sg, h, x, holds_s, dt, ramps: RampBounds | None = None, caps=None, limit=None):
    """Raw s(t) at dt from grid speeds x and holds (seconds after each grid point); with ``ramps`` and
    ``caps`` the intervals into and out of a capped plateau ramp at the largest acceleration and hold the
    cap for the rest (:func:`ramp_kinks`; with ``limit`` also those into and out of a flat top at the speed
    limits), the others run at constant acceleration."""
    N = sg.shape[0]
    ur, uf = ramp_kinks(h, x, caps, ramps, limit)
    D = _ramp_times(h, x[:-1], x[1:], ur, uf)      # (N-1,)
    if not np.all(np.isfinite(D)):
        k = int(np.nonzero(~np.isfinite(D))[0][0])
        raise FloatingPointError(f"zero speed over a path interval at grid point {k}")
    v = np.sqrt(np.maximum(x, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(h > 0, (x[1:] - x[:-1]) / (2 * np.where(h > 0, h, 1.0)), 0.0)
    H = holds_s
    step = np.empty(N)
    step[:-1] = H[:-1] + D
    step[-1] = H[-1]
    TH = np.concatenate([[0.0], np.cumsum(step)[:-1]])
    total = float(TH[-1] + H[-1])
    nt = int(math.ceil(total / dt)) + 1
    t = np.arange(nt) * dt
    g = np.clip(np.searchsorted(TH, t, side="right") - 1, 0, N - 1)
    tau = t - TH[g] - H[g]
    s = sg[g].copy()
    gi = np.minimum(g, N - 2)
    Dg = np.where(g < N - 1, D[gi], 0.0)
    mov = (tau > 0) & (g < N - 1)
    tm = np.minimum(tau, Dg)
    s[mov] = np.minimum(sg[g[mov]] + v[g[mov]] * tm[mov] + 0.5 * u[gi[mov]] * tm[mov] ** 2, sg[g[mov] + 1])
    kr = mov & (ur[gi] > 0) & (x[np.minimum(g + 1, N - 1)] > x[g])
    if kr.any():           # ramp at ur to the end speed, then that speed
        k, tk = gi[kr], tm[kr]
        a = np.maximum(ur[k], u[k])
        t1 = (v[k + 1] - v[k]) / a
        r = np.minimum(tk, t1)
        s[kr] = np.minimum(sg[k] + v[k] * r + 0.5 * a * r * r + v[k + 1] * np.maximum(tk - t1, 0.0), sg[k + 1])
    kf = mov & (uf[gi] > 0) & (x[np.minimum(g + 1, N - 1)] < x[g])
    if kf.any():           # the start speed, then a ramp down at uf to the end speed
        k, tk = gi[kf], tm[kf]
        a = np.maximum(uf[k], -u[k])
        dr = (x[k] - x[k + 1]) / (2 * a)
        tc = (h[k] - dr) / v[k]
        r = np.maximum(tk - tc, 0.0)
        s[kf] = np.minimum(sg[k] + v[k] * np.minimum(tk, tc) + v[k] * r - 0.5 * a * r * r, sg[k + 1])
    return s, TH, total


def _box_filter(s_raw: np.ndarray, n: int) -> np.ndarray:
    """Moving average of n samples over s_raw padded with its first and last value (length + n)."""
    if n <= 1:
        return s_raw.copy()
    ds = np.diff(np.concatenate([s_raw, np.full(n, s_raw[-1])]))
    ds = np.concatenate([np.zeros(n - 1), ds])
    C = np.concatenate([[0.0], np.cumsum(ds)])
    inc = (C[n:] - C[:-n]) / n
    out = s_raw[0] + np.concatenate([[0.0], np.cumsum(inc)[: s_raw.shape[0] + n - 1]])
    out = np.maximum.accumulate(out)
    return np.minimum(out, s_raw[-1])
