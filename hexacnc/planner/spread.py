"""Spreading of limits over the moving average's reach (step 4 of the method in :mod:`hexacnc.planner.plan`):
a speed limit or an acceleration cap holds for every sample whose filter window holds it.  The reaches end
inside grid intervals; the values there change continuously with the reach (:func:`reach_end_limits`,
:func:`spread_cap`, and the grid points at reach ends of :mod:`hexacnc.planner.reachgrid`).
"""
from __future__ import annotations

import math

import numpy as np

def dilate_min(sg: np.ndarray, x: np.ndarray, T: float, max_span: int = 4000, speed2=None,
               max_reach: float = math.inf) -> np.ndarray:
    """Spread every speed limit over the distance travelled at that speed in the filter window.

    The moving average of width T gives, at position s_j, the mean raw speed of the
    positions passed within T.  If the raw speed is at most sqrt(x_j) for all
    positions within ``r_j = sqrt(x_j) T/2`` of s_j (the window spans T/2 either side of its centre),
    that mean is at most sqrt(x_j):
    so ``x_k <= x_j`` wherever ``|s_k - s_j| <= r_j``.  Slow spots have short reach.  ``speed2`` (N,):
    spread another quantity x (an acceleration cap) over the reach of these speeds^2 instead.  No reach
    exceeds ``max_reach`` (mm).
    """
    N = x.shape[0]
    fin, r, lo, hi = reaches(sg, x, T, max_reach, speed2)
    cnt = np.minimum(hi - lo + 1, max_span)
    # only limits lower than some point in their reach matter
    j = np.nonzero(fin & (cnt > 1))[0]
    out = x.copy()
    if j.size:
        np.minimum(out, range_min(N, lo[j], cnt[j], x[j]), out=out)
    return out


def reaches(sg: np.ndarray, x: np.ndarray, T: float, max_reach: float = math.inf, speed2=None) -> tuple:
    """The reaches of :func:`dilate_min` (same arguments): (finite (N,) bool, reach r (N,) mm, first and last
    grid point within ``s_j -+ r_j`` (N,) each)."""
    fin = np.isfinite(x)
    r = np.where(fin, np.minimum(np.sqrt(np.maximum(x if speed2 is None else speed2, 0.0)) * T, max_reach), 0.0)
    lo = np.searchsorted(sg, sg - r, side="left")
    hi = np.searchsorted(sg, sg + r, side="right") - 1
    return fin, r, lo, hi


def range_min(N: int, a: np.ndarray, cnt: np.ndarray, vals: np.ndarray) -> np.ndarray:
    """(N,) the smallest of ``vals[j]`` over the index ranges ``[a_j, a_j + cnt_j)`` holding each index
    (inf where none; every ``cnt_j >= 1``).  Every range is the union of two power-of-two blocks; the minimum
    over the blocks starting at each point is pushed down level by level (the same minima as a scatter over
    every point of every range, in O(N log max(cnt)))."""
    out = np.full(N, np.inf)
    if a.size == 0:
        return out
    lev = np.floor(np.log2(cnt)).astype(np.int64)
    top = int(lev.max())
    tab = [None] * (top + 1)
    for L in range(top, -1, -1):
        cur = np.full(N, np.inf) if tab[L] is None else tab[L]
        m = np.nonzero(lev == L)[0]
        if m.size:
            np.minimum.at(cur, a[m], vals[m])
            np.minimum.at(cur, a[m] + cnt[m] - (1 << L), vals[m])
        if L == 0:
            np.minimum(out, cur, out=out)
            break
        hh = 1 << (L - 1)
        nxt = cur.copy()
        np.minimum(nxt[hh:], cur[:-hh], out=nxt[hh:])
        tab[L - 1] = nxt
        tab[L] = None
    return out


