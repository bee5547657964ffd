"""Whole-program planning: path -> limit check -> time parameterisation -> verified setpoint table.

Method (see docs/planner.md):

1. :func:`~hexacnc.planner.path.build_path` turns blocks into pieces with C1
   corner blends inside the G64 P tolerance (rotations included).
2. A grid in ``s`` whose spacing bounds the strut-length error between samples
   by ``[planner] sample_bound_mm`` (and joint angles by ``G h / 2``): strut
   lengths and joint angles are checked on it with the limits shrunk by those
   bounds; the first violation is a :class:`PlanError` naming line and limit.
3. Strut derivatives ``L'``, ``L''``, ``L'''`` by central differences of the
   inverse kinematics; a forward-backward pass on ``s_dot^2`` over the whole
   program (TOPP) under feed, rapid, angular-velocity, strut velocity and
   acceleration limits, a curvature-jerk bound and a path-acceleration cap that
   keeps the filter's jerk within the limit).
4. The profile ``s(t)`` sampled at the cycle period and smoothed by a moving
   average of width ``w = max(A/J) / 0.9``; no window holds an acceleration
   reversal: slow spots are spread over the window's reach and every speed peak
   is capped to a plateau of at least ``w`` (stops are holds of at least ``w`` so
   the smoothed motion really stops there).
5. The struts of the resulting table are measured (finite differences at the
   cycle period); where velocity, acceleration or jerk utilisation exceeds its
   target the speed limit (at jerk-only violations also the acceleration cap) is
   lowered locally and steps 3-5 repeat.  The reported peak utilisations are
   these measurements.

Acceleration and jerk are planned to at most ``ETA`` (0.95) of the limits: the
rest is the headroom the sampler uses for jerk-limited override, pause and stop
transitions.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import PlanError
from ..gcode import blocks as B
from ..kinematics import Hexapod
from . import path as P
from .topp import interval_times
from .toppvec import WavefrontTopp, accel_coefficients

#: fraction of the acceleration and jerk limits the nominal plan may use
ETA = 0.95
#: fraction of the velocity limit the nominal plan may use
ETA_V = 1.0
#: share of the jerk limit a full acceleration change through the smoothing filter may take: the moving
#: average's width is ``w = max(a_max / j_max) / FILTER_JERK_SHARE`` (a one-sided change of the path
#: acceleration by A then gives path jerk A / w; reversals are kept out of every window by plateaus)
FILTER_JERK_SHARE = 0.9
#: share of the jerk limit the acceleration cap leaves to the filter and curvature terms together
RHO_CAP = 1.0
#: bisection steps of the peak caps (level resolution 2^-n of the peak's height above its valleys)
CAP_BISECT = 14
#: a jerk-only violation lowers the acceleration cap by the verification's factor f and the speed limit
#: by f ** CAP_JERK_SPEED (the filter's |L'| du / w hardly changes with speed)
CAP_JERK_SPEED = 0.75
#: reach of the spreading, in filter widths (w/2 plus 10 %: at the reach's end the filter's transition
#: still adds jerk where the curvature term is near its share)
SPREAD_REACH = 0.55
#: rounds of peak caps per pass (a re-solve moves a ramp by up to a grid step: the second catches that)
CAP_ROUNDS = 2
#: share of the jerk limit the curvature term |L'''| s_dot^3 may take in the TOPP pass
RHO_J = 0.9     # 0.9: 3D_Chips 1.5 % shorter than at 0.8; the verification keeps the total jerk <= ETA
#: share of the jerk limit an acceleration step at a junction may take
RHO_STEP = 0.5
#: share of the planned acceleration (ETA a_max) the TOPP pass may use (the rest absorbs smoothing)
ACC_SHARE = 0.97
#: extra grid offsets from both ends of every piece (s-units)
GRADE_MM = np.array([0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5])
#: samples whose interval bound stays below this are not measured by exact inverse kinematics
SCREEN = 0.5
#: s step of the central differences (mm or deg)
FD_STEP = 0.01
#: thresholds above which a model pass evaluates a sample (v, a, j): its violation thresholds
#: (the bounds are upper bounds of the model, so a sample below them cannot violate), 1e-9 lower
MODEL_SCREEN = (ETA_V * 0.9995 * (1 - 1e-9), ETA * (1 - 1e-9), ETA * (1 - 1e-9))
#: samples per chunk of the exact measurement (bounds its memory)
EXACT_CHUNK = 50_000

_DEBUG = bool(__import__('os').environ.get('HEXACNC_PLAN_DEBUG'))

FLAG_MOTION = 1
FLAG_RAPID = 2
FLAG_DWELL = 4
FLAG_PROGRAM_PAUSE = 8
FLAG_PAUSED = 16
FLAG_STOPPING = 32
FLAG_END = 64
FLAG_EVENT = 128


@dataclass
class Hold:
    grid: int                  #: hold after grid point
    seconds: float             #: extra standstill beyond the filter's minimum
    line: int
    pause: bool = False        #: M0 (or M1 with optional stop) waits for resume
    optional: bool = False
    kinds: list = field(default_factory=list)


class Plan:
    """A planned program: a setpoint table at ``dt`` plus a summary.

    Attributes: ``duration_s``, ``utilisation`` (dict of peak strut velocity,
    acceleration and jerk as fractions of each limit), ``min_joint_margin_deg``,
    ``min_length_margin_mm``, ``line_times`` {line: (start_s, end_s)},
    ``events`` [(time_s, line, kind, value)], ``planning_s``.
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    # -- evaluation -----------------------------------------------------------------
    def platform_at(self, s: np.ndarray) -> np.ndarray:
        """Platform poses (N,6) mm/rad at path positions ``s``."""
        s = np.asarray(s, dtype=float)
        return self.path.platform(self.path.piece_at(s), s)

    def rows(self) -> np.ndarray:
        """The whole nominal table as rows [x,y,z,a,b,c(rad),line,flags] (override 1, no pauses)."""
        X = self.platform_at(self.s_tab)
        return np.hstack([X, self.line_tab[:, None].astype(float), self.flag_tab[:, None].astype(float)])

    def sampler(self, period_s: float | None = None, optional_stop: bool = False):
        """Runtime sampler (see :class:`hexacnc.planner.sampler.PlanSampler`)."""
        from .sampler import PlanSampler
        return PlanSampler(self, self.dt if period_s is None else float(period_s), optional_stop=optional_stop)

    @property
    def start_pose_platform(self) -> np.ndarray:
        """(6,) platform pose at the start, mm / rad."""
        return self.platform_at(np.array([0.0]))[0]

    @property
    def end_pose_platform(self) -> np.ndarray:
        return self.platform_at(np.array([self.path.total]))[0]

    def summary(self) -> dict:
        """JSON-ready summary (mm, s, degrees)."""
        return {
            "ok": True,
            "duration_s": round(self.duration_s, 6),
            "utilisation": {k: round(float(v), 6) for k, v in self.utilisation.items()},
            "min_joint_margin_deg": round(self.min_joint_margin_deg, 6),
            "min_length_margin_mm": round(self.min_length_margin_mm, 6),
            "segments": int(self.n_segments),
            "blends": int(self.n_blends),
            "stops": int(self.n_stops),
            "path_length": round(self.path.total, 6),
            "grid_points": int(self.grid_points),
            "sample_bound_mm": self.sample_bound_mm,
            "planning_s": round(self.planning_s, 4),
            "iterations": int(self.iterations),
            "lines": {str(k): [round(a, 4), round(b, 4)] for k, (a, b) in sorted(self.line_times.items())},
        }


