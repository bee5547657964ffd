"""Grid points where the spreading of a slow spot ends (step 4 of :mod:`hexacnc.planner.plan`).

A speed limit ``x_j`` is spread over ``|s - s_j| <= r_j`` (:func:`~hexacnc.planner.spread.dilate_min`), and
the reach's end ``s_j +- r_j`` falls inside a grid interval.  On the grid alone the point beyond keeps its
own, higher, limit until the reach passes it and then drops to ``x_j`` at once: the limits, and the planned
time, step as a path grows, because a slow spot's reach grows more slowly than a path scaled up around it
(twelve G64 moves of 1.198 um planned 9 cycles longer than of 1.216 um).  A grid point at every reach end
that binds (the point beyond has a higher limit) represents the spread limit exactly: the ramp out of the
slow spot starts where the reach ends, and the plan changes continuously with the path.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import path as P
from .grid import Derivs, Grid, derivatives
from .holds import Rests, rests
from .profile import _accel_cap
from .spread import dilate_min, reach_ends, rest_sides, separated
from .speeds import speed_limits

#: a reach end closer than this share of its interval to a grid point gets no point of its own (the
#: interval's interpolated limit, :func:`~hexacnc.planner.spread.reach_end_limits`, covers it)
MIN_SHARE = 1e-6
#: a reach end binds when the limit just beyond it is higher than the spread one by more than this share: identical
#: blends repeated along a path have limits equal up to the rounding of their derivatives (~1e-8), and a bare
#: comparison flickered with 0.05 % changes of length (twelve 1 um moves: 56 / 54 / 55 grid points, plans of
#: 0.1055 / 0.1050 / 0.1055 s)
BIND_REL = 1e-6
#: a grid point where the ramp from or to each rest reaches its speed (:func:`rest_ramp_positions`)
REST_RAMP_POINTS = True


def spread_frame(g: Grid, rs: Rests) -> tuple:
    """Positions the spreading runs on (a gap after every stop at a duplicated junction point, so that no
    reach crosses a stop), the links kept, and the longest reach (mm)."""
    reach_mm = float(g.sg[-1] - g.sg[0]) + 1.0
    cut = rs.stop_idx[rs.stop_idx < g.n - 1]
    cut = cut[g.h[cut] == 0]
    sg_sep, keep = separated(g.sg, cut, 2.0 * reach_mm)
    return sg_sep, keep, reach_mm


def end_positions(g: Grid, rs: Rests, xlim: np.ndarray, T: float) -> tuple:
    """The binding reach ends of the speed limits ``xlim`` (stops at rest) spread over ``T`` seconds:
    (interval index (m,), path position (m,)), sorted, at most one per position."""
    sg_sep, _keep, reach_mm = spread_frame(g, rs)
    xw = xlim.copy()
    xw[rs.stop_all] = np.inf
    out = dilate_min(sg_sep, xw, T, max_reach=reach_mm)
    out[rs.stop_all] = 0.0
    kk, t, xs, b = reach_ends(sg_sep, xw, T, reach_mm)
    # the point beyond has a higher limit
    bind = (out[b] > xs * (1.0 + BIND_REL)) & (t > MIN_SHARE) & (t < 1.0 - MIN_SHARE)
    kk, t = kk[bind], t[bind]
    if kk.size == 0:
        return kk, np.zeros(0)
    s = g.sg[kk] + t * (g.sg[kk + 1] - g.sg[kk])
    inside = (s > g.sg[kk]) & (s < g.sg[kk + 1])
    kk, s = kk[inside], s[inside]
    order = np.lexsort((s, kk))
    kk, s = kk[order], s[order]
    new = np.concatenate([[True], (kk[1:] != kk[:-1]) | (s[1:] != s[:-1])])
    return kk[new], s[new]


def insert_points(path: P.Path, hx, cfg, g: Grid, dv: Derivs, lims, dt: float, kk: np.ndarray, s: np.ndarray,
                  arrays: tuple) -> tuple:
    """The grid with points at ``s`` inside the intervals ``kk`` (sorted), their derivatives and speed
    limits; ``arrays`` (xlim, c, e, dd) extended with the new points' rows.  Returns (grid, derivs, arrays)."""
    pidx_new = g.pidx[kk]
    mini = Grid(s, pidx_new, np.ones(s.shape[0]), np.zeros(0, dtype=np.int64), g.lmarg, g.amarg)
    dn = derivatives(path, hx, mini)
    xn, cn, en, ddn = speed_limits(path, cfg, mini, dn, dt, *lims)
    at = kk + 1
    sg = np.insert(g.sg, at, s)
    pidx = np.insert(g.pidx, at, pidx_new)
    shift = np.searchsorted(kk, np.arange(g.n), side="left")     # points inserted before each old point
    h = np.diff(sg)
    junction = np.nonzero(g.h == 0)[0]
    h[junction + shift[junction]] = 0.0
    h = np.maximum(h, 0.0)
    last = g.last + shift[g.last]
    g2 = replace(g, sg=sg, pidx=pidx, h=h, last=last)
    dv2 = Derivs(np.insert(dv.Lp, at, dn.Lp, axis=0), np.insert(dv.Lpp, at, dn.Lpp, axis=0),
                 np.insert(dv.Lppp, at, dn.Lppp, axis=0), np.insert(dv.Xg, at, dn.Xg, axis=0),
                 np.insert(dv.dtip, at, dn.dtip, axis=0), None)
    new_rows = (xn, cn, en, ddn)
    out = tuple(np.insert(a, at, b, axis=0) for a, b in zip(arrays, new_rows))
    return g2, dv2, out