def reach_ends(sg: np.ndarray, x: np.ndarray, T: float, max_reach: float = math.inf, speed2=None) -> tuple:
    """Where the reaches of :func:`dilate_min` (same arguments) end inside a grid interval of positive
    length: per end the interval ``k`` (its points k, k+1), the end's position in it ``t`` (0 at k, 1 at
    k+1), the spread limit and the grid point just beyond the reach.  ``speed2``: as in :func:`dilate_min`."""
    N = x.shape[0]
    fin, r, lo, hi = reaches(sg, x, T, max_reach, speed2)
    j = np.nonzero(fin & (r > 0.0))[0]
    ks, ts, xs, bs = [], [], [], []
    if j.size and N >= 2:
        sj, rj = sg[j], r[j]
        for side, last_in in ((1.0, hi[j]), (-1.0, lo[j] - 1)):  # the interval (k, k+1) the end lies in
            end = sj + side * rj
            k = last_in
            ok = (k >= 0) & (k < N - 1)
            k, jj, end = k[ok], j[ok], end[ok]
            hk = sg[k + 1] - sg[k]
            pos = hk > 0.0
            k, jj, end, hk = k[pos], jj[pos], end[pos], hk[pos]
            ks.append(k)
            ts.append(np.clip((end - sg[k]) / hk, 0.0, 1.0))
            xs.append(x[jj])
            bs.append(k + 1 if side > 0 else k)
    if not ks:
        z = np.zeros(0, dtype=np.int64)
        return z, np.zeros(0), np.zeros(0), z
    return np.concatenate(ks), np.concatenate(ts), np.concatenate(xs), np.concatenate(bs)


def reach_end_limits(sg: np.ndarray, x: np.ndarray, upper: np.ndarray, T: float,
                     max_reach: float = math.inf, speed2=None) -> np.ndarray:
    """Speed limits (N,) for the grid points just beyond the end of a spreading's reach (inf elsewhere).

    ``x`` the limits :func:`dilate_min` spreads (same ``sg``, ``T``, ``max_reach``); ``upper`` (N,) the
    limits of the points without this spreading.  A reach ends inside a grid interval; the point beyond
    keeps its own limit only while the reach is short of it and takes the spread one as soon as the reach
    passes it: a step in the limits as a path grows (a slow spot's reach grows more slowly than a path
    scaled up around it, so its end crosses grid points).  The point beyond gets the spread limit
    interpolated towards ``upper`` by the share of the interval that lies beyond the reach, so the limits
    change continuously with the reach; every copy of a duplicated junction point alike (the smallest of all
    reach ends at a point).  ``speed2``: as in :func:`dilate_min`.  The planner puts a grid point at each end it
    knows beforehand (:mod:`~hexacnc.planner.reachgrid`); this covers the others."""
    N = x.shape[0]
    lim = np.full(N, np.inf)
    k, t, xs, b = reach_ends(sg, x, T, max_reach, speed2)
    if k.size == 0:
        return lim
    f = np.where(b > k, 1.0 - t, t)                              # share of the interval beyond the reach
    first = np.searchsorted(sg, sg, side="left")                 # copies of a point: first index, count
    b0, nb = first[b], np.searchsorted(sg, sg, side="right")[b] - first[b]
    for o in range(int(nb.max())):
        m = np.nonzero(o < nb)[0]
        c, xm, fm = b0[m] + o, xs[m], f[m]
        bind = upper[c] > xm
        c, xm, fm = c[bind], xm[bind], fm[bind]
        with np.errstate(invalid="ignore"):
            val = np.where(fm > 0.0, xm + fm * (upper[c] - xm), xm)     # an infinite upper: no nan at f = 0
        np.minimum.at(lim, c, val)
    return lim