# ---------------------------------------------------------------------------
def _strut_geometry(X: np.ndarray, hx: Hexapod):
    """Per strut k (lists of 6): unit vectors ``u[k]`` (3 arrays (N,)), lengths ``L`` (N,6), the joint-angle
    cosines ``cb``, ``cp`` (N,6) and the Jacobian (N,6,6) rows ``[u, (R p_k) x u / char_length]``
    for platform poses X (N,6) mm/rad.  Component-wise on (N,) arrays: no (N,6,3) temporaries."""
    r = P.rot_elems(X[:, 3:])
    N = X.shape[0]
    L = np.empty((N, 6))
    cb = np.empty((N, 6))
    cp = np.empty((N, 6))
    Jt = np.empty((6, 6, N))                  # strut, column, pose: contiguous writes
    cl = 1.0 / hx.char_length_mm
    for k in range(6):
        px, py, pz = hx.plat[k]
        ax, ay, az = hx.plat_axes[k]
        rx = r[0] * px + r[1] * py + r[2] * pz
        ry = r[3] * px + r[4] * py + r[5] * pz
        rz = r[6] * px + r[7] * py + r[8] * pz
        sx = X[:, 0] + rx - hx.base[k, 0]
        sy = X[:, 1] + ry - hx.base[k, 1]
        sz = X[:, 2] + rz - hx.base[k, 2]
        lk = np.sqrt(sx * sx + sy * sy + sz * sz)
        L[:, k] = lk
        inv = 1.0 / lk
        ux, uy, uz = sx * inv, sy * inv, sz * inv
        bx, by, bz = hx.base_axes[k]
        cb[:, k] = ux * bx + uy * by + uz * bz
        # platform joint: -u . (R a_k)
        cp[:, k] = -(ux * (r[0] * ax + r[1] * ay + r[2] * az) + uy * (r[3] * ax + r[4] * ay + r[5] * az)
                     + uz * (r[6] * ax + r[7] * ay + r[8] * az))
        Jk = Jt[k]
        Jk[0] = ux
        Jk[1] = uy
        Jk[2] = uz
        Jk[3] = (ry * uz - rz * uy) * cl
        Jk[4] = (rz * ux - rx * uz) * cl
        Jk[5] = (rx * uy - ry * ux) * cl
    np.clip(cb, -1.0, 1.0, out=cb)
    np.clip(cp, -1.0, 1.0, out=cp)
    return L, cb, cp, Jt.transpose(2, 0, 1)


