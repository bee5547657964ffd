"""Short stretches between two rests run as one S-curve along the path (a step after the verified table of
:mod:`hexacnc.planner.plan`).

The filtered profile spends about the filter's width on every slowdown and a plateau of that width on every
speed peak, whatever the distance (a 1 um move took 86.5 ms), and features closer than the filter's reach
interact through its window, so a longer stretch could plan shorter.  A stretch from rest to rest with at most
``MAX_PIECES`` pieces and no hold inside is also planned as the time-optimal rest-to-rest motion of its path
position ``s`` (:mod:`.scurve`) under constant bounds ``V, A, J`` on ``s``, chosen so that at every sample of
every piece (and strut ``i``) of the stretch::

    |L_i'| V <= ETA_V 0.995 v_i                      (and V within the feed and the angular limit)
    |L_i'| A + |L_i''| V^2 <= ETA a_i
    |L_i'| J + 3 |L_i''| V A + |L_i'''| V^3 + |dL_i''| V^2 / dt <= JERK_SHARE ETA j_i

(``dL''``: the curvature step at a junction, read as a jerk by differences at the cycle period).  ``V`` and
``A`` are those of shortest time, ``J`` the largest they leave.  Scaling a stretch by ``k > 1`` divides ``L''``
by k and ``L'''`` by k^2: the bounds of the scaled stretch divided by k satisfy these inequalities on the
original one, and :func:`~hexacnc.planner.scurve.move_time` is the same for a move and bounds scaled together, so
the time of a stretch never exceeds the time of a scaled-up copy (up to the kinematics' nonlinearity over the
stretch).  Where the S-curve takes fewer rows (with the rest after it) than the filtered table, its rows replace
them; the new table is measured exactly and any stretch whose rows exceed a target gets its filtered rows back.
:func:`trim_start` and :func:`trim_end` drop the rows at rest the moving average adds before the first hold and
after the last one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import path as P
from . import scurve
from .consts import ETA_V
from .grid import Grid, derivatives
from .holds import hold_rows
from .profile import ETA
from .speeds import feed_angular_limits

#: stretches with more pieces keep the filtered profile (constant bounds suit short stretches only)
MAX_PIECES = 64
#: samples per piece (both ends included) at which the bounds are taken: every one of them on a blend, arc or
#: spline (one bound over a blend's quarters: a twelve-move 0.07 mm square 0.182 s instead of 0.163 s, slower than
#: the filtered profile), the largest on a line
SAMPLES = 17
#: the search: GRID speeds (log-spaced fractions of the largest feasible one, down to V_RANGE), then ZOOMS scans
#: of ZOOM_POINTS around the best; at each speed a golden section of GOLDEN_STEPS over log A (down to A_RANGE)
GRID = 32
ZOOM_POINTS = 9
ZOOMS = 3
GOLDEN_STEPS = 22
V_RANGE, A_RANGE = 1e-4, 1e-6
#: candidate x piece x strut values per temporary array of the search
CHUNK_VALUES = 1 << 20
#: share of ETA j the S-curve's jerk inequality may use: the sampler interpolates the table (Catmull-Rom) at a
#: fractional phase after a change of rate, which reads a jerk step up to 4 % higher (measured on S-curves)
JERK_SHARE = 0.95
#: the largest speed and the acceleration it leaves are taken where their time is within this share of the lower
#: bound (every stretch of lines: no search)
TIGHT = 1e-3
#: below this share above the bound (lines: the curvature terms are small) the search starts on GRID_SIMPLE
SIMPLE = 0.02
GRID_SIMPLE = 12
#: rounds of reverting stretches whose rows exceed a target
MAX_ROUNDS = 3


@dataclass
class Stretch:
    a: int          #: grid point of the rest it leaves
    b: int          #: grid point of the rest it reaches
    s0: float       #: path position of ``a``
    D: float        #: length in s
    V: float = 0.0
    A: float = 0.0
    J: float = 0.0
    T: float = math.inf
    phase: tuple | None = None  #: the S-curve's phase durations (scurve.phases), once chosen


def stretches(path: P.Path, g: Grid, stop_idx: np.ndarray, holds_s: np.ndarray) -> list[tuple[Stretch, np.ndarray]]:
    """The stretches between consecutive rests with at most MAX_PIECES pieces of positive length and no hold
    inside (an event that does not stop the motion still holds the raw profile there), each with its pieces."""
    out = []
    held = np.concatenate([[0], np.cumsum(holds_s > 0)])
    for a, b in zip(stop_idx[:-1].tolist(), stop_idx[1:].tolist()):
        s0, s1 = float(g.sg[a]), float(g.sg[b])
        if s1 <= s0:
            continue
        lo = int(np.searchsorted(g.sg, s0, side="right"))
        hi = int(np.searchsorted(g.sg, s1, side="left"))
        if held[hi] - held[lo] > 0:
            continue
        tol = 1e-12 * (1.0 + abs(s1))
        m = np.arange(int(g.pidx[a]), int(g.pidx[b]) + 1)
        m = m[(path.slen[m] > 0) & (path.s0[m] >= s0 - tol) & (path.s0[m] + path.slen[m] <= s1 + tol)]
        if 0 < m.size <= MAX_PIECES:
            out.append((Stretch(a, b, s0, s1 - s0), m))
    return out


def _samples(path: P.Path, hx, cfg, pieces: list[np.ndarray]):
    """Bounds on the parts of every piece of every stretch from derivatives at SAMPLES fractions of it: a line is
    one part (its largest values), any other piece one part per sample.  Returns (a1, a2, a3, step, vcap, first
    part of each stretch): |L'|, |L''|, |L'''| (n,6; on a line each at its own worst sample, which only makes the
    inequalities stricter), the curvature steps |dL''| (n,6) at the junctions inside a stretch, and the feed /
    angular speed cap (n,)."""
    m = np.concatenate(pieces)
    u = np.linspace(0.0, 1.0, SAMPLES)
    pidx = np.repeat(m, SAMPLES)
    sg = path.s0[pidx] + np.tile(u, m.size) * path.slen[pidx]
    n = sg.shape[0]
    dv = derivatives(path, hx, Grid(sg, pidx, np.zeros(max(n - 1, 0)), np.zeros(0, dtype=np.int64),
                                    np.zeros(0), np.zeros(0)))
    vc = np.sqrt(feed_angular_limits(path, cfg, pidx, dv.dtip, dv.Xg)).reshape(m.size, SAMPLES)
    d3 = [np.abs(d).reshape(m.size, SAMPLES, 6) for d in (dv.Lp, dv.Lpp, dv.Lppp)]
    line = path.kind[m] == P.LINE
    nparts = np.where(line, 1, SAMPLES)
    first_part = np.concatenate([[0], np.cumsum(nparts)[:-1]])
    N = int(nparts.sum())
    a = [np.empty((N, 6)) for _ in range(3)]
    vcap = np.empty(N)
    other = (first_part[~line][:, None] + np.arange(SAMPLES)[None]).ravel()
    for out, d in zip(a, d3):
        out[first_part[line]] = d[line].max(axis=1)
        out[other] = d[~line].reshape(-1, 6)
    vcap[first_part[line]] = vc[line].min(axis=1)
    vcap[other] = vc[~line].ravel()
    step = np.zeros((N, 6))
    first = np.concatenate([[0], np.cumsum([p.size for p in pieces])[:-1]])
    inner = np.ones(m.size, dtype=bool)
    inner[first] = False                               # a stretch's first piece starts at a rest
    k = np.nonzero(inner)[0]                           # pieces that follow another in their stretch
    if k.size:
        d = np.abs(dv.Lpp[k * SAMPLES] - dv.Lpp[k * SAMPLES - 1])
        step[first_part[k]] = np.maximum(step[first_part[k]], d)
        step[first_part[k] - 1] = np.maximum(step[first_part[k] - 1], d)
    return a[0], a[1], a[2], step, vcap, first_part[first]


def _on_parts(X, seg, n: int):
    """Per-stretch values (C, S) repeated onto the n parts of the stretches (C, n, 1)."""
    return np.repeat(X, np.diff(np.append(seg, n)), axis=1)[:, :, None]


def _accel_at(V, seg, a1, a2, amax):
    """The largest A (C, S) that ``|L'| A + |L''| V^2 <= ETA a`` leaves at speeds V (C, S); <= 0: none."""
    Vs = _on_parts(V, seg, a1.shape[0])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ra = ETA * amax[None, None] - a2[None] * Vs * Vs
        A = np.where(a1[None] > 1e-12, ra / np.maximum(a1[None], 1e-300), np.where(ra >= 0, _BIG, -_BIG)).min(axis=2)
    return np.minimum(np.minimum.reduceat(A, seg, axis=1), _BIG)