def time_coordinate(sg: np.ndarray, x: np.ndarray, gap_s: float = 1e3) -> np.ndarray:
    """Seconds (N,) from the first grid point to each at the speeds^2 ``x`` (N,), constant path acceleration
    between neighbours (``2 h / (v_k + v_k+1)``).  An interval of positive length with both ends at rest (a
    stop's gap in the spreading frame, :func:`separated`) counts ``gap_s``, far longer than any reach.
    :func:`dilate_min` on these positions with ``speed2`` one spreads over T seconds of travel at the speeds x."""
    v = np.sqrt(np.maximum(x, 0.0))
    h = np.diff(sg)
    vs = v[:-1] + v[1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(vs > 0.0, 2.0 * h / vs, np.where(h > 0.0, gap_s, 0.0))
    return np.concatenate([[0.0], np.cumsum(d)])


#: the acceleration cap spread over the filter's reach before the TOPP pass (:func:`spread_cap`)
SPREAD_CAP = True
#: farthest the acceleration cap is spread (mm): a corner's or a curve's low cap reaches the ramps beside it
#: (at the speeds there the filter's reach is a few tenths of a mm); on long fast moves the reach at the
#: uncapped speeds would lower the cap over whole moves (rest-to-rest moves 1.2 % longer, smoothed CAM 11 %)
SPREAD_CAP_MM = 0.2


def spread_cap(sg: np.ndarray, ecap: np.ndarray, x: np.ndarray, T: float, keep=None) -> np.ndarray:
    """The acceleration cap of every grid interval, at its first point (N,; the TOPP pass bounds an interval
    there), lowered to the caps the filter carries into it: the moving average carries an acceleration to
    every sample whose window holds it (a ramp at a line's cap beside a corner blend gave the blend's samples
    more jerk than the blend's cap allows).  Every point's cap reaches ``T`` seconds either side at the
    speed^2 ``x`` there (at most SPREAD_CAP_MM).  An interval takes the caps of both its ends (a ramp
    anywhere inside it keeps them; past a duplicated junction point, the other copy's too), the caps whose
    reach covers it, and a cap whose reach ends inside it interpolated towards the interval's cap without it
    by the share beyond the reach: the caps change continuously as a reach grows across grid points (a
    whole interval took a cap as soon as the reach touched it: the planned time fell by up to 75 cycles
    for a longer move).  ``keep`` (N-1,) bool: the links between neighbours (False at a stop, whose hold
    keeps the two sides' filter windows apart; ``sg`` then runs with a gap there: :func:`separated`)."""
    v2 = np.minimum(x, (SPREAD_CAP_MM / T) ** 2)
    N = ecap.shape[0]
    if N < 2:
        return ecap.copy()
    lnk = np.ones(N - 1, dtype=bool) if keep is None else keep
    own = np.minimum(ecap[:-1], np.where(lnk, ecap[1:], np.inf))       # the caps of both ends
    iv = own.copy()
    # the caps whose reach holds the whole interval (both ends)
    fin, _r, lo, hi = reaches(sg, ecap, T, speed2=v2)
    j = np.nonzero(fin & (hi > lo))[0]
    if j.size:
        np.minimum(iv, range_min(N - 1, lo[j], np.minimum(hi[j] - lo[j], 3999), ecap[j]), out=iv)
    z = np.nonzero((np.diff(sg)[1:] == 0) & lnk[1:] & lnk[:-1])[0]       # the next interval a junction's copies
    if z.size:
        iv[z] = np.minimum(iv[z], ecap[z + 2])
    # the caps whose reach ends inside the interval, by the share of it within the reach
    k, t, cj, b = reach_ends(sg, ecap, T, speed2=v2)
    if k.size:
        f = np.where(b > k, 1.0 - t, t)                              # share of the interval beyond the reach
        u = own[k]
        m = u > cj
        np.minimum.at(iv, k[m], cj[m] + f[m] * (u[m] - cj[m]))
    _junction_caps(sg, iv, own, lnk)
    out = np.empty(N)
    out[:-1] = iv
    out[-1] = np.min(ecap[hi == N - 1])                          # the last point: the caps reaching it
    return out


def _junction_caps(sg: np.ndarray, iv: np.ndarray, own: np.ndarray, lnk: np.ndarray) -> None:
    """A junction's zero-length intervals in ``iv`` (N-1,), whose cap only bounds the speed there (the speed at
    which the struts leave the cap), take the caps of the real intervals either side and of their own ends,
    not a reach's whole step at their position (in place)."""
    h = np.diff(sg)
    zl = np.nonzero((h == 0) & lnk)[0]
    if zl.size == 0:
        return
    n = iv.shape[0]
    idx = np.arange(n)
    prev = np.maximum.accumulate(np.where(h > 0, idx, -1))[zl]
    nxt = np.minimum.accumulate(np.where(h > 0, idx, n)[::-1])[::-1][zl]
    side = np.full(zl.size, np.inf)
    ok = prev >= 0
    side[ok] = iv[prev[ok]]
    ok = nxt < n
    side[ok] = np.minimum(side[ok], iv[nxt[ok]])
    iv[zl] = np.minimum(own[zl], side)


def separated(sg: np.ndarray, cut: np.ndarray, gap: float) -> tuple:
    """Path positions (N,) with ``gap`` added after every grid point in ``cut`` (indices), so that a
    spreading whose reach is less than ``gap`` never crosses one, and the mask (N-1,) of the links not
    cut."""
    keep = np.ones(max(sg.shape[0] - 1, 0), dtype=bool)
    cut = cut[cut < sg.shape[0] - 1]
    keep[cut] = False
    return sg + gap * np.concatenate([[0.0], np.cumsum(~keep)]), keep


#: a cap point's reach matters to the ramp beside a rest when its cap is below this share of the ramp's own
#: (the caps along a line differ by a few per mille)
REST_CAP_SHARE = 0.8
#: caps within this factor of each other are kept off a ramp together (one level of :func:`rest_ramp_sides`)
REST_CAP_GROUP = 1.25


def rest_sides(at_rest: np.ndarray, h: np.ndarray) -> tuple:
    """The intervals of positive length beside a rest whose other end moves: (rest point, far point) (m,) each,
    sorted by interval (the far point is the rest point +-1).  ``at_rest`` (N,) bool, ``h`` (N-1,) lengths."""
    N = at_rest.shape[0]
    r = np.nonzero(at_rest)[0]
    rr, aa = [], []
    for step in (1, -1):
        a = r + step
        ok = (a >= 0) & (a < N)
        rs, a = r[ok], a[ok]
        ok = ~at_rest[a] & (h[np.minimum(rs, a)] > 0.0)
        rr.append(rs[ok])
        aa.append(a[ok])
    r, a = np.concatenate(rr), np.concatenate(aa)
    o = np.argsort(np.minimum(r, a), kind="stable")
    return r[o], a[o]


def rest_ramp_sides(sg: np.ndarray, h: np.ndarray, at_rest: np.ndarray, ecap: np.ndarray, x: np.ndarray,
                    T: float) -> list:
    """The intervals next to a rest that low acceleration caps reach (:func:`spread_cap`, at the speeds^2
    ``x``): per such side (rest point, far point, step +-1, [(point, distance from the far point, cap)],
    cap levels ascending).

    A corner's low cap reaches the ramp from (or to) a rest while the raw profile runs from the interval's
    far point to the corner in less than ``T``; then the whole ramp is taken at that cap.  As moves grow the
    reach leaves the interval and the ramp is suddenly quick: a G1 X then G1 Y planned 17 cycles shorter at
    0.084 mm than at 0.078 mm.  The alternative (:func:`rest_ramp_ceiling`): every point from the far point
    to such a cap point no faster than ``dist / T``, so that its reach ends at the far point.  At the reach's
    edge that ceiling is the speed already run.  ``sg`` (N,) positions with gaps at stops, ``h`` (N-1,)
    interval lengths, ``at_rest`` (N,) bool, ``ecap`` (N,) caps before spreading."""
    N = sg.shape[0]
    vcap = SPREAD_CAP_MM / T
    sides = []
    for r, a in zip(*(v.tolist() for v in rest_sides(at_rest, h))):
        step = a - r
        own = min(ecap[r], ecap[a])
        pts = []
        k = a + step
        while 0 <= k < N and not at_rest[k] and abs(sg[k] - sg[a]) < SPREAD_CAP_MM:
            dist = abs(sg[k] - sg[a])
            if ecap[k] < REST_CAP_SHARE * own and T * min(math.sqrt(max(x[k], 0.0)), vcap) > dist > 0.0:
                pts.append((k, dist, float(ecap[k])))
            k += step
        if not pts:
            continue
        levels = []
        for cap in sorted(p[2] for p in pts):
            if not levels or cap > levels[-1] * REST_CAP_GROUP:
                levels.append(cap)
            else:
                levels[-1] = cap
        sides.append((r, a, step, pts, levels))
    return sides


def rest_ramp_ceiling(T: float, side: tuple, level: float, out: np.ndarray) -> None:
    """Lower ``out`` (N,) x units to the ceiling that keeps the caps of ``side`` (:func:`rest_ramp_sides`)
    up to ``level`` off its ramp: the points from the far point to each such cap point no faster than its
    distance / T (in place)."""
    _r, a, step, pts, _levels = side
    for k, dist, cap in pts:
        if cap <= level:
            v2 = (dist / T * (1.0 - 1e-6)) ** 2
            lo, hi = (a, k) if step > 0 else (k, a)
            np.minimum(out[lo:hi + 1], v2, out=out[lo:hi + 1])