def condition_numbers(J: np.ndarray, limit: float) -> np.ndarray:
    """Spectral condition numbers of the square matrices J (N,n,n) where they may exceed ``limit``.

    With singular values s_1 >= .. >= s_n, ``|det J| = prod s_i``, ``s_1^2 <= F^2 = ||J||_F^2`` and
    (AM-GM) ``prod_{i<n} s_i^2 <= (F^2 / (n-1))^(n-1)``, so
    ``cond = s_1 / s_n = s_1 prod_{i<n} s_i / |det J| <= F^n / ((n-1)^((n-1)/2) |det J|)``.
    Where this bound is at most ``limit`` it is returned (the pose passes either way); elsewhere the
    exact value from the eigenvalues of ``J^T J`` (inf where singular).
    """
    n = J.shape[-1]
    F2 = np.einsum("nij,nij->n", J, J)
    with np.errstate(all="ignore"):
        det = np.abs(np.linalg.det(J))
        out = F2 ** (0.5 * n) / ((n - 1) ** (0.5 * (n - 1)) * det)
    todo = np.nonzero(~(out <= limit))[0]           # NaN / inf included
    if todo.size:
        Jt = J[todo]
        with np.errstate(all="ignore"):
            ev = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", Jt, Jt))      # singular values squared
            c = np.sqrt(ev[:, -1] / np.maximum(ev[:, 0], 1e-300))
        out[todo] = np.where(ev[:, 0] > 0, c, np.inf)
    return out


def _check_limits(path: P.Path, hx: Hexapod, cfg, sg, pidx, Xg, lmarg, amarg):
    """Strut lengths and joint angles on the grid with the limits shrunk by the sampling bounds.

    Returns (min joint margin deg, min length margin mm); raises PlanError at the first violation.
    """
    L, cb, cp, J = _strut_geometry(Xg, hx)
    ab = np.arccos(cb)
    ap = np.arccos(cp)
    lm = lmarg[pidx][:, None]
    am = amarg[pidx][:, None]
    lo = L - lm - hx.min_length[None]
    hi = hx.max_length[None] - (L + lm)
    amax = hx.max_angle_rad[None]
    jb = amax - (ab + am)
    jp = amax - (ap + am)
    # singularity (checked at the samples; a cheap upper bound, exact values only where it is inconclusive)
    cond = condition_numbers(J, hx.max_condition)
    bad = (np.any(lo < 0, axis=1) | np.any(hi < 0, axis=1) | np.any(jb < 0, axis=1) | np.any(jp < 0, axis=1)
           | ~np.isfinite(cond) | (cond > hx.max_condition))
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        m = int(pidx[k])
        line = int(path.line[m])
        tip = path.tip(np.array([m]), np.array([sg[k]]))[0]
        where = (f"at tool tip [{tip[0]:.3f}, {tip[1]:.3f}, {tip[2]:.3f}] mm, "
                 f"[{math.degrees(tip[3]):.3f}, {math.degrees(tip[4]):.3f}, {math.degrees(tip[5]):.3f}] deg")
        for i in range(6):
            if lo[k, i] < 0:
                raise PlanError(f"strut {i + 1} length {L[k, i]:.4f} mm (+-{lm[k, 0]:.4g} mm sampling bound) "
                                f"below min_length_mm {hx.min_length[i]:g} {where}", line=line,
                                limit=f"strut {i + 1} min_length_mm")
            if hi[k, i] < 0:
                raise PlanError(f"strut {i + 1} length {L[k, i]:.4f} mm (+-{lm[k, 0]:.4g} mm sampling bound) "
                                f"above max_length_mm {hx.max_length[i]:g} {where}", line=line,
                                limit=f"strut {i + 1} max_length_mm")
        for i in range(6):
            lim = math.degrees(hx.max_angle_rad[i])
            if jb[k, i] < 0:
                raise PlanError(f"base joint {i + 1} angle {math.degrees(ab[k, i]):.4f} deg "
                                f"(+{math.degrees(am[k, 0]):.4g} deg sampling bound) over max_angle_deg {lim:g} "
                                f"{where}", line=line, limit=f"base joint {i + 1} max_angle_deg")
            if jp[k, i] < 0:
                raise PlanError(f"platform joint {i + 1} angle {math.degrees(ap[k, i]):.4f} deg "
                                f"(+{math.degrees(am[k, 0]):.4g} deg sampling bound) over max_angle_deg {lim:g} "
                                f"{where}", line=line, limit=f"platform joint {i + 1} max_angle_deg")
        raise PlanError(f"near-singular pose: Jacobian condition {cond[k]:.4g} over max_condition "
                        f"{hx.max_condition:g} {where}", line=line, limit="max_condition")
    jm = float(np.degrees(min(jb.min(), jp.min()))) if jb.size else math.nan
    lmm = float(min(lo.min(), hi.min())) if lo.size else math.nan
    return jm, lmm


def _dilate_min(sg: np.ndarray, x: np.ndarray, T: float, max_span: int = 4000) -> np.ndarray:
    """Spread every speed limit over the distance travelled at that speed in the filter window.

    The moving average of width T gives, at position s_j, the mean raw speed of the
    positions passed within T.  If the raw speed is at most sqrt(x_j) for all
    positions within ``r_j = sqrt(x_j) T/2`` of s_j (the window spans T/2 either side of its centre),
    that mean is at most sqrt(x_j):
    so ``x_k <= x_j`` wherever ``|s_k - s_j| <= r_j``.  Slow spots have short reach.
    """
    N = x.shape[0]
    fin = np.isfinite(x)
    r = np.where(fin, np.sqrt(np.maximum(x, 0.0)) * T, 0.0)
    lo = np.searchsorted(sg, sg - r, side="left")
    hi = np.searchsorted(sg, sg + r, side="right") - 1
    cnt = np.minimum(hi - lo + 1, max_span)
    # only limits lower than some point in their reach matter
    j = np.nonzero(fin & (cnt > 1))[0]
    out = x.copy()
    if j.size == 0:
        return out
    # every range [lo_j, lo_j + cnt_j) is the union of two power-of-two blocks; the minimum over
    # the blocks starting at each point is pushed down level by level (the same minima as a
    # scatter over every point of every range, in O(N log max_span))
    a = lo[j]
    cj = cnt[j]
    xj = x[j]
    lev = np.floor(np.log2(cj)).astype(np.int64)
    top = int(lev.max())
    tab = [None] * (top + 1)
    for L in range(top, -1, -1):
        cur = np.full(N, np.inf) if tab[L] is None else tab[L]
        m = np.nonzero(lev == L)[0]
        if m.size:
            np.minimum.at(cur, a[m], xj[m])
            np.minimum.at(cur, a[m] + cj[m] - (1 << L), xj[m])
        if L == 0:
            np.minimum(out, cur, out=out)
            break
        hh = 1 << (L - 1)
        nxt = cur.copy()
        np.minimum(nxt[hh:], cur[:-hh], out=nxt[hh:])
        tab[L - 1] = nxt
        tab[L] = None
    return out


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


