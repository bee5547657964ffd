"""Time parameterisation tightened until the measured table is within the limits (steps 3-5 of
:mod:`hexacnc.planner.plan`): TOPP, plateaus at speed peaks, the raw profile and its moving average, the
measurement, and local lowering of the limits where a sample exceeds its target."""
from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass

import numpy as np

from ..errors import PlanError
from . import path as P
from .consts import (CAP_JERK_SPEED, CAP_ROUNDS, CAP_SPEED_SHARE, ETA_V, LOWER_AIM, LOWER_MARGIN_SLOPE,
                     MAX_ITERATIONS, MODEL_SCREEN, REST_RAMP_MAX_POINTS, REST_RAMPS, SCREEN, SPREAD_IN_TIME,
                     SPREAD_REACH)
from .grid import Derivs, Grid
from .holds import Rests, hold_rows
from .profile import (ETA, RampBounds, _accel_cap, _box_filter, _cap_round, _cap_speed, _runs, _sample_profile,
                      _with_accel_cap)
from .reachgrid import spread_frame
from .spread import (SPREAD_CAP, dilate_min, reach_end_limits, rest_ramp_ceiling, rest_ramp_sides, spread_cap,
                     time_coordinate)
from .toppvec import WavefrontTopp
from .verify import _Bounds, _measure_fast

log = logging.getLogger("hexacnc.planner.plan")


@dataclass
class Profile:
    """The result: table ``s_f`` at dt, grid speeds ``x``, raw times ``TH`` of the grid points, the measured
    utilisations per sample and the passes it took."""
    s_f: np.ndarray
    x: np.ndarray
    TH: np.ndarray
    meas: tuple
    iterations: int


def _margin(r: np.ndarray, floor: float) -> np.ndarray:
    """The extra factor on a lowering to the target ratio ``r`` (target / measured, < 1 where violated):
    ``floor`` for a clear violation, rising to 1 as the violation vanishes, so that the lowered limit, and
    the planned time, do not jump where a sample crosses its target (:data:`~.consts.LOWER_MARGIN_SLOPE`)."""
    return np.clip(1.0 - LOWER_MARGIN_SLOPE * (1.0 / np.maximum(r, 1e-12) - 1.0), floor, 1.0)