def rest_ramp_positions(g: Grid, dv: Derivs, rs: Rests, limits: tuple, jmax, w: float) -> tuple:
    """A point on every interval next to a rest, where a ramp at the largest acceleration there reaches the far
    point's speed limit (at most a quarter of the interval in): the ramp gets an interval of its own, and a corner's
    low cap kept off it (tighten.Tightener._rest_ramps) costs only that short distance.  Returns (interval index,
    path position), as :func:`end_positions`."""
    xlim, _c, e, _dd = limits
    at_rest = np.zeros(g.n, dtype=bool)
    at_rest[rs.stop_all] = True
    r, a = rest_sides(at_rest, g.h)
    ok = np.isfinite(xlim[a])
    r, a = r[ok], a[ok]
    # the TOPP bound and the filter's acceleration cap at the far point's limit, from the rest
    cap = _accel_cap(dv.Lp[r], dv.Lpp[r], dv.Lppp[r], xlim[a], jmax, w)
    u = np.minimum(np.min(e[r], axis=1), cap)
    i = np.minimum(r, a)
    h = g.h[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.minimum(xlim[a] / (2.0 * u), 0.25 * h)
    ok = (u > 0.0) & (d > MIN_SHARE * h)
    return i[ok].astype(np.int64), g.sg[r[ok]] + (a[ok] - r[ok]) * d[ok]


def with_reach_points(path: P.Path, hx, cfg, events, g: Grid, dv: Derivs, rs: Rests, limits: tuple, lims,
                      dt: float, T: float, hold_min: float) -> tuple:
    """The planning grid with a point at every binding end of the spreading of the speed limits over ``T``
    seconds.  ``limits`` (xlim, c, e, dd) of :func:`~hexacnc.planner.speeds.speed_limits`.  Returns
    (grid, derivs, rests, limits), unchanged where no reach ends inside an interval."""
    kk, s = end_positions(g, rs, limits[0], T)
    if REST_RAMP_POINTS:
        kr, sr = rest_ramp_positions(g, dv, rs, limits, lims[2], 2.0 * T)
        if kr.size:
            kk, s = np.concatenate([kk, kr]), np.concatenate([s, sr])
            o = np.lexsort((s, kk))
            kk, s = kk[o], s[o]
    if kk.size == 0:
        return g, dv, rs, limits
    g, dv, limits = insert_points(path, hx, cfg, g, dv, lims, dt, kk, s, limits)
    return g, dv, rests(path, events, g, hold_min, dt), limits