def _limits_at(V, A, seg, a1, a2, a3, step, amax, jmax, dt):
    """For candidate speeds V and accelerations A (C, S): the largest J the jerk inequality leaves on every part
    of each stretch; 0 where none, or where ``|L'| A + |L''| V^2 <= ETA a`` fails on a part."""
    Vs = _on_parts(V, seg, a1.shape[0])
    As = _on_parts(A, seg, a1.shape[0])
    inv = np.where(a1 > 1e-12, 1.0 / np.maximum(a1, 1e-300), 0.0)[None]
    V2 = Vs * Vs
    ok_a = (a1[None] * As + a2[None] * V2 <= ETA * amax[None, None]).all(axis=2)
    rj = JERK_SHARE * ETA * jmax[None, None] - 3.0 * a2[None] * Vs * As - a3[None] * V2 * Vs - step[None] * V2 / dt
    J = np.where(inv > 0, rj * inv, np.where(rj >= 0, _BIG, -_BIG)).min(axis=2)
    Jm = np.minimum.reduceat(J, seg, axis=1)
    okm = np.minimum.reduceat(ok_a.astype(np.int8), seg, axis=1) > 0
    return np.where(okm & (Jm > 0), np.minimum(Jm, _BIG), 0.0)


_BIG = 1e30