class Tightener:
    """The loop's state: limits, caps and the factors the measurement lowered."""

    def __init__(self, path: P.Path, hx, g: Grid, dv: Derivs, rs: Rests, xlim, c, e, dd, lims, dt: float,
                 nf: int, w_plateau: float):
        self.path, self.hx, self.g, self.dv, self.rs = path, hx, g, dv, rs
        self.vmax, self.amax, self.jmax = lims
        self.dt, self.nf, self.w_plateau = dt, nf, w_plateau
        Ng = g.n
        # no spreading crosses a stop: its hold (at least the filter's width) keeps the filter windows of
        # the motion before it and after it apart (a tiny move's next move lowered its last intervals'
        # acceleration cap, over fewer of them as it grew: a longer move planned shorter)
        self.sg_sep, self.keep, self.reach_mm = spread_frame(g, rs)
        xlim = xlim.copy()
        xlim[rs.stop_all] = 0.0
        self.xlim = self._spread(xlim, xlim.copy())
        # path acceleration cap from the speeds of the uncapped solution (capping only lowers them, and the
        # cap only grows as speeds drop, so it stays valid)
        x0 = WavefrontTopp(g.h, c, e, dd).solve(self.xlim)
        if SPREAD_IN_TIME:
            # (the cap stays at the speeds x0 of the distance spreading: at the faster speeds of the spreading in
            # time it would be lower on every curve, and the verification measures the jerk either way)
            self.xlim = self._spread_in_time(xlim, x0)
        base = (c, e, dd, self.xlim, x0)      # what the caps are taken from, under any ceiling
        self.ecap, c7, self.e, self.dd, self.xlim, self.ceiling = self._caps_for(base, np.full(Ng, np.inf))
        if REST_RAMPS:
            c7 = self._rest_ramps(base, c7)
        c = c7
        del x0
        self.topp = WavefrontTopp(g.h, c, self.e, self.dd)   # same result as topp.forward_backward
        self.factor = np.ones(Ng)
        self.caps = np.full(Ng, np.inf)             # speed caps at peaks (x units)
        self.cfac = np.ones(Ng)                     # the verification's factors on the acceleration cap
        self.xcapf = np.full(Ng, np.inf)            # speed limits where a lowered cap leaves no acceleration
        self.bounds = _Bounds(dv.Lp, dv.Lpp, dv.Lppp, self.vmax, self.amax, self.jmax)
        self.xc = None

    def _caps_for(self, base: tuple, ceil: np.ndarray) -> tuple:
        """The acceleration cap taken at the uncapped solution's speeds ``x0`` under the ceiling ``ceil`` (x units,
        inf: none), then again nearer the speeds it allows where it holds the profile below them.  ``base``: (c, e,
        dd, spread limits, x0) before any cap.  Returns (cap, c, e, dd, limits, ceiling) with the TOPP bounds' cap
        row in ``c``."""
        c, e, dd, spread_lim, x0 = base
        x0 = np.minimum(x0, ceil)
        ecap, c7, e7, dd7, xl = self._capped(c, e, dd, spread_lim, x0)
        # speeds (x units) the cap was taken at, where below x0: a ceiling for the cap's sake, not a limit of the
        # struts, so the verification's lowering does not scale it (a ceiling right at a ramp's speeds, lowered,
        # would cut the ramp into a hill of its own)
        ceiling = ceil.copy()
        if CAP_SPEED_SHARE < 1.0:
            # where the cap holds the profile below x0, take it at speeds xu between the capped solution y and x0,
            # with xu as a ceiling: the cap is valid for the profile (it runs at most xu), and y stays feasible
            # (a higher cap, looser xcap limits), so the profile runs at least as fast as y
            y = WavefrontTopp(self.g.h, c7, e7, dd7).solve(np.minimum(xl, ceil))
            slow = y < x0
            if slow.any():
                v0, vy = np.sqrt(np.maximum(x0, 0.0)), np.sqrt(np.maximum(y, 0.0))
                xu = np.where(slow, (vy + CAP_SPEED_SHARE * (v0 - vy)) ** 2, x0)
                ecap, c7, e7, dd7, xl = self._capped(c, e, dd, spread_lim, xu)
                ceiling = np.minimum(ceiling, np.where(slow, xu, np.inf))
        return ecap, c7, e7, dd7, xl, ceiling

    def _rest_ramps(self, base: tuple, c7):
        """Where corners' low caps reach the ramp from or to a rest (:func:`rest_ramp_sides`), the fastest of:
        the ramp at those caps, or the stretch to the corner slow enough to keep the lowest one, two, ... cap
        levels off the ramp (a ceiling, :meth:`_caps_for`).  Each candidate is run through TOPP and the plateaus,
        and every stretch between two rests takes the one whose raw profile is shortest there.  Returns the TOPP
        bounds' cap row (``c7``); the caps, limits and ceiling are updated where a ceiling was chosen."""
        g, dv = self.g, self.dv
        if g.n > REST_RAMP_MAX_POINTS:
            return c7
        T = SPREAD_REACH * self.nf * self.dt
        at_rest = np.zeros(g.n, dtype=bool)
        at_rest[self.rs.stop_all] = True
        x0 = base[4]
        raw = _accel_cap(dv.Lp, dv.Lpp, dv.Lppp, x0, self.jmax, self.nf * self.dt)
        sides = rest_ramp_sides(self.sg_sep, g.h, at_rest, raw, x0, T)
        if not sides:
            return c7
        n_lev = max(len(sd[4]) for sd in sides)
        # the stretch between rests each point belongs to
        sec_of = np.searchsorted(np.nonzero(at_rest)[0], np.arange(g.n), side="right")
        cands = [(self.ecap, c7, self.e, self.dd, self.xlim, self.ceiling)]
        for lev in range(n_lev):
            cl = np.full(g.n, np.inf)
            for sd in sides:
                rest_ramp_ceiling(T, sd, sd[4][min(lev, len(sd[4]) - 1)], cl)
            cands.append(self._caps_for(base, cl))
        n_sec = int(sec_of.max()) + 1
        times = np.array([np.bincount(sec_of[:-1], self._raw_times(cd), minlength=n_sec) for cd in cands])
        best = np.argmin(times, axis=0)
        chosen = np.full(g.n, np.inf)
        for sd in sides:
            lev = int(best[sec_of[min(sd[0], sd[1])]])
            if lev > 0:
                rest_ramp_ceiling(T, sd, sd[4][min(lev - 1, len(sd[4]) - 1)], chosen)
        if not np.isfinite(chosen).any():
            return c7
        self.ecap, c7, self.e, self.dd, self.xlim, self.ceiling = self._caps_for(base, chosen)
        return c7

    def _raw_times(self, cand: tuple) -> np.ndarray:
        """(N-1,) seconds of the raw profile per interval (TOPP, plateaus, sampling) under the caps, limits and
        ceiling ``cand`` of :meth:`_caps_for`."""
        g = self.g
        t = copy.copy(self)
        _ecap, c7, t.e, t.dd, t.xlim, t.ceiling = cand
        t.topp = WavefrontTopp(g.h, c7, t.e, t.dd)
        t.caps = np.full(g.n, np.inf)
        x = t.solve(True, [], [])
        x = t.plateaus(x, CAP_ROUNDS)
        try:
            _s, TH, total = _sample_profile(g.sg, g.h, x, self.rs.holds_s, self.dt, t.ramps(), t.caps, t.xc)
        except FloatingPointError:
            return np.full(g.n - 1, np.inf)
        return np.diff(np.append(TH, total))[:-1] - self.rs.holds_s[:-1]

    def _capped(self, c, e, dd, xlim, xs):
        """The acceleration cap (N,) valid at speeds^2 up to ``xs`` (N,), spread over the filter's reach at those
        speeds; the TOPP bounds ``c, e, dd`` with its row; the limits ``xlim`` lowered where curvature alone
        needs more than the cap.  Returns (cap, c, e, dd, limits)."""
        nf, dt, Ng = self.nf, self.dt, self.g.n
        dv = self.dv
        ecap = _accel_cap(dv.Lp, dv.Lpp, dv.Lppp, xs, self.jmax, nf * dt)
        if SPREAD_CAP:   # the moving average carries an acceleration to every sample whose window holds it
            ecap = spread_cap(self.sg_sep, ecap, xs, SPREAD_REACH * nf * dt, self.keep)
        c7, e7, dd7, xcap = _with_accel_cap(c, e, dd, ecap)
        lower = np.nonzero(xcap < xlim)[0]
        if lower.size:      # curvature alone needs more than the cap: a speed limit, spread like the others
            xw = np.full(Ng, np.inf)
            xw[lower] = xcap[lower]
            xlim = np.minimum(xlim, self._spread(xw, xlim))
        return ecap, c7, e7, dd7, xlim

    def _spread(self, xw, upper, xs=None):
        """Speed limits spread over the filter's reach (the window reaches w/2 = T either side of its centre);
        stops spread nothing and stay at rest.  ``upper``: the limits without these (finite), towards which the
        points just beyond a reach's end are interpolated (:func:`reach_end_limits`).

        ``xs`` None: over the distance ``T sqrt(x_j)`` travelled at each limit's own speed.  ``xs`` (speeds^2 of a
        TOPP solution): over T seconds of travel at those speeds (:meth:`_spread_in_time`)."""
        sa = self.rs.stop_all
        xw = xw.copy()
        xw[sa] = np.inf
        T = SPREAD_REACH * self.nf * self.dt
        if xs is None:
            pos, speed2, reach = self.sg_sep, None, self.reach_mm
        else:
            pos, speed2, reach = time_coordinate(self.sg_sep, xs), np.ones(xw.shape[0]), math.inf
        out = dilate_min(pos, xw, T, max_reach=reach, speed2=speed2)
        out[sa] = 0.0
        # the grid has a point at every binding reach end known before (reachgrid); the others are interpolated,
        # towards the limits the other spreadings leave the points beyond (``out`` there: beyond a reach, its own
        # spot does not hold), not towards their own limits
        np.minimum(out, reach_end_limits(pos, xw, np.minimum(upper, out), T, reach, speed2), out=out)
        out[sa] = 0.0
        return out

    def _spread_in_time(self, xlim, x0):
        """The limits ``xlim`` spread over the filter's reach measured in time: the window holds T seconds of raw
        motion either side of its centre, and beside a slow spot the raw profile runs slower than a neighbouring
        limit's own speed, so that limit's window covers less path than the distance spreading's
        ``T sqrt(x_j)``.  Spread over T seconds at the speeds ``x0`` of the TOPP solution under the distance
        spreading: a binding slow spot crawls at its own speed across its reach there, so its spreading is the
        same, and the staircase of its neighbours' spread limits beside it goes.  Where the relaxed limits let
        the profile run faster than ``x0`` a window can reach further than assumed; the verification measures
        the table and lowers the limits where a sample exceeds its target, as for the filter's other
        approximations.  (Spreading once more in the time of TOPP(p1), min'ed in, holds for every window of that
        solution, but TOPP(p1) ramps off a slow spot far faster than the raw profile with its plateaus runs:
        the windows it gives are far too wide, and the planned time jumped by up to 76 cycles between
        neighbouring lengths of twelve G64 moves.)"""
        return self._spread(xlim, xlim, x0)

    def solve(self, first: bool, changed, cap_changed) -> np.ndarray:
        """TOPP on the current limits (from scratch the first time, else on the changed ranges)."""
        if first:
            self.xc = np.minimum(self.xlim, self.ceiling)
            return self.topp.solve(self.xc)
        Ng = self.g.n
        for a0, a1 in cap_changed:
            sl = slice(a0, a1 + 1)
            ec = self.ecap[sl] * self.cfac[sl]
            bound = np.zeros(Ng)
            bound[sl] = ec
            self.topp.set_bound(6, np.arange(a0, a1 + 1), bound)
            # a lower cap can leave no acceleration at the highest speeds: those become a limit
            self.xcapf[sl] = np.minimum(self.xcapf[sl], _cap_speed(self.e[sl, :6], self.dd[sl, :6], ec))
        xc = self.xc
        for a0, a1 in changed:
            sl = slice(a0, a1 + 1)
            xl = np.minimum(self.xlim[sl] * self.factor[sl], self.ceiling[sl])   # the ceiling is not lowered
            xc[sl] = np.minimum(np.minimum(xl, self.xcapf[sl]), self.caps[sl])
        return self.topp.solve_ranges(xc, changed, bounds_changed=bool(cap_changed))

    def plateaus(self, x: np.ndarray, rounds: int) -> np.ndarray:
        """Speed peaks capped (caps only ever lowered, kept across passes) until each has a plateau of w, so
        that no filter window holds an acceleration reversal; re-solving moves the ramps by up to a grid
        step, so a second round caps what the first left."""
        spans = None                       # the first round looks at every hill
        for _round in range(rounds):
            region, cap = _cap_round(self.g.h, x, self.w_plateau, spans, ramps=self.ramps())
            if region is None:
                break
            self.caps[region] = np.minimum(self.caps[region], cap[region])
            self.xc[region] = np.minimum(self.xc[region], cap[region])
            spans = _runs(region)          # whole hills: the next round only looks at those
            x = self.topp.solve_ranges(self.xc, spans)
        return x

    def ramps(self) -> RampBounds:
        """The TOPP bounds the ramps into and out of capped plateaus run at (profile.ramp_kinks)."""
        return RampBounds(self.topp)

    def table(self, x: np.ndarray):
        """Raw profile at dt, its moving average, and rows that rest exactly at each hold."""
        g, rs, dt, nf = self.g, self.rs, self.dt, self.nf
        try:
            s_raw, TH, _total = _sample_profile(g.sg, g.h, x, rs.holds_s, dt, self.ramps(), self.caps, self.xc)
        except FloatingPointError as exc:
            k = int(str(exc).rsplit(" ", 1)[-1])
            raise PlanError("the path cannot be traversed: zero speed allowed over a stretch", line=int(
                self.path.line[g.pidx[k]]), limit="speed") from exc
        s_f = _box_filter(s_raw, nf)
        # rows whose window lies inside a stop's hold rest exactly at the stop (the running sum of the
        # filter leaves them an ulp off, which put them on the arriving piece in the model pass)
        for k in rs.rest_grid:
            c0, c1 = hold_rows(TH[k], rs.holds_s[k], dt, nf)
            c1 = min(s_f.shape[0] - 1, c1)
            if c1 >= c0:
                s_f[c0:c1 + 1] = g.sg[k]
                # the rows around stay on their side of the stop (the same rounding, either way)
                np.minimum(s_f[max(0, c0 - nf):c0], g.sg[k], out=s_f[max(0, c0 - nf):c0])
                np.maximum(s_f[c1 + 1:c1 + 1 + nf], g.sg[k], out=s_f[c1 + 1:c1 + 1 + nf])
        return s_f, TH

    def measure(self, s_f: np.ndarray, exact: bool):
        """Model passes only decide where to slow down: a sample whose bound is within its violation
        threshold cannot violate (model <= bound), so only the others are evaluated."""
        dv = self.dv
        return _measure_fast(self.path, self.hx, self.g.sg, dv.Lp, dv.Lpp, dv.Lppp, self.bounds, s_f, self.dt,
                             self.vmax, self.amax, self.jmax, exact, SCREEN if exact else MODEL_SCREEN)

    def lower(self, s_f, uv, ua, uj, viol, iters: int, exact_iters: int):
        """Lower the limits on every grid point a violating sample's filter window touched; returns the
        changed ranges of the speed limit and of the acceleration cap."""
        viol_v, viol_a, viol_j = viol
        bad = viol_v | viol_a | viol_j
        fac = np.ones(s_f.shape[0])
        with np.errstate(divide="ignore"):
            aim = 1.0 - LOWER_AIM
            rv = ETA_V * 0.9995 * aim / np.maximum(uv, 1e-12)
            ra = ETA * aim / np.maximum(ua, 1e-12)
            rj = ETA * aim / np.maximum(uj, 1e-12)
            fac = np.where(viol_v, np.minimum(fac, rv * rv * _margin(rv, 0.98)), fac)
            fac = np.where(viol_a, np.minimum(fac, ra * _margin(ra, 0.97)), fac)
            fac = np.where(viol_j, np.minimum(fac, rj * _margin(rj, 0.9)), fac)
        fac = np.maximum(fac, 0.3)
        if iters > 25 or exact_iters > 8:
            fac = np.minimum(fac, 0.7)
        jb = np.nonzero(bad)[0]
        nf, sg, Ng = self.nf, self.g.sg, self.g.n
        # group into runs; tighten every grid point the filter window touched
        br = np.nonzero(np.diff(jb) > nf)[0]
        starts = np.concatenate([[0], br + 1])
        ends = np.concatenate([br, [jb.size - 1]])
        Nt = s_f.shape[0]
        changed, cap_changed = [], []
        for a0, a1 in zip(starts, ends):
            j0, j1 = jb[a0], jb[a1]
            lo_s = s_f[max(0, j0 - nf - 1)]
            hi_s = s_f[min(Nt - 1, j1 + nf + 1)]
            g0 = max(0, int(np.searchsorted(sg, lo_s, side="left")) - 1)
            g1 = min(Ng, int(np.searchsorted(sg, hi_s, side="right")) + 1)
            f = float(np.min(fac[j0:j1 + 1]))
            if not (viol_v[j0:j1 + 1].any() or viol_a[j0:j1 + 1].any()):
                # jerk alone: mostly the filter's |L'| du / w, which slower speeds hardly change, so
                # the acceleration cap is lowered with the speed limit
                self.cfac[g0:g1] *= f
                cap_changed.append((g0, g1 - 1))
                f = f ** CAP_JERK_SPEED
            self.factor[g0:g1] *= f
            changed.append((g0, g1 - 1))
        return changed, cap_changed