def _with_accel_cap(c, e, d, ecap):
    """The acceleration bounds with one more row ``-ecap <= u <= ecap`` and the speed limit (N,) at which
    some strut's bound leaves that range (``c_i + d_i x <= ecap`` and ``e_i + d_i x >= -ecap``)."""
    N, m = c.shape
    xcap = np.full(N, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(m):
            ad = np.abs(d[:, i])
            ok = ad > 1e-15
            np.minimum(xcap, np.where(ok, (e[:, i] + ecap) / np.where(ok, ad, 1.0), np.inf), out=xcap)
    c7 = np.empty((N, m + 1))
    e7 = np.empty((N, m + 1))
    d7 = np.zeros((N, m + 1))
    c7[:, :m] = c
    c7[:, m] = -ecap
    e7[:, :m] = e
    e7[:, m] = ecap
    d7[:, :m] = d
    return c7, e7, d7, xcap


def _cap_peaks(h: np.ndarray, x: np.ndarray, w: float):
    """Speed caps (x units, per grid point; inf where none) that give every speed peak of the profile x
    a plateau of at least ``w`` seconds, so that a moving average of width ``w`` never holds an
    acceleration reversal; and the hill number of each grid point.

    A hill runs from one local minimum of x to the next; its cap is the highest level L (bisection)
    whose plateau, from the first grid point at or above L on the way up to the last one on the way
    down, lasts at least w at speed L (the capped profile reaches L at those points: it did before).
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
        """The plateau at level L (between the crossing grid points) lasts at least w at speed L."""
        a = np.minimum(np.searchsorted(key_r, hid + L / scale, side="left"), ri.size - 1)
        b = np.minimum(np.searchsorted(key_f, (H - 1 - hid) + L / scale, side="left"), fi.size - 1)
        return S[fi[b]] - S[ri[a]] >= w * L

    cap = np.full(H, np.inf)
    hid = np.arange(H)
    hid = hid[(vpk > 0) & ~long_enough(hid, vpk)]           # the others have their plateau already
    if hid.size:
        v_lo = np.minimum(np.maximum(v[hs[hid]], v[he[hid]]), vpk[hid])
        short = ~long_enough(hid, v_lo)
        # a hill too short for a plateau above its higher valley is flattened to that valley (it joins
        # its neighbour); between two stops it gets the highest plateau it can hold
        lo = np.where(short & (v_lo > 0), v_lo, np.where(short, 0.0, v_lo))
        hi = np.where(short & (v_lo > 0), v_lo, vpk[hid])
        for _ in range(CAP_BISECT):
            mid = 0.5 * (lo + hi)
            ok = long_enough(hid, mid)
            lo = np.where(ok, mid, lo)
            hi = np.where(ok, hi, mid)
        cap[hid] = np.where(lo > 0, lo, np.inf)        # no plateau possible on the grid: left to the checks
    return cap[hill] ** 2, hill


def _cap_round(h, x, w, spans=None, max_spans: int = 64):
    """One round of peak caps on the whole profile (``spans`` None) or on grid ranges that start and end
    at a valley.  Returns (mask of the grid points of the hills that need a cap, caps (N,) valid there),
    or (None, None) when every peak has its plateau."""
    N = x.shape[0]
    if spans is not None and len(spans) <= max_spans:
        region = np.zeros(N, dtype=bool)
        cap = np.full(N, np.inf)
        for a0, a1 in spans:
            if a1 <= a0:
                continue
            c, hill = _cap_peaks(h[a0:a1], x[a0:a1 + 1], w)
            more = c < x[a0:a1 + 1] * (1 - 1e-9)
            if more.any():
                hm = np.zeros(int(hill[-1]) + 1, dtype=bool)
                hm[hill[more]] = True
                sub = hm[hill]
                region[a0:a1 + 1] |= sub
                cap[a0:a1 + 1] = np.where(sub, c, cap[a0:a1 + 1])
        return (region, cap) if region.any() else (None, None)
    cap, hill = _cap_peaks(h, x, w)
    more = cap < x * (1 - 1e-9)
    if not more.any():
        return None, None
    hm = np.zeros(int(hill[-1]) + 1, dtype=bool)
    hm[hill[more]] = True
    return hm[hill], cap


def _runs(mask: np.ndarray) -> list:
    """Inclusive (first, last) index pairs of the runs of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0].tolist(), (np.nonzero(d == -1)[0] - 1).tolist()))


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
    Ng = sg.shape[0]
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
        return (*res, idx.size)
    g = np.clip(np.searchsorted(sg, s_f, side="right") - 1, 0, sg.shape[0] - 2)
    res = list(bounds.at(g, sd, sdd, sddd, extras=True))      # governor ratios for the final table
    need = (res[0] > screen) | (res[1] > screen) | (res[2] > screen)
    need[_near_junctions(sg, s_f, sd)] = True
    need[_on_short_pieces(path, s_f, sd)] = True
    idx = np.nonzero(need)[0]
    if idx.size == 0:
        return (*res, 0)
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
            arr[ek] = _rowmax(M, lim)
    return (*res, idx.size)