def _time(D, V, A, J):
    ok = (A > 0) & (J > 0) & (V > 0)
    return np.where(ok, scurve.move_time(D, np.where(ok, V, 1.0), np.where(ok, A, 1.0), np.where(ok, J, 1.0)),
                    np.inf)


def fit_bounds(st: list[Stretch], pieces: list[np.ndarray], path: P.Path, hx, cfg, lims, dt: float,
               t_max: np.ndarray) -> None:
    """Sets V, A, J and T of every stretch: the speed V and acceleration A of shortest time (J the largest they
    leave).  T stays inf where even a lower bound of it exceeds ``t_max`` (per stretch, s).  Where the largest
    V and the A it leaves come within TIGHT of that lower bound they are taken; elsewhere searched on a grid of
    log V and log A and finer grids around the best."""
    a1, a2, a3, step, vcap, seg = _samples(path, hx, cfg, pieces)
    vmax, amax, jmax = lims
    cnt = np.diff(np.append(seg, a1.shape[0]))
    with np.errstate(divide="ignore"):
        def worst(x):
            return np.minimum.reduceat(x.min(axis=1), seg)
        vhi = np.minimum.reduceat(np.minimum(_per(a1, ETA_V * 0.995 * vmax).min(axis=1), vcap), seg)
        ahi = worst(_per(a1, ETA * amax))
        jhi = worst(_per(a1, JERK_SHARE * ETA * jmax))
        # every feasible V also keeps |L''| V^2 < ETA a and |L'''| V^3 < ETA j on its own
        vub = np.minimum(vhi, np.minimum(worst(np.sqrt(_per(a2, ETA * amax))),
                                         worst(np.cbrt(_per(a3, JERK_SHARE * ETA * jmax)))))
    D = np.array([s.D for s in st])
    ok = np.isfinite(vhi) & (vhi > 0) & np.isfinite(ahi) & (ahi > 0) & np.isfinite(jhi) & (jhi > 0)
    vhi, ahi, jhi, vub = (np.where(ok, x, 1.0) for x in (vhi, ahi, jhi, vub))
    T = np.full(D.size, np.inf)
    V, A, J = np.zeros(D.size), np.zeros(D.size), np.zeros(D.size)
    t_lb = np.where(ok, _time(D, vub, ahi, jhi), np.inf)
    # the largest speed and the acceleration it leaves
    Ac = _accel_at(vhi[None], seg, a1, a2, amax)[0]
    Jc = _limits_at(vhi[None], Ac[None], seg, a1, a2, a3, step, amax, jmax, dt)[0]
    Tc = _time(D, vhi, Ac, Jc)
    near = ok & (Tc <= t_lb * (1.0 + TIGHT))
    T, V, A, J = (np.where(near, x, y) for x, y in ((Tc, T), (vhi, V), (Ac, A), (Jc, J)))
    todo = ok & ~near & (t_lb < t_max)
    # where the largest speed is within SIMPLE of the bound the optimum lies near it: a coarser first grid finds it
    for grid, sel in ((GRID_SIMPLE, todo & (Tc <= t_lb * (1.0 + SIMPLE))), (GRID, todo & (Tc > t_lb * (1.0 + SIMPLE)))):
        idx = np.nonzero(sel)[0]
        if idx.size:
            pm = np.repeat(sel, cnt)
            sub = [x[pm] for x in (a1, a2, a3, step)]
            sseg = np.concatenate([[0], np.cumsum(cnt[idx])[:-1]])
            T[idx], V[idx], A[idx], J[idx] = _search(D[idx], vhi[idx], ahi[idx], sseg, sub, amax, jmax, dt, grid)
    for k, s in enumerate(st):
        s.V, s.A, s.J, s.T = float(V[k]), float(A[k]), float(J[k]), float(T[k])


