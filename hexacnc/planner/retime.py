"""Final time scaling of a verified setpoint table against the strut limits (measured from the rows).

The jerk filter of :mod:`hexacnc.planner.profile` leaves the strut limits partly unused (its transitions
are slower than a jerk-limited optimum's, its slow spots are spread).  This pass runs the table faster
where the rows leave room: the new table is ``s_new(t) = s_old(tau(t))`` with ``d tau / dt = r >= 1``.
With the old strut rates ``l', l'', l'''`` (in old time) the new ones are ``l' r``, ``l'' r^2 + l' r'``
and ``l''' r^3 + 3 l'' r r' + l' r''``; ``r`` is therefore chosen at most the pointwise room
``R = min(V/|l'|, sqrt(A/|l''|), cbrt(J/|l'''|))`` (targets V, A, J), shaped so that its derivatives fit
the room left at each row (:func:`_shaped_rate`: slow rows let it change fast; with ``SHAPED`` off, eroded
and smoothed over a fixed window), and the result is measured again from the rows (exact inverse
kinematics, finite differences at the cycle period).  Where a row exceeds a target the room there is
lowered and the pass repeats; if it does not converge the old table is kept.  ``r`` is 1 wherever the
table rests (holds keep their duration).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .path import platform_struts

#: largest rate (the pass never runs a row more than this much faster)
R_MAX = 3.0
#: smoothing window of the rate, in rows (the erosion reaches a full window either side)
WINDOW_ROWS = 40
#: share of the programmed feed and the angular-velocity limit the scaled rows may use (rounding margin)
FEED_TARGET = 1.0 - 1e-7
#: repeats after a violation before the old table is kept
MAX_ROUNDS = 6
#: Newton steps of the whole-cycle rounding of every stretch's saving
QUANTISE_NEWTON = 8
#: rounds of the chain-rule prediction per measurement, and the share of the targets it aims at
PREDICT_ROUNDS = 12
PREDICT_SHARE = 0.995
#: the rate shaped by the room for its change (:func:`_shaped_rate`), else smoothed over WINDOW_ROWS
SHAPED = True
#: share of the room's excess over 1 the shaped rate aims at (the rest leaves room for its change)
RATE_LEVEL = 0.6
#: rows of the shaped rate's box smoothing
RATE_BOX_ROWS = 12
#: every this many rows the rate is 1 (stretches decided on their own are at most this long)
ANCHOR_ROWS = 2000


@dataclasses.dataclass
class Retimed:
    s_tab: np.ndarray            #: new table (path positions at the cycle period)
    t_of_old: np.ndarray         #: new time (s) of every old row
    rounds: int
    gain: float                  #: old duration / new duration


def row_utilisation(path, hx, s_tab: np.ndarray, dt: float, vmax, amax, jmax):
    """Per row peak |v|, |a|, |jerk| of the struts over the limits (exact inverse kinematics, finite
    differences at ``dt``: velocity between rows k-1, k and k, k+1; acceleration at k; jerk of the two
    third differences touching k)."""
    L = path.platform_struts(path.piece_at(s_tab), s_tab, hx.plat, hx.base)[1]
    return _utilisation_of(L, dt, vmax, amax, jmax)


def _utilisation_of(L: np.ndarray, dt: float, vmax, amax, jmax):
    """:func:`row_utilisation` of the strut lengths L (n, 6) of the rows."""
    n = L.shape[0]
    uv = np.zeros(n)
    ua = np.zeros(n)
    uj = np.zeros(n)
    if n < 4:
        return uv, ua, uj
    v = np.max(np.abs(np.diff(L, axis=0)) / (dt * vmax[None]), axis=1)
    uv[1:] = v
    uv[:-1] = np.maximum(uv[:-1], v)
    ua[1:-1] = np.max(np.abs(L[2:] - 2 * L[1:-1] + L[:-2]) / (dt * dt * amax[None]), axis=1)
    j = np.max(np.abs(L[3:] - 3 * L[2:-1] + 3 * L[1:-2] - L[:-3]) / (dt ** 3 * jmax[None]), axis=1)
    uj[1:-2] = j
    uj[2:-1] = np.maximum(uj[2:-1], j)
    return uv, ua, uj


def _lengths_and_tips(path, hx, s_tab: np.ndarray):
    """Strut lengths (n, 6), tool-tip poses (n, 6) and pieces (n,) of the rows: one evaluation of the path."""
    pc = path.piece_at(s_tab)
    tip = path.tip(pc, s_tab)
    return platform_struts(tip, path.tool_point[pc], hx.plat, hx.base)[1], tip, pc


def feed_utilisation(path, s_tab: np.ndarray, dt: float, max_angular_velocity_deg_s: float,
                     tip=None, pc=None) -> np.ndarray:
    """Per row the larger of the programmed feed's and the angular-velocity limit's use between rows k-1, k
    and k, k+1 (finite differences of the tool tip): the feed is the tool-tip speed (mm/s), or the angular
    speed (deg/s) of a move that only rotates, as the planner reads it.  ``tip``, ``pc``: the rows' tool-tip
    poses and pieces if already at hand."""
    n = s_tab.shape[0]
    out = np.zeros(n)
    if n < 2:
        return out
    if tip is None:
        pc = path.piece_at(s_tab)
        tip = path.tip(pc, s_tab)
    d = np.diff(tip, axis=0)
    ds = np.diff(s_tab)
    lin = np.linalg.norm(d[:, :3], axis=1)
    ang = np.linalg.norm(np.degrees(d[:, 3:]), axis=1)
    meas = np.where(lin > 1e-6 * ds, lin, ang)
    feed = np.minimum(path.feed[pc[:-1]], path.feed[pc[1:]])
    u = meas / (dt * feed)
    if np.isfinite(max_angular_velocity_deg_s):
        a = 0.5 * (tip[:-1, 3:] + tip[1:, 3:])
        r = d[:, 3:] / dt
        cb, sb, cc, sc = np.cos(a[:, 1]), np.sin(a[:, 1]), np.cos(a[:, 2]), np.sin(a[:, 2])
        wx = cc * cb * r[:, 0] - sc * r[:, 1]
        wy = sc * cb * r[:, 0] + cc * r[:, 1]
        wz = -sb * r[:, 0] + r[:, 2]
        u = np.maximum(u, np.sqrt(wx * wx + wy * wy + wz * wz) / np.radians(max_angular_velocity_deg_s))
    out[1:] = u
    out[:-1] = np.maximum(out[:-1], u)
    return out


def _room(uv, ua, uj, uf, targets) -> np.ndarray:
    tv, ta, tj = targets
    with np.errstate(divide="ignore"):
        R = np.minimum(np.minimum(tv / uv, np.sqrt(ta / ua)), np.cbrt(tj / uj))
        R = np.minimum(R, FEED_TARGET / uf)
    return np.clip(R, 1.0, R_MAX)


def _smooth_rate(R: np.ndarray, w: int) -> np.ndarray:
    """A rate at most R everywhere, changing over ``w`` rows (erosion over 2w+1, two box filters of w/2)."""
    from scipy.ndimage import minimum_filter1d, uniform_filter1d
    r = minimum_filter1d(R, 2 * w + 1, mode="nearest")
    h = max(1, w // 2)
    r = uniform_filter1d(uniform_filter1d(r, h, mode="nearest"), h, mode="nearest")
    return np.minimum(r, R)


def _slope_room(R: np.ndarray, rates, dt: float, lims, m: int) -> np.ndarray:
    """The slope ``D`` (per row, 1/s in old time, the minimum over 2m+1 rows) a rate at the level
    ``Rc = 1 + RATE_LEVEL (R - 1)`` may take.  By the chain rule the new strut acceleration is
    ``l2 r^2 + l1 r r'`` and the jerk ``l3 r^3 + 3 l2 r^2 r' + l1 r (r'^2 + r r'')`` (' = d/d old time), so
    ``|r'| <= (A_i - |l2_i| Rc^2) / (|l1_i| Rc)`` and, for a slope-D profile smoothed by a box of ``m`` rows
    (``|r''| <= 2 D / (m dt)``), ``|l1| Rc D^2 + (3 |l2| Rc^2 + 2 |l1| Rc^2 / (m dt)) D <= J_i - |l3| Rc^3``.
    Both bounds only grow as R is lowered: the slope of the first R stays valid for every lower one."""
    from scipy.ndimage import minimum_filter1d
    d1, d2, d3 = rates
    vmax, amax, jmax, targets, _ = lims
    Rc = 1.0 + RATE_LEVEL * (R - 1.0)
    W = m * dt
    D = np.full(R.shape[0], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(d1.shape[1]):
            l1, l2, l3 = np.abs(d1[:, i]), np.abs(d2[:, i]), np.abs(d3[:, i])
            da = (targets[1] * amax[i] - l2 * Rc * Rc) / (l1 * Rc)
            da = np.where(l1 > 0, np.maximum(da, 0.0), np.inf)
            c = np.maximum(targets[2] * jmax[i] - l3 * Rc ** 3, 0.0)
            b = 3.0 * l2 * Rc * Rc + 2.0 * l1 * Rc * Rc / W
            dj = np.where(b > 0, 2.0 * c / (b + np.sqrt(b * b + 4.0 * l1 * Rc * c)), np.inf)
            np.minimum(D, np.minimum(da, dj), out=D)
    return np.minimum(minimum_filter1d(D, 2 * m + 1, mode="nearest"), 1e6)


def _shaped_rate(R: np.ndarray, D: np.ndarray, dt: float, m: int) -> np.ndarray:
    """A rate at most R whose slope stays within ``D`` (:func:`_slope_room`): slow rows (small ``l1``) let it
    change fast, so it can rise between two slow corners.  The level ``1 + RATE_LEVEL (R - 1)`` (the rest of
    the room is left for the change) eroded over m rows, limited to slope D forwards and backwards (min-plus
    scans), smoothed by a box of m rows."""
    from scipy.ndimage import minimum_filter1d, uniform_filter1d
    Rc = 1.0 + RATE_LEVEL * (R - 1.0)
    r0 = minimum_filter1d(Rc, m + 1, mode="nearest")
    C = np.concatenate([[0.0], np.cumsum(D[1:] * dt)])
    fwd = C + np.minimum.accumulate(r0 - C)
    bwd = -C + np.minimum.accumulate((r0 + C)[::-1])[::-1]
    r = uniform_filter1d(np.minimum(fwd, bwd), m, mode="nearest")
    return np.clip(np.minimum(r, R), 1.0, None)


def _quantise(r: np.ndarray, dt: float) -> np.ndarray:
    """The rate with the time saved over every stretch of r > 1 rounded down to whole cycles (the excess of
    the stretch, r - 1, scaled by a factor in [0, 1]): wherever r = 1 the new rows then sample the old
    table at its own phase (a curvature step read by the finite differences reads as before).

    The saving of a stretch, ``f(alpha) = sum dt (1 - 2 / (2 + alpha (e_i + e_i+1)))``, is increasing and
    concave in alpha: Newton's method from alpha = 1 (f above the whole cycles) steps below the root once
    and then rises to it from below, so the saving never exceeds the whole cycles."""
    n = r.shape[0]
    r = np.where(r < 1.0 + 1e-9, 1.0, r)
    up = r > 1.0
    if not up.any():
        return r
    d = np.diff(np.concatenate([[0], up.astype(np.int8), [0]]))
    a = np.nonzero(d == 1)[0]
    b = np.nonzero(d == -1)[0]                   # stretch = rows a..b-1; intervals max(a-1,0)..min(b,n-1)-1
    ia = np.maximum(a - 1, 0)
    ib = np.minimum(b, n - 1)
    cnt = ib - ia
    first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    owner = np.repeat(np.arange(a.size), cnt)
    iv = np.repeat(ia, cnt) + (np.arange(int(cnt.sum())) - np.repeat(first, cnt))
    ex = r - 1.0
    E = ex[iv] + ex[iv + 1]                      # excess of both ends of every interval of a stretch

    def f_and_df(alpha):
        q = 2.0 + alpha[owner] * E
        return (np.add.reduceat(dt * (1.0 - 2.0 / q), first), np.add.reduceat(dt * 2.0 * E / (q * q), first))

    s1, _ = f_and_df(np.ones(a.size))
    goal = np.floor(s1 / dt + 1e-9) * dt
    alpha = np.ones(a.size)
    for _ in range(QUANTISE_NEWTON):
        f, df = f_and_df(alpha)
        alpha = np.clip(alpha - np.where(df > 0, (f - goal) / np.where(df > 0, df, 1.0), alpha), 0.0, 1.0)
    lab = np.zeros(n, dtype=np.int64)
    lab[a] = np.arange(1, a.size + 1)
    lab[b[b < n]] -= np.arange(1, a.size + 1)[b < n]
    lab = np.cumsum(lab)                         # stretch number (1-based) of every row, 0 outside
    return 1.0 + ex * np.concatenate([[0.0], alpha])[lab]


def _apply(s_old: np.ndarray, r: np.ndarray, dt: float):
    """The table run at rate r (per old row): new rows at the cycle period, the new time of each old row
    and the old time (in rows) of each new row."""
    from scipy.interpolate import CubicSpline      # scipy only when retiming (import ~1 s)
    n = s_old.shape[0]
    t_old = np.arange(n) * dt
    t_new = np.concatenate([[0.0], np.cumsum(dt * 2.0 / (r[:-1] + r[1:]))])
    m = int(np.floor(t_new[-1] / dt + 1e-9)) + 1
    tq = np.arange(m) * dt
    tau = np.clip(CubicSpline(t_new, t_old)(tq), 0.0, t_old[-1])
    s = CubicSpline(t_old, s_old)(tau)
    # where the new row falls on an old row (r = 1 since the last whole-cycle saving), take it bit for bit
    k = np.rint(tau / dt).astype(np.int64)
    on = np.abs(tau - k * dt) <= 1e-6 * dt
    s[on] = s_old[k[on]]
    s = np.clip(np.maximum.accumulate(s), s_old[0], s_old[-1])
    rows = tau / dt
    if s[-1] != s_old[-1]:                  # the end row is the old end (at rest)
        s = np.append(s, s_old[-1])
        rows = np.append(rows, n - 1.0)
    return s, t_new, rows


def _strut_rates(L: np.ndarray, dt: float):
    """Central differences (per row, zero at the ends) of the strut lengths L (n, 6): first to third."""
    n = L.shape[0]
    d1 = np.zeros_like(L)
    d2 = np.zeros_like(L)
    d3 = np.zeros_like(L)
    d1[1:-1] = (L[2:] - L[:-2]) / (2 * dt)
    d2[1:-1] = (L[2:] - 2 * L[1:-1] + L[:-2]) / (dt * dt)
    if n >= 5:
        d3[2:-2] = (L[4:] - 2 * L[3:-1] + 2 * L[1:-3] - L[:-4]) / (2 * dt ** 3)
    return d1, d2, d3


def _predict(rates, uf, r: np.ndarray, dt: float, lims, idx: np.ndarray) -> np.ndarray:
    """Predicted share (over the targets) of the rows ``idx`` run at rate r, by the chain rule on the old
    rows' strut rates l1, l2, l3 (each (n, 6)): ``l1 r``, ``l2 r^2 + l1 r_t``,
    ``l3 r^3 + 3 l2 r r_t + l1 r_tt``."""
    d1, d2, d3 = (x[idx] for x in rates)
    vmax, amax, jmax, targets, ftarget = lims
    rp = np.gradient(r, dt)
    rpp = np.gradient(rp, dt)[idx]
    rp = rp[idx]
    rr = r[idx]
    rt = (rr * rp)[:, None]
    rtt = (rr * rp * rp + rr * rr * rpp)[:, None]
    c = rr[:, None]
    v = (np.abs(d1) / vmax[None]).max(axis=1) * rr / targets[0]
    a = (np.abs(d2 * (c * c) + d1 * rt) / amax[None]).max(axis=1) / targets[1]
    j = (np.abs(d3 * (c * c * c) + d2 * (3.0 * c * rt) + d1 * rtt) / jmax[None]).max(axis=1) / targets[2]
    return np.maximum(np.maximum(v, a), np.maximum(j, uf[idx] * rr / ftarget))


def _lower(R: np.ndarray, rows_bad: np.ndarray, back: int) -> np.ndarray:
    """R with its excess over 1 halved within a window of the old rows ``rows_bad`` and ``back`` rows
    before them (a row without room of its own exceeds when the time saved before it moved its phase)."""
    from scipy.ndimage import maximum_filter1d
    n = R.shape[0]
    hit = np.zeros(n)
    hit[rows_bad] = 1.0
    near = maximum_filter1d(hit, 2 * WINDOW_ROWS + 1, mode="nearest") > 0
    c = np.concatenate([[0.0], np.cumsum(hit)])
    ahead = np.minimum(np.arange(n) + back, n)
    before = c[ahead] - c[:-1] > 0
    return np.where(near | before, 1.0 + (R - 1.0) * 0.5, R)


def _measure_rows(path, hx, s: np.ndarray, sel: np.ndarray, dt, lims, wmax_deg_s) -> np.ndarray:
    """Largest share (v, a, j over their targets, feed over its target) at the rows ``sel`` (sorted unique
    indices) of the table ``s``; each run of selected rows is measured with 3 rows either side."""
    n = s.shape[0]
    d = np.diff(np.concatenate([[-10], sel]))
    start = np.nonzero(d > 7)[0]                      # runs closer than their margins are measured as one
    a = sel[start]
    b = sel[np.concatenate([start[1:] - 1, [sel.size - 1]])]
    lo, hi = np.maximum(a - 3, 0), np.minimum(b + 3, n - 1)
    cnt = hi - lo + 1
    idx = np.repeat(lo, cnt) + (np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    vmax, amax, jmax, targets, ftarget = lims
    L, tip, pc = _lengths_and_tips(path, hx, s[idx])
    uv, ua, uj = _utilisation_of(L, dt, vmax, amax, jmax)
    uf = feed_utilisation(path, s[idx], dt, wmax_deg_s, tip, pc)
    over = np.maximum(np.maximum(uv / targets[0], ua / targets[1]), np.maximum(uj / targets[2], uf / ftarget))
    return over[np.searchsorted(idx, sel)]


def _run_labels(up: np.ndarray) -> np.ndarray:
    """Run number (1-based) of every True of ``up`` (maximal runs), 0 elsewhere."""
    return np.cumsum(np.diff(np.concatenate([[0], up.astype(np.int8)])) == 1) * up


def retime(path, hx, s_tab: np.ndarray, dt: float, vmax, amax, jmax, targets,
           max_angular_velocity_deg_s: float = float("inf")) -> Retimed:
    """The table ``s_tab`` (rows at ``dt``) run faster where the rows leave room below ``targets`` (v, a, j
    fractions of the limits) and the programmed feed; every row of the result is within them (measured
    from the rows); ``rounds`` = -1 when nothing was gained (the old table is returned).

    The rate is 1 at rest and at every ANCHOR_ROWS-th row, so the rows run faster come in stretches; each
    stretch saves whole cycles, so the rows between stretches are old rows (shifted by whole cycles) and
    every stretch is decided on its own: the rate is lowered where the chain rule on the old rows predicts
    an excess (cheap), the new rows are measured, a stretch within the targets is kept as it is, one over
    them is lowered and measured again, and after MAX_ROUNDS dropped (rate 1)."""
    from scipy.ndimage import maximum_filter1d
    vmax, amax, jmax = (np.asarray(x, dtype=float) for x in (vmax, amax, jmax))
    n = s_tab.shape[0]
    keep = Retimed(s_tab, np.arange(n) * dt, -1, 1.0)
    if n < 8:
        return keep
    L, tip, pc = _lengths_and_tips(path, hx, s_tab)
    uv, ua, uj = _utilisation_of(L, dt, vmax, amax, jmax)
    uf = feed_utilisation(path, s_tab, dt, max_angular_velocity_deg_s, tip, pc)
    del tip, pc
    # a target the table itself exceeds (by rounding) becomes the table's own peak: never worse than before
    targets = (max(targets[0], uv.max()), max(targets[1], ua.max()), max(targets[2], uj.max()))
    lims = (vmax, amax, jmax, targets, max(FEED_TARGET, float(uf.max())))
    rates = _strut_rates(L, dt)
    del L
    # rows at rest (equal to a neighbour): no room there and within a window of them, so that every stop
    # keeps its standstill rows exactly
    still = np.zeros(n, dtype=np.int8)
    eq = s_tab[1:] == s_tab[:-1]
    still[1:] |= eq
    still[:-1] |= eq
    near_rest = maximum_filter1d(still, 2 * WINDOW_ROWS + 1, mode="nearest") > 0
    R = np.where(near_rest, 1.0, _room(uv, ua, uj, uf, targets))
    R[::ANCHOR_ROWS] = 1.0
    ok = np.zeros(n, dtype=bool)                  # rows of stretches measured within the targets (r frozen)
    r_ok = np.ones(n)
    for rnd in range(MAX_ROUNDS + 1):
        # the slope room of this round's R (valid for the lower R the prediction leaves: both bounds grow)
        D = _slope_room(R, rates, dt, lims, RATE_BOX_ROWS) if SHAPED else None
        for _ in range(PREDICT_ROUNDS):
            r = _quantise(_shaped_rate(R, D, dt, RATE_BOX_ROWS) if SHAPED else _smooth_rate(R, WINDOW_ROWS), dt)
            r[ok] = r_ok[ok]
            act = np.nonzero((maximum_filter1d((r > 1.0).astype(np.int8), 5, mode="nearest") > 0) & ~ok)[0]
            bad = act[_predict(rates, uf, r, dt, lims, act) > PREDICT_SHARE]
            if bad.size == 0:
                break
            R = _lower(R, bad, 0)
        runs = _run_labels(r > 1.0)
        if rnd == MAX_ROUNDS:                     # stretches never measured within the targets: rate 1
            r = np.where(ok, r, 1.0)
            runs = np.zeros(n, dtype=np.int64)
        if r.max() <= 1.0 + 1e-9:
            return keep
        s_new, t_new, rows = _apply(s_tab, r, dt)
        k = np.clip(np.rint(rows).astype(np.int64), 0, n - 1)
        todo = maximum_filter1d(np.where(ok, 0, runs), 7, mode="nearest")          # +-3 rows
        sel = np.nonzero(todo[k] > 0)[0]
        if sel.size == 0:
            break
        over = _measure_rows(path, hx, s_new, sel, dt, lims, max_angular_velocity_deg_s)
        bad_runs = np.unique(todo[k[sel[over > 1.0]]])
        good = np.isin(runs, np.setdiff1d(np.unique(todo[k[sel]]), bad_runs)) & (runs > 0)
        ok |= good
        r_ok = np.where(good, r, r_ok)
        if bad_runs.size == 0:
            break
        R = np.where(ok, R, _lower(R, k[sel[over > 1.0]], 0))
    return Retimed(s_new, t_new, rnd, (n - 1) / max(s_new.shape[0] - 1, 1))


def hold_times(t_of_old: np.ndarray, TH: np.ndarray, lag_s: float, dt: float) -> np.ndarray:
    """Start times (s) of the raw profile's holds in the retimed table: the old table comes to rest
    ``lag_s`` (the filter's lag) after ``TH``; the new one at the new time of that row, and rests as long
    (the rate is 1 at rest)."""
    t_old = np.arange(t_of_old.shape[0]) * dt
    return np.interp(TH + lag_s, t_old, t_of_old) - lag_s