def _sample_profile(sg, h, x, holds_s, dt):
    """Raw s(t) at dt from grid speeds x and holds (seconds after each grid point)."""
    N = sg.shape[0]
    D = interval_times(h, x)                       # (N-1,)
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


def plan_program(blocks, cfg, hexapod: Hexapod | None = None, period_s: float | None = None) -> Plan:
    """Plan a whole program (list of :class:`~hexacnc.gcode.blocks.Block`) for the machine ``cfg``.

    Raises :class:`PlanError` (line, limit) at the first strut-length, joint-angle
    or singularity violation along the path, or for bad input.
    """
    t_start = time.perf_counter()
    hx = hexapod if hexapod is not None else Hexapod(cfg)
    dt = float(period_s if period_s is not None else cfg.cycle.period_s)
    pc = cfg.planner
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float)
    jmax = np.asarray(cfg.max_jerk_mm_s3, dtype=float)
    path, events = P.build_path(blocks, cfg)
    w_f = float(np.max(amax / jmax)) / FILTER_JERK_SHARE
    nf = max(1, int(math.ceil(w_f / dt)))
    hold_min = nf * dt + 2 * dt      # the smoothed motion rests for at least two cycles at a stop
    w_plateau = nf * dt + 2 * dt     # raw plateau at every speed peak (two cycles of rounding margin)

    if path.n == 0:
        # no motion: a standstill at the start pose (if any) for dwells
        raise PlanError("program has no motion", line=None, limit="input", code="empty")

    # ---- grid -----------------------------------------------------------------
    h_p, nint, lmarg, amarg = P.sample_spacing(path, hx.plat, float(np.min(hx.min_length)), pc.sample_bound_mm)
    # uniform samples at the bounded spacing plus a geometric refinement near both ends of each
    # piece (speed changes concentrate there; extra samples only tighten the bound)
    pidx, u_loc, counts = P.grid_offsets(path, h_p, nint, GRADE_MM)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sg = path.s0[pidx] + u_loc
    last = first + counts - 1
    sg[last] = path.s0 + path.slen
    Ng = sg.shape[0]
    h = np.diff(sg)
    h[last[:-1]] = 0.0        # duplicated junction points
    h = np.maximum(h, 0.0)

    # ---- derivatives by central differences (same piece formula on both sides) --------
    d = FD_STEP
    offs = (-2 * d, -d, 0.0, d, 2 * d)
    Ls = []
    tips = []
    tool_pt = path.tool_point[pidx]
    for o, tip in zip(offs, path.tips(pidx, [sg + o for o in offs])):
        X, L = P.platform_struts(tip, tool_pt, hx.plat, hx.base)
        Ls.append(L)
        if o == 0.0:
            Xg = X
        if o in (-d, d):
            tips.append(tip)
    Lm2, Lm1, L0, Lp1, Lp2 = Ls
    Lp = (Lp1 - Lm1) / (2 * d)
    Lpp = (Lp1 - 2 * L0 + Lm1) / (d * d)
    Lppp = (Lp2 - 2 * Lp1 + 2 * Lm1 - Lm2) / (2 * d ** 3)
    dtip = (tips[1] - tips[0]) / (2 * d)
    del Ls, tips, Lm2, Lm1, L0, Lp1, Lp2, X, L, tip       # ~25 MB on 3D_Chips: less to fault in

    jmarg, lmmarg = _check_limits(path, hx, cfg, sg, pidx, Xg, lmarg, amarg)

    # ---- speed limits -------------------------------------------------------------------
    xyz_speed = np.linalg.norm(dtip[:, :3], axis=1)
    ang_speed_deg = np.linalg.norm(np.degrees(dtip[:, 3:]), axis=1)
    meas = np.where(xyz_speed > 1e-6, xyz_speed, np.maximum(ang_speed_deg, 1e-12))
    feed = path.feed[pidx]
    xlim = (feed / meas) ** 2
    # angular velocity |omega| = |E abc'| s_dot
    abc = Xg[:, 3:]
    cb_, sb_, cc_, sc_ = np.cos(abc[:, 1]), np.sin(abc[:, 1]), np.cos(abc[:, 2]), np.sin(abc[:, 2])
    da_, db_, dc_ = dtip[:, 3], dtip[:, 4], dtip[:, 5]
    wx = cc_ * cb_ * da_ - sc_ * db_
    wy = sc_ * cb_ * da_ + cc_ * db_
    wz = -sb_ * da_ + dc_
    wn = np.sqrt(wx * wx + wy * wy + wz * wz)
    wmax = math.radians(pc.max_angular_velocity_deg_s)
    with np.errstate(divide="ignore", over="ignore"):
        xlim = np.minimum(xlim, np.where(wn > 1e-12, (wmax / np.maximum(wn, 1e-12)) ** 2, np.inf))
        aLp = np.abs(Lp)
        xv = np.min(np.where(aLp > 1e-12, (ETA_V * 0.995 * vmax[None] / np.maximum(aLp, 1e-300)) ** 2, np.inf),
                    axis=1)
        aL3 = np.abs(Lppp)
        xj = np.min(np.where(aL3 > 1e-12, (RHO_J * ETA * jmax[None] / np.maximum(aL3, 1e-300)) ** (2.0 / 3.0),
                             np.inf), axis=1)
    xlim = np.minimum(np.minimum(xlim, xv), xj)
    c, e, dd, xmvc = accel_coefficients(Lp, Lpp, ETA * ACC_SHARE * amax)
    xlim = np.minimum(xlim, xmvc)
    # curvature jumps at tangent-continuous junctions: an acceleration step dL'' x between two
    # cycles reads as a jerk dL'' x / dt, so x <= RHO_STEP J dt / |dL''|
    jn = np.nonzero(h == 0)[0]
    if jn.size:
        dLpp = np.abs(Lpp[jn + 1] - Lpp[jn])
        with np.errstate(divide="ignore"):
            xs = np.min(np.where(dLpp > 1e-12, RHO_STEP * jmax[None] * dt / np.maximum(dLpp, 1e-300), np.inf), axis=1)
        xlim[jn] = np.minimum(xlim[jn], xs)
        xlim[jn + 1] = np.minimum(xlim[jn + 1], xs)

    # ---- stops and holds ------------------------------------------------------------------
    holds: dict[int, Hold] = {}
    stop_grid = set()
    for m in path.stops_after:
        stop_grid.add(int(last[m]))
    for m, blk in events:
        g = int(last[m]) if m >= 0 else 0
        hd = holds.setdefault(g, Hold(g, 0.0, int(blk.line)))
        hd.kinds.append(blk)
        if blk.kind == B.DWELL:
            hd.seconds += max(0.0, float(blk.seconds or 0.0))
            hd.line = int(blk.line)
        elif blk.kind == B.PAUSE:
            hd.pause = True
            hd.line = int(blk.line)
        elif blk.kind == B.OPTIONAL_PAUSE:
            hd.optional = True
            hd.line = int(blk.line)
        if blk.kind in P.STOP_EVENTS:
            stop_grid.add(g)
    stop_idx = np.array(sorted(stop_grid | {0, Ng - 1}), dtype=np.int64)
    # at a stop both duplicated junction points are at rest
    dup = stop_idx[stop_idx + 1 < Ng]
    dup = dup[h[dup] == 0] + 1
    stop_all = np.concatenate([stop_idx, dup])
    xlim[stop_all] = 0.0
    holds_s = np.zeros(Ng)
    pause_grid = []
    for g in stop_idx:
        # the program's start and end need no hold: the smoothing starts from rest and its tail
        # (T of the final position) brings the motion to rest
        if 0 < g < Ng - 1:
            holds_s[g] = hold_min
    for g, hd in holds.items():
        extra = hd.seconds
        if hd.pause or hd.optional:
            extra += 2 * hold_min
            pause_grid.append(g)
        holds_s[g] = hold_min + extra + (2 * dt if extra > 0 else 0.0)
    holds_s[0] = max(holds_s[0], 0.0)
    rest_grid = [int(g) for g in np.nonzero(holds_s > 0)[0]]


    # ---- TOPP + smoothing + measurement, tightened until within limits ---------------------------
    factor = np.ones(Ng)
    s_grid_for_lookup = sg
    xw = xlim.copy()
    xw[stop_all] = np.inf
    xlim = _dilate_min(sg, xw, SPREAD_REACH * nf * dt)     # the window reaches w/2 either side of its centre
    xlim[stop_all] = 0.0
    # path acceleration cap from the speeds of the uncapped solution (capping only lowers them, and the
    # cap only grows as speeds drop, so it stays valid)
    x0 = WavefrontTopp(h, c, e, dd).solve(xlim)
    ecap = _accel_cap(Lp, Lpp, Lppp, x0, jmax, nf * dt)
    del x0
    c, e, dd, xcap = _with_accel_cap(c, e, dd, ecap)
    lower = np.nonzero(xcap < xlim)[0]
    if lower.size:              # curvature alone needs more than the cap: a speed limit, spread like the others
        xw = np.full(Ng, np.inf)
        xw[lower] = xcap[lower]
        xw[stop_all] = np.inf
        xlim = np.minimum(xlim, _dilate_min(sg, xw, SPREAD_REACH * nf * dt))
        xlim[stop_all] = 0.0
    topp = WavefrontTopp(h, c, e, dd)      # same result as topp.forward_backward, numpy wavefronts
    caps = np.full(Ng, np.inf)             # speed caps at peaks (x units)
    cfac = np.ones(Ng)                     # the verification's factors on the acceleration cap
    xcapf = np.full(Ng, np.inf)            # speed limits where a lowered cap leaves no acceleration
    cap_changed = []
    del c
    changed: list = []             # grid ranges whose limit changed since the last pass
    bounds = _Bounds(Lp, Lpp, Lppp, vmax, amax, jmax)
    iters = 0
    exact = False
    exact_iters = 0
    for iters in range(1, 40):
        if iters == 1:
            xc = xlim.copy()
            x = topp.solve(xc)
        elif changed:
            for a0, a1 in cap_changed:
                sl = slice(a0, a1 + 1)
                ec = ecap[sl] * cfac[sl]
                bound = np.zeros(Ng)
                bound[sl] = ec
                topp.set_bound(6, np.arange(a0, a1 + 1), bound)
                # a lower cap can leave no acceleration at the highest speeds: those become a limit
                with np.errstate(divide="ignore", invalid="ignore"):
                    ad = np.abs(dd[sl, :6])
                    xcw = np.where(ad > 1e-15, (e[sl, :6] + ec[:, None]) / np.where(ad > 1e-15, ad, 1.0),
                                   np.inf).min(axis=1)
                xcapf[sl] = np.minimum(xcapf[sl], xcw)
            for a0, a1 in changed:
                xc[a0:a1 + 1] = np.minimum(np.minimum(xlim[a0:a1 + 1] * factor[a0:a1 + 1], xcapf[a0:a1 + 1]),
                                           caps[a0:a1 + 1])
            x = topp.solve_ranges(xc, changed, bounds_changed=bool(cap_changed))
        # speed peaks: capped (caps only ever lowered, kept across passes) until each has a plateau of w,
        # so that no filter window holds an acceleration reversal; re-solving moves the ramps by up to a
        # grid step, so a second round caps what the first left
        spans = None                       # the first round looks at every hill
        for _round in range(CAP_ROUNDS if iters == 1 or changed else 0):
            region, cap = _cap_round(h, x, w_plateau, spans)
            if region is None:
                break
            caps[region] = np.minimum(caps[region], cap[region])
            xc[region] = np.minimum(xc[region], cap[region])
            spans = _runs(region)          # whole hills: the next round only looks at those
            if _DEBUG:
                print(f"   caps round {_round}: {len(spans)} runs, {int(region.sum())} points")
            x = topp.solve_ranges(xc, spans)
        try:
            s_raw, TH, total = _sample_profile(sg, h, x, holds_s, dt)
        except FloatingPointError as exc:
            k = int(str(exc).rsplit(" ", 1)[-1])
            raise PlanError("the path cannot be traversed: zero speed allowed over a stretch", line=int(
                path.line[pidx[k]]), limit="speed") from exc
        s_f = _box_filter(s_raw, nf)
        # rows whose window lies inside a stop's hold rest exactly at the stop (the running sum of the
        # filter leaves them an ulp off, which put them on the arriving piece in the model pass)
        for g in rest_grid:
            c0 = int(math.ceil(TH[g] / dt - 1e-9)) + nf
            c1 = min(s_f.shape[0] - 1, int(math.floor((TH[g] + holds_s[g]) / dt + 1e-9)) - 1)
            if c1 >= c0:
                s_f[c0:c1 + 1] = sg[g]
                # the rows around stay on their side of the stop (the same rounding, either way)
                np.minimum(s_f[max(0, c0 - nf):c0], sg[g], out=s_f[max(0, c0 - nf):c0])
                np.maximum(s_f[c1 + 1:c1 + 1 + nf], sg[g], out=s_f[c1 + 1:c1 + 1 + nf])
        # model passes only decide where to slow down: a sample whose bound is within its violation
        # threshold cannot violate (model <= bound), so only the others are evaluated
        uv, ua, uj, va, ajr, vjr, n_detail = _measure_fast(path, hx, sg, Lp, Lpp, Lppp, bounds, s_f, dt, vmax,
                                                            amax, jmax, exact, SCREEN if exact else MODEL_SCREEN)
        viol_v = uv > ETA_V * 0.9995
        viol_a = ua > ETA
        viol_j = uj > ETA
        bad = viol_v | viol_a | viol_j
        if _DEBUG:
            print(f"plan iter {iters} exact={exact} uv={uv.max():.3f} ua={ua.max():.3f} uj={uj.max():.3f} "
                  f"bad v/a/j={viol_v.sum()}/{viol_a.sum()}/{viol_j.sum()} T={s_f.shape[0] * dt:.2f}s")
            for arr in (ua, uj):
                jw = int(np.argmax(arr))
                pm = int(path.piece_at(np.array([s_f[jw]]))[0])
                gw = int(np.searchsorted(sg, s_f[jw]))
                print("   worst at t", jw * dt, "s", s_f[jw], "piece", pm, "kind", path.kind[pm], "line",
                      path.line[pm], "x", x[gw - 2:gw + 2], "xlim", xlim[gw - 2:gw + 2], "h", h[gw - 2:gw + 2],
                      "sd", (s_f[jw + 1] - s_f[jw - 1]) / 2 / dt)
        changed = []
        cap_changed = []
        if not bad.any():
            if exact:
                break
            exact = True        # the model is satisfied: now measure the real table
            exact_iters = 0
            continue
        if exact:
            exact_iters += 1
        fac = np.ones(s_f.shape[0])
        with np.errstate(divide="ignore"):
            fac = np.where(viol_v, np.minimum(fac, (ETA_V * 0.999 / np.maximum(uv, 1e-12)) ** 2 * 0.98), fac)
            fac = np.where(viol_a, np.minimum(fac, ETA / np.maximum(ua, 1e-12) * 0.97), fac)
            fac = np.where(viol_j, np.minimum(fac, ETA / np.maximum(uj, 1e-12) * 0.9), fac)
        fac = np.maximum(fac, 0.3)
        if iters > 25 or exact_iters > 8:
            fac = np.minimum(fac, 0.7)
        jb = np.nonzero(bad)[0]
        # group into runs; tighten every grid point the filter window touched
        br = np.nonzero(np.diff(jb) > nf)[0]
        starts = np.concatenate([[0], br + 1])
        ends = np.concatenate([br, [jb.size - 1]])
        Nt = s_f.shape[0]
        for a0, a1 in zip(starts, ends):
            j0, j1 = jb[a0], jb[a1]
            lo_s = s_f[max(0, j0 - nf - 1)]
            hi_s = s_f[min(Nt - 1, j1 + nf + 1)]
            g0 = max(0, int(np.searchsorted(s_grid_for_lookup, lo_s, side="left")) - 1)
            g1 = min(Ng, int(np.searchsorted(s_grid_for_lookup, hi_s, side="right")) + 1)
            f = float(np.min(fac[j0:j1 + 1]))
            if not (viol_v[j0:j1 + 1].any() or viol_a[j0:j1 + 1].any()):
                # jerk alone: mostly the filter's |L'| du / w, which slower speeds hardly change, so
                # the acceleration cap is lowered with the speed limit
                cfac[g0:g1] *= f
                cap_changed.append((g0, g1 - 1))
                f = f ** CAP_JERK_SPEED
            factor[g0:g1] *= f
            changed.append((g0, g1 - 1))
    else:
        raise PlanError(f"could not meet the strut dynamic limits (velocity {uv.max():.3f}, acceleration "
                        f"{ua.max():.3f}, jerk {uj.max():.3f} of the limits) after {iters} iterations",
                        line=int(path.line[0]), limit="dynamics")

    Nt = s_f.shape[0]
    # ---- tables: line, flags, holds ----------------------------------------------------------------
    pt = path.piece_at(s_f)
    line_tab = path.line[pt].astype(np.int32)
    flag_tab = np.where(path.rapid[pt], FLAG_MOTION | FLAG_RAPID, FLAG_MOTION).astype(np.int32)
    ev_out = []
    pause_idx = []
    for g, hd in sorted(holds.items()):
        # the smoothed table stands still once the filter window lies inside the raw hold
        c0 = min(Nt - 1, int(math.ceil(TH[g] / dt - 1e-9)) + nf)
        c1 = min(Nt - 1, max(c0, int(math.floor((TH[g] + holds_s[g]) / dt + 1e-9)) - 1))
        line_tab[c0:c1 + 1] = hd.line
        flag_tab[c0:c1 + 1] = FLAG_DWELL
        for blk in hd.kinds:
            val = {B.SPINDLE: float(getattr(blk, "spindle_rpm", 0.0)), B.COOLANT: getattr(blk, "coolant", "off"),
                   B.TOOL_CHANGE: int(getattr(blk, "tool", 0)), B.DWELL: float(getattr(blk, "seconds", 0.0))
                   }.get(blk.kind)
            ev_out.append((c0 * dt, int(blk.line), blk.kind, val))
            flag_tab[c0] |= FLAG_EVENT
        if hd.pause or hd.optional:
            p = (c0 + c1) // 2
            pause_idx.append((p, hd.optional, hd.line))
            flag_tab[p] |= FLAG_PROGRAM_PAUSE
    # events that do not stop (coolant) are attached at their position
    for m, blk in events:
        if blk.kind not in P.STOP_EVENTS:
            g = int(last[m]) if m >= 0 else 0
            j = min(Nt - 1, int((TH[g]) / dt) + nf // 2)
            ev_out.append((j * dt, int(blk.line), blk.kind, getattr(blk, "coolant", None)))
            flag_tab[j] |= FLAG_EVENT
    flag_tab[-1] |= FLAG_END
    # per-line timing
    line_times: dict[int, tuple[float, float]] = {}
    if Nt:
        order = np.arange(Nt)
        ul, first_i = np.unique(line_tab, return_index=True)
        _, last_rev = np.unique(line_tab[::-1], return_index=True)
        last_i = Nt - 1 - last_rev
        for ln, a0, a1 in zip(ul.tolist(), first_i.tolist(), last_i.tolist()):
            line_times[int(ln)] = (a0 * dt, (a1 + 1) * dt)
        del order
    util = {"velocity": float(uv.max()), "acceleration": float(ua.max()), "jerk": float(uj.max())}
    # governor data for the sampler: block maxima (GOV samples) looking ahead
    from .sampler import governor_tables
    gov = governor_tables(uv, ua, uj, va, ajr, vjr, dt)
    plan = Plan(
        cfg=cfg, hexapod=hx, path=path, dt=dt, s_tab=s_f, line_tab=line_tab, flag_tab=flag_tab,
        duration_s=(Nt - 1) * dt, utilisation=util, min_joint_margin_deg=jmarg, min_length_margin_mm=lmmarg,
        line_times=line_times, events=ev_out, pause_idx=pause_idx, gov=gov, filter_s=nf * dt,
        n_segments=int(np.sum(path.kind != P.BLEND)), n_blends=int(np.sum(path.kind == P.BLEND)),
        n_stops=len(stop_idx), grid_points=Ng, sample_bound_mm=pc.sample_bound_mm, iterations=iters,
        grid_s=sg, grid_x=x, grid_h=h, grid_stops=stop_all, grid_L1=Lp, grid_L2=Lpp, grid_L3=Lppp,
        planning_s=time.perf_counter() - t_start,
    )
    return plan