def _per(a: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """lim / a per part and strut (inf where a strut does not move)."""
    return np.where(a > 1e-12, lim[None] / np.maximum(a, 1e-300), np.inf)


def _search(D, vhi, ahi, seg, parts, amax, jmax, dt, grid):
    """(T, V, A, J) of shortest time per stretch.  For a given V the time is unimodal in A on the accelerations
    that leave some jerk (golden section); over V a scan below the largest feasible speed, then finer scans
    around the best (its optimum often lies right under that speed, where the feasible A narrow)."""
    a1, a2, a3, step = parts
    n = a1.shape[0]
    chunk = max(1, CHUNK_VALUES // (6 * n))
    vf = _v_feasible(vhi, seg, parts, amax, jmax, dt)

    def inner(V):
        """Best time and A (C, S) at speeds V (C, S)."""
        T, A = np.empty(V.shape), np.empty(V.shape)
        for c0 in range(0, V.shape[0], chunk):
            v = V[c0:c0 + chunk]
            top = np.minimum(_accel_at(v, seg, a1, a2, amax), _accel_jerk0(v, seg, a1, a2, a3, step, jmax, dt))
            top = np.where(top > 0, np.minimum(top, ahi[None]), 0.0)

            def t_of(y, v=v, top=top):
                a = top * np.exp(y)
                return _time(D[None], v, a, _limits_at(v, a, seg, a1, a2, a3, step, amax, jmax, dt))
            y, t = _golden(t_of, np.full(v.shape, math.log(A_RANGE)), np.full(v.shape, -1e-9), GOLDEN_STEPS)
            T[c0:c0 + chunk], A[c0:c0 + chunk] = t, top * np.exp(y)
        return T, A

    lo, hi = np.full(D.size, math.log(V_RANGE)), np.full(D.size, -1e-9)
    best_t, best_x = np.full(D.size, np.inf), hi.copy()
    for z in range(ZOOMS + 1):
        m = grid if z == 0 else ZOOM_POINTS
        x = lo[None] + np.linspace(0.0, 1.0, m)[:, None] * (hi - lo)[None]
        T, _A = inner(vf[None] * np.exp(x))
        k = T.argmin(axis=0)
        t = T[k, np.arange(D.size)]
        better = t < best_t
        best_t, best_x = np.where(better, t, best_t), np.where(better, x[k, np.arange(D.size)], best_x)
        cell = (hi - lo) / (m - 1)
        lo, hi = best_x - cell, np.minimum(best_x + cell, -1e-9)
    V = vf * np.exp(best_x)
    T, A = inner(V[None])
    J = _limits_at(V[None], A, seg, a1, a2, a3, step, amax, jmax, dt)[0]
    return T[0], V, A[0], J


def _golden(f, lo, hi, steps: int):
    """Minimum of f over [lo, hi] elementwise (golden section on a unimodal f); returns (x, f(x))."""
    r = 0.5 * (math.sqrt(5.0) - 1.0)
    x1, x2 = hi - r * (hi - lo), lo + r * (hi - lo)
    f1, f2 = f(x1), f(x2)
    for _ in range(steps):
        left = f1 <= f2
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        xn = np.where(left, hi - r * (hi - lo), lo + r * (hi - lo))
        fn = f(xn)
        x1, x2 = np.where(left, xn, x2), np.where(left, x1, xn)
        f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
    return np.where(f1 <= f2, x1, x2), np.minimum(f1, f2)


def _accel_jerk0(V, seg, a1, a2, a3, step, jmax, dt):
    """The A (C, S) at which the jerk inequality leaves no jerk at speeds V (C, S); <= 0: none at any A."""
    Vs = _on_parts(V, seg, a1.shape[0])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = JERK_SHARE * ETA * jmax[None, None] - a3[None] * Vs ** 3 - step[None] * Vs * Vs / dt
        d = 3.0 * a2[None] * Vs
        A0 = np.where(c <= 0, -_BIG, np.where(d > 0, c / np.where(d > 0, d, 1.0), _BIG)).min(axis=2)
    return np.minimum.reduceat(A0, seg, axis=1)


def _v_feasible(vhi, seg, parts, amax, jmax, dt):
    """The largest speed (S,) below which some A > 0 leaves some jerk: ``|L''| V^2 < ETA a`` and
    ``|L'''| V^3 + |dL''| V^2 / dt < JERK_SHARE ETA j`` on every part (bisection in log V)."""
    a1, a2, a3, step = parts
    lo, hi = np.log(vhi) + math.log(1e-9), np.log(vhi)

    def ok(x):
        V = np.exp(x)[None]
        return ((_accel_at(V, seg, a1, a2, amax) > 0) & (_accel_jerk0(V, seg, a1, a2, a3, step, jmax, dt) > 0))[0]
    top = ok(hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        good = ok(mid)
        lo, hi = np.where(good, mid, lo), np.where(good, hi, mid)
    return np.where(top, vhi, np.exp(lo))


def _n_rows(T: float, dt: float) -> int:
    """Moving rows of an S-curve of T seconds (after the row at rest, before the one that arrives)."""
    return max(1, int(math.ceil(T / dt - 1e-9))) - 1


def _rows(st: Stretch, sg_b: float, dt: float) -> np.ndarray:
    """Positions of the S-curve's moving rows (:func:`_n_rows` of them)."""
    t = dt * np.arange(1, _n_rows(st.T, dt) + 1)
    return np.minimum(st.s0 + scurve.positions(st.D, st.V, st.A, st.J, t, st.phase), sg_b)


def _first_moving(s_f: np.ndarray, s0: float) -> int:
    """First row of the table past the rest at s0."""
    return int(np.searchsorted(s_f, s0, side="right"))


def _at(sg: np.ndarray, k: int) -> tuple[int, int]:
    """The grid points at the position of point k (a stop's duplicated junction points): [lo, hi)."""
    return int(np.searchsorted(sg, sg[k], side="left")), int(np.searchsorted(sg, sg[k], side="right"))


def _rest_rows(hold_s: float, nf: int, dt: float) -> int:
    """Rows at rest the filtered table has at a stop with raw hold ``hold_s``: the rows whose window lies inside
    the hold (the ones :func:`~hexacnc.planner.tables.row_tables` marks as the hold's) and the one after."""
    return max(1, int(math.floor(hold_s / dt + 1e-9)) - nf) + 1


def _group_rest(sg: np.ndarray, holds_s: np.ndarray, b: int, nf: int, dt: float) -> int:
    """:func:`_rest_rows` of all the holds at the position of grid point b (they may sit on its duplicates)."""
    lo, hi = _at(sg, b)
    return _rest_rows(float(holds_s[lo:hi].sum()), nf, dt)


def trim_start(s_f: np.ndarray, TH: np.ndarray, meas: tuple, sg: np.ndarray, holds_s: np.ndarray, nf: int,
               dt: float):
    """The table without the rows at rest before the first hold's rows: with events at the start the raw profile
    holds there first, and the moving average stands still for its whole width before the hold rows
    (:func:`~hexacnc.planner.holds.hold_rows`) begin.  Returns (table, raw times moved with the rows, measurement)."""
    lo, hi = _at(sg, 0)
    if not np.any(holds_s[lo:hi] > 0):
        return s_f, TH, meas
    r = min(hold_rows(TH[0], 0.0, dt, nf)[0], int(np.searchsorted(s_f, sg[0], side="right")) - 1)
    if r <= 0:
        return s_f, TH, meas
    return s_f[r:], TH - r * dt, tuple(m[r:] if isinstance(m, np.ndarray) else m for m in meas)


def trim_end(s_f: np.ndarray, TH: np.ndarray, meas: tuple, sg: np.ndarray, holds_s: np.ndarray, nf: int, dt: float):
    """The table without the rows at rest after the last stop's hold rows (:func:`_rest_rows`, counted from the
    row where the table reaches the end, :func:`~hexacnc.planner.holds.hold_rows`): the moving average stands still
    for its whole width after the raw hold.  Returns (table, measurement)."""
    lo = _at(sg, sg.shape[0] - 1)[0]
    n = hold_rows(TH[lo], 0.0, dt, nf)[0] + _group_rest(sg, holds_s, sg.shape[0] - 1, nf, dt)
    if n >= s_f.shape[0]:
        return s_f, meas
    return s_f[:n], tuple(m[:n] if isinstance(m, np.ndarray) else m for m in meas)


def splice(s_f: np.ndarray, TH: np.ndarray, chosen: list[Stretch], sg: np.ndarray, holds_s: np.ndarray, nf: int,
           dt: float):
    """The table with the moving rows of the chosen stretches replaced by their S-curves, each followed by the
    rows at rest its stop's holds ask of the filtered table (:func:`_group_rest`), whatever the phase of the old
    rows; elsewhere the old rows are kept, and their grid points' raw times move with them as a block.  Inside a
    stretch a point's raw time is the row where the table passes it, less the filter's half-width; at a stop the
    hold rows start at the arrival.  Returns (table, raw times, row ranges of the S-curves)."""
    parts, ranges = [], []
    TH2 = TH.copy()
    n_out, at, g_from = 0, 0, 0      # rows written, next old row to copy, first grid point not yet placed
    for st in chosen:
        i0 = _first_moving(s_f, st.s0)
        a_hi = _at(sg, st.a)[1]
        TH2[g_from:a_hi] = TH[g_from:a_hi] + (n_out - at) * dt
        parts.append(s_f[at:i0])
        n_out += i0 - at
        new = _rows(st, float(sg[st.b]), dt)
        ranges.append((n_out, n_out + new.size - 1))
        parts.append(new)
        b_lo, b_hi = _at(sg, st.b)
        k = np.arange(a_hi, b_lo)
        if k.size:
            r = n_out + np.searchsorted(np.append(new, sg[st.b]), sg[k], side="left")
            TH2[k] = np.maximum(r - nf // 2, 0) * dt
        n_out += new.size
        rest = _group_rest(sg, holds_s, st.b, nf, dt)
        parts.append(np.full(rest, sg[st.b]))
        TH2[b_lo:b_hi] = (n_out - nf) * dt + (TH[b_lo:b_hi] - TH[b_lo])
        n_out += rest
        at = int(np.searchsorted(s_f, sg[st.b], side="right"))      # the old rows' departure from that stop
        g_from = b_hi
    TH2[g_from:] = TH[g_from:] + (n_out - at) * dt
    parts.append(s_f[at:])
    return np.concatenate(parts), TH2, ranges


def rest_to_rest(path: P.Path, hx, cfg, g: Grid, stop_idx: np.ndarray, holds_s: np.ndarray, s_f, TH, meas,
                 measure, nf: int, dt: float, lims):
    """The verified table with every short stretch between rests that runs faster as an S-curve replaced by it
    (see the module docstring).  ``measure(table)``: the exact measurement (uv, ua, uj, ...).  Returns (table,
    raw times, measurement)."""
    cand = stretches(path, g, stop_idx, holds_s)
    if not cand:
        return s_f, TH, meas
    st = [c[0] for c in cand]
    # the old rows of each stretch: moving, and at rest at its stop until the next departure (or the end)
    old = np.array([int(np.searchsorted(s_f, g.sg[s.b], side="right")) - _first_moving(s_f, s.s0) for s in st])
    fit_bounds(st, [c[1] for c in cand], path, hx, cfg, lims, dt, (old + 1) * dt)
    chosen = [s for s, m in zip(st, old) if math.isfinite(s.T)
              and _n_rows(s.T, dt) + _group_rest(g.sg, holds_s, s.b, nf, dt) < m]
    if chosen:
        ph = scurve.phases(*(np.array([getattr(s, f) for s in chosen]) for f in "DVAJ"))
        for k, s in enumerate(chosen):
            s.phase = (ph[0][k], ph[1][k], ph[2][k])
    for _round in range(MAX_ROUNDS):
        if not chosen:
            return s_f, TH, meas
        table, TH2, ranges = splice(s_f, TH, chosen, g.sg, holds_s, nf, dt)
        m = measure(table)
        bad = (m[0] > ETA_V * 0.9995) | (m[1] > ETA) | (m[2] > ETA)
        if not bad.any():
            return table, TH2, m
        rows = np.nonzero(bad)[0]
        keep = []
        for s, (r0, r1) in zip(chosen, ranges):
            hit = np.any((rows >= r0 - 4) & (rows <= r1 + 4))
            if not hit:
                keep.append(s)
        if len(keep) == len(chosen):       # the violation is not the S-curves': keep the verified table
            return s_f, TH, meas
        chosen = keep
    return s_f, TH, meas