def tighten(tt: Tightener) -> Profile:
    """Passes of TOPP, plateaus, table and measurement until the model, then the exact measurement, is
    within the targets; raises PlanError after MAX_ITERATIONS."""
    changed: list = []             # grid ranges whose limit changed since the last pass
    cap_changed: list = []
    exact = False
    exact_iters = 0
    iters = 0
    for iters in range(1, MAX_ITERATIONS):
        first = iters == 1
        if first or changed:
            x = tt.solve(first, changed, cap_changed)
        x = tt.plateaus(x, CAP_ROUNDS if first or changed else 0)
        s_f, TH = tt.table(x)
        meas = tt.measure(s_f, exact)
        uv, ua, uj = meas[0], meas[1], meas[2]
        viol = (uv > ETA_V * 0.9995, ua > ETA, uj > ETA)
        if log.isEnabledFor(logging.DEBUG):
            log.debug(f"plan iter {iters} exact={exact} uv={uv.max():.3f} ua={ua.max():.3f} uj={uj.max():.3f} "
                      f"bad v/a/j={viol[0].sum()}/{viol[1].sum()}/{viol[2].sum()} T={s_f.shape[0] * tt.dt:.2f}s")
        changed, cap_changed = [], []
        if not (viol[0] | viol[1] | viol[2]).any():
            if exact:
                return Profile(s_f, x, TH, meas, iters)
            exact = True        # the model is satisfied: now measure the real table
            exact_iters = 0
            continue
        if exact:
            exact_iters += 1
        changed, cap_changed = tt.lower(s_f, uv, ua, uj, viol, iters, exact_iters)
    raise PlanError(f"could not meet the strut dynamic limits (velocity {uv.max():.3f}, acceleration "
                    f"{ua.max():.3f}, jerk {uj.max():.3f} of the limits) after {iters} iterations",
                    line=int(tt.path.line[0]), limit="dynamics")
