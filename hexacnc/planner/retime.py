"""Final time scaling of a verified setpoint table against the strut limits (measured from the rows).

The jerk filter of :mod:`hexacnc.planner.profile` leaves the strut limits partly unused (its transitions
are slower than a jerk-limited optimum's, its slow spots are spread).  This pass runs the table faster
where the rows leave room: the new table is ``s_new(t) = s_old(tau(t))`` with ``d tau / dt = r >= 1``.
With the old strut rates ``l', l'', l'''`` (in old time) the new ones are ``l' r``, ``l'' r^2 + l' r'``
and ``l''' r^3 + 3 l'' r r' + l' r''``; ``r`` is therefore chosen at most the pointwise room
``R = min(V/|l'|, sqrt(A/|l''|), cbrt(J/|l'''|))`` (targets V, A, J), eroded and smoothed over a window
so that its derivatives stay small, and the result is measured again from the rows (exact inverse
kinematics, finite differences at the cycle period).  Where a row exceeds a target the room there is
lowered and the pass repeats; if it does not converge the old table is kept.  ``r`` is 1 wherever the
table rests (holds keep their duration).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import maximum_filter1d, minimum_filter1d, uniform_filter1d

#: largest rate (the pass never runs a row more than this much faster)
R_MAX = 1.5
#: smoothing window of the rate, in rows (the erosion reaches a full window either side)
WINDOW_ROWS = 56
#: share of the programmed feed and the angular-velocity limit the scaled rows may use (rounding margin)
FEED_TARGET = 1.0 - 1e-7
#: repeats after a violation before the old table is kept
MAX_ROUNDS = 12
#: windows before a violating row whose room is lowered with it
BACK_WINDOWS = 8


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


def feed_utilisation(path, s_tab: np.ndarray, dt: float, max_angular_velocity_deg_s: float) -> np.ndarray:
    """Per row the larger of the programmed feed's and the angular-velocity limit's use between rows k-1, k
    and k, k+1 (finite differences of the tool tip): the feed is the tool-tip speed (mm/s), or the angular
    speed (deg/s) of a move that only rotates, as the planner reads it."""
    n = s_tab.shape[0]
    out = np.zeros(n)
    if n < 2:
        return out
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
    r = minimum_filter1d(R, 2 * w + 1, mode="nearest")
    h = max(1, w // 2)
    r = uniform_filter1d(uniform_filter1d(r, h, mode="nearest"), h, mode="nearest")
    return np.minimum(r, R)


def _quantise(r: np.ndarray, dt: float) -> np.ndarray:
    """The rate with the time saved over every stretch of r > 1 rounded down to whole cycles (the excess of
    the stretch, r - 1, scaled by a factor in [0, 1]): wherever r = 1 the new rows then sample the old
    table at its own phase (a curvature step read by the finite differences reads as before)."""
    r = np.where(r < 1.0 + 1e-9, 1.0, r)
    up = r > 1.0
    if not up.any():
        return r
    d = np.diff(np.concatenate([[0], up.astype(np.int8), [0]]))
    a = np.nonzero(d == 1)[0]
    b = np.nonzero(d == -1)[0]                   # stretch = rows a..b-1; intervals a-1..b-1 touch it
    ia = np.maximum(a - 1, 0)
    ex = r - 1.0

    lab = np.zeros(r.shape[0], dtype=np.int64)
    lab[a] = np.arange(1, a.size + 1)
    lab[np.minimum(b, r.shape[0] - 1)] -= np.where(b < r.shape[0], np.arange(1, a.size + 1), 0)
    lab = np.cumsum(lab)                         # stretch number (1-based) of every row, 0 outside

    def saving(alpha):
        rr = 1.0 + ex * np.concatenate([[0.0], alpha])[lab]
        step = dt - dt * 2.0 / (rr[:-1] + rr[1:])
        cs = np.concatenate([[0.0], np.cumsum(step)])
        hi = np.minimum(b, r.shape[0] - 1)
        return cs[hi] - cs[ia]

    goal = np.floor(saving(np.ones(a.size)) / dt + 1e-9) * dt
    lo = np.zeros(a.size)
    hi_ = np.ones(a.size)
    for _ in range(40):
        mid = 0.5 * (lo + hi_)
        ok = saving(mid) <= goal
        lo = np.where(ok, mid, lo)
        hi_ = np.where(ok, hi_, mid)
    return 1.0 + ex * np.concatenate([[0.0], lo])[lab]


def _apply(s_old: np.ndarray, r: np.ndarray, dt: float):
    """The table run at rate r (per old row): new rows at the cycle period and the new time of each old row."""
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
    if s[-1] != s_old[-1]:                  # the end row is the old end (at rest)
        s = np.append(s, s_old[-1])
    return s, t_new


def retime(path, hx, s_tab: np.ndarray, dt: float, vmax, amax, jmax, targets,
           max_angular_velocity_deg_s: float = float("inf")) -> Retimed:
    """The table ``s_tab`` (rows at ``dt``) run faster where the rows leave room below ``targets`` (v, a, j
    fractions of the limits); every row of the result is within the targets (measured), or the old
    table is returned (``rounds`` = -1)."""
    vmax, amax, jmax = (np.asarray(x, dtype=float) for x in (vmax, amax, jmax))
    n = s_tab.shape[0]
    keep = Retimed(s_tab, np.arange(n) * dt, -1, 1.0)
    if n < 8:
        return keep
    uv, ua, uj = row_utilisation(path, hx, s_tab, dt, vmax, amax, jmax)
    # a target the table itself exceeds (by rounding) becomes the table's own peak: never worse than before
    targets = (max(targets[0], uv.max()), max(targets[1], ua.max()), max(targets[2], uj.max()))
    # rows at rest (equal to a neighbour): no room there and within a window of them, so that every stop
    # keeps its standstill rows exactly
    still = np.zeros(n, dtype=np.int8)
    eq = s_tab[1:] == s_tab[:-1]
    still[1:] |= eq
    still[:-1] |= eq
    near_rest = maximum_filter1d(still, 2 * WINDOW_ROWS + 1, mode="nearest") > 0
    uf = feed_utilisation(path, s_tab, dt, max_angular_velocity_deg_s)
    R = np.where(near_rest, 1.0, _room(uv, ua, uj, uf, targets))
    for rnd in range(MAX_ROUNDS):
        r = _quantise(_smooth_rate(R, WINDOW_ROWS), dt)
        if r.max() <= 1.0 + 1e-9:
            return keep
        s_new, t_new = _apply(s_tab, r, dt)
        nv, na, nj = row_utilisation(path, hx, s_new, dt, vmax, amax, jmax)
        nf = feed_utilisation(path, s_new, dt, max_angular_velocity_deg_s)
        over = np.maximum(np.maximum(nv / targets[0], na / targets[1]), nj / targets[2])
        # the feed: never above FEED_TARGET, nor above the old table's own peak where that was higher
        over = np.maximum(over, nf / max(FEED_TARGET, float(uf.max())))
        if over.max() <= 1.0:
            return Retimed(s_new, t_new, rnd, (n - 1) / max(s_new.shape[0] - 1, 1))
        # lower the room around every violating row (mapped back to old rows) by its excess; also over the
        # stretch before it (BACK_WINDOWS windows): a row that has no room itself (r ~ 1) exceeds only because
        # the time saved before it moved its sampling phase against a curvature step
        bad = np.nonzero(over > 1.0)[0]
        old = np.clip(np.searchsorted(t_new, bad * dt), 0, n - 1)
        hit = np.zeros(n)
        np.maximum.at(hit, old, 1.0)
        near = minimum_filter1d(-hit, 2 * WINDOW_ROWS + 1, mode="nearest") < 0
        c = np.concatenate([[0.0], np.cumsum(hit)])
        ahead = np.minimum(np.arange(n) + BACK_WINDOWS * WINDOW_ROWS, n)
        back = c[ahead] - c[:-1] > 0                    # a violating row within BACK_WINDOWS windows ahead
        R = np.where(near | back, 1.0 + (R - 1.0) * 0.5, R)
    return keep


def hold_times(t_of_old: np.ndarray, TH: np.ndarray, lag_s: float, dt: float) -> np.ndarray:
    """Start times (s) of the raw profile's holds in the retimed table: the old table comes to rest
    ``lag_s`` (the filter's lag) after ``TH``; the new one at the new time of that row, and rests as long
    (the rate is 1 at rest)."""
    t_old = np.arange(t_of_old.shape[0]) * dt
    return np.interp(TH + lag_s, t_old, t_of_old) - lag_s
