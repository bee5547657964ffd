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

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import PlanError
from ..gcode import blocks as B
from ..kinematics import Hexapod
from ..setpoint import (FLAG_DWELL, FLAG_END, FLAG_EVENT, FLAG_MOTION, FLAG_PAUSED,  # noqa: F401 (re-exported)
                        FLAG_PROGRAM_PAUSE, FLAG_RAPID, FLAG_STOPPING)
from . import path as P
from . import rawmoves as R
from .limits import _check_limits
from .softlimits import check_box
from .retime import hold_times, retime
from .profile import (ETA, _accel_cap, _box_filter, _cap_round, _cap_speed, _dilate_min, _runs,
                      _sample_profile, _with_accel_cap)
from .toppvec import WavefrontTopp, accel_coefficients
from .verify import FD_STEP, _Bounds, _measure_fast

# ETA (the share of the acceleration and jerk limits) is defined in profile.py, whose acceleration cap uses it;
# FD_STEP (the central differences' step) in verify.py, which checks pieces shorter than its stencil
#: fraction of the velocity limit the nominal plan may use
ETA_V = 1.0
#: share of the jerk limit a full acceleration change through the smoothing filter may take: the moving
#: average's width is ``w = max(a_max / j_max) / FILTER_JERK_SHARE`` (a one-sided change of the path
#: acceleration by A then gives path jerk A / w; reversals are kept out of every window by plateaus)
FILTER_JERK_SHARE = 0.9
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
#: the derivatives' step on a piece shorter than FD_PIECE_STEPS * FD_STEP is its length / FD_PIECE_STEPS,
#: at least FD_MIN_STEP (mm; the third difference's rounding, ~1e-16 L / step^3, stays below 1 mm^-2)
FD_PIECE_STEPS = 8
FD_MIN_STEP = 1e-4
#: grid intervals at least on a piece that rests at both ends (short moves from rest to rest)
REST_PIECE_INTERVALS = 32
#: run the verified table faster where its rows leave room below the shares (retime.py, measured from the rows);
#: off: 3D_Chips.ngc 93.05 -> 87.83 s but planning 1.0 -> 3.3 s CPU (below the 100x real-time target)
RETIME = False
#: samples whose interval bound stays below this are not measured by exact inverse kinematics
SCREEN = 0.5
#: thresholds above which a model pass evaluates a sample (v, a, j): its violation thresholds
#: (the bounds are upper bounds of the model, so a sample below them cannot violate), 1e-9 lower
MODEL_SCREEN = (ETA_V * 0.9995 * (1 - 1e-9), ETA * (1 - 1e-9), ETA * (1 - 1e-9))

log = logging.getLogger(__name__)



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
            "smoothed": int(self.n_smoothed),
            "stops": int(self.n_stops),
            "path_length": round(self.path.total, 6),
            "grid_points": int(self.grid_points),
            "sample_bound_mm": self.sample_bound_mm,
            "planning_s": round(self.planning_s, 4),
            "iterations": int(self.iterations),
            "lines": {str(k): [round(a, 4), round(b, 4)] for k, (a, b) in sorted(self.line_times.items())},
        }


# ---------------------------------------------------------------------------
def plan_program(blocks, cfg, hexapod: Hexapod | None = None, period_s: float | None = None,
                 start_pose=None) -> Plan:
    """Plan a whole program (list of :class:`~hexacnc.gcode.blocks.Block`) for the machine ``cfg``.

    ``start_pose``: tool-tip pose (mm, deg; tool length 0) where a program without motion stands
    (default: the tool tip at ``[workspace] home_pose``); a program with motion starts where its first
    move starts.

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
        # no motion (empty, comments only, M2 only, dwells and events): a standstill at the start pose
        return _standstill(cfg, hx, dt, events, start_pose, t_start)

    # ---- grid -----------------------------------------------------------------
    h_p, nint, lmarg, amarg = P.sample_spacing(path, hx.plat, float(np.min(hx.min_length)), pc.sample_bound_mm)
    # a piece that rests at both ends (a short move from rest to rest) needs moving grid points inside, and
    # enough of them that its speed peak gets a plateau near the best level (the caps place plateaus
    # between grid points): REST_PIECE_INTERVALS at least (a finer spacing only tightens the bounds above)
    rest_end = np.zeros(path.n, dtype=bool)
    rest_end[[m for m in path.stops_after]] = True
    rest_end[[m for m, blk in events if m >= 0 and blk.kind in P.STOP_EVENTS]] = True
    rest_start = np.concatenate([[True], rest_end[:-1]])
    two = rest_start & rest_end & (nint < REST_PIECE_INTERVALS)
    if two.any():
        nint = np.where(two, REST_PIECE_INTERVALS, nint)
        h_p = np.where(two, path.slen / REST_PIECE_INTERVALS, h_p)
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
    # the step is FD_STEP, or an eighth of a shorter piece (the stencil of a piece far shorter than FD_STEP
    # reads its polynomial far outside the piece: a 1 um blend's third derivative came out orders too large)
    # (a zero-length piece keeps FD_STEP: its polynomial is only read at its point; the rounding of a third
    # difference grows as 1 / step^3, FD_MIN_STEP keeps it far below any jerk bound that matters)
    sl = path.slen[pidx]
    d = np.where(sl > 0, np.minimum(FD_STEP, np.maximum(sl / FD_PIECE_STEPS, FD_MIN_STEP)), FD_STEP)
    offs = (-2, -1, 0, 1, 2)
    Ls = []
    tips = []
    tool_pt = path.tool_point[pidx]
    for o, tip in zip(offs, path.tips(pidx, [sg + o * d for o in offs])):
        X, L = P.platform_struts(tip, tool_pt, hx.plat, hx.base)
        Ls.append(L)
        if o == 0:
            Xg = X
        if o in (-1, 1):
            tips.append(tip)
    Lm2, Lm1, L0, Lp1, Lp2 = Ls
    dc = d[:, None]
    Lp = (Lp1 - Lm1) / (2 * dc)
    Lpp = (Lp1 - 2 * L0 + Lm1) / (dc * dc)
    Lppp = (Lp2 - 2 * Lp1 + 2 * Lm1 - Lm2) / (2 * dc ** 3)
    dtip = (tips[1] - tips[0]) / (2 * dc)
    tip_g = 0.5 * (tips[0] + tips[1])         # tool tip at the grid (the mean of the +-d samples: O(d^2) off)
    del Ls, tips, Lm2, Lm1, L0, Lp1, Lp2, X, L, tip       # ~25 MB on 3D_Chips: less to fault in

    jmarg, lmmarg = _check_limits(path, hx, cfg, sg, pidx, Xg, lmarg, amarg)
    # Cartesian soft limits (after the machine's own limits, which name the physical cause first)
    check_box(cfg, Xg, tip_g, path.line[pidx])
    del tip_g

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

    def spread(xw):
        """Speed limits spread over the filter's reach (the window reaches w/2 either side of its
        centre); stops spread nothing and stay at rest."""
        xw[stop_all] = np.inf
        out = _dilate_min(sg, xw, SPREAD_REACH * nf * dt)
        out[stop_all] = 0.0
        return out

    xlim = spread(xlim.copy())
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
        xlim = np.minimum(xlim, spread(xw))
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
                xcapf[sl] = np.minimum(xcapf[sl], _cap_speed(e[sl, :6], dd[sl, :6], ec))
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
            if log.isEnabledFor(logging.DEBUG):
                log.debug(f"caps round {_round}: {len(spans)} runs, {int(region.sum())} points")
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
        if log.isEnabledFor(logging.DEBUG):
            log.debug(f"plan iter {iters} exact={exact} uv={uv.max():.3f} ua={ua.max():.3f} uj={uj.max():.3f} "
                      f"bad v/a/j={viol_v.sum()}/{viol_a.sum()}/{viol_j.sum()} T={s_f.shape[0] * dt:.2f}s")
            for arr in (ua, uj):
                jw = int(np.argmax(arr))
                pm = int(path.piece_at(np.array([s_f[jw]]))[0])
                gw = int(np.searchsorted(sg, s_f[jw]))
                log.debug("worst at t %s s %s piece %s kind %s line %s x %s xlim %s h %s sd %s", jw * dt, s_f[jw],
                          pm, path.kind[pm], path.line[pm], x[gw - 2:gw + 2], xlim[gw - 2:gw + 2],
                          h[gw - 2:gw + 2], (s_f[jw + 1] - s_f[jw - 1]) / 2 / dt)
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

    if RETIME:            # the verified table, run faster where its rows leave room (retime.py)
        rt = retime(path, hx, s_f, dt, vmax, amax, jmax, (ETA_V * 0.995, ETA, ETA), pc.max_angular_velocity_deg_s)
        if rt.rounds >= 0:
            m = _measure_fast(path, hx, sg, Lp, Lpp, Lppp, bounds, rt.s_tab, dt, vmax, amax, jmax, True, SCREEN)
            if m[0].max() <= max(ETA_V * 0.9995, uv.max()) and m[1].max() <= ETA and m[2].max() <= ETA:
                s_f, TH = rt.s_tab, hold_times(rt.t_of_old, TH, nf * dt, dt)
                uv, ua, uj, va, ajr, vjr, n_detail = m
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
            ev_out.append((c0 * dt, int(blk.line), blk.kind, _event_value(blk)))
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
        ul, first_i = np.unique(line_tab, return_index=True)
        _, last_rev = np.unique(line_tab[::-1], return_index=True)
        last_i = Nt - 1 - last_rev
        for ln, a0, a1 in zip(ul.tolist(), first_i.tolist(), last_i.tolist()):
            line_times[int(ln)] = (a0 * dt, (a1 + 1) * dt)
    util = {"velocity": float(uv.max()), "acceleration": float(ua.max()), "jerk": float(uj.max())}
    # governor data for the sampler: block maxima (GOV samples) looking ahead
    from .sampler import governor_tables
    gov = governor_tables(uv, ua, uj, va, ajr, vjr, dt)
    plan = Plan(
        cfg=cfg, hexapod=hx, path=path, dt=dt, s_tab=s_f, line_tab=line_tab, flag_tab=flag_tab,
        duration_s=(Nt - 1) * dt, utilisation=util, min_joint_margin_deg=jmarg, min_length_margin_mm=lmmarg,
        line_times=line_times, events=ev_out, pause_idx=pause_idx, gov=gov, filter_s=nf * dt,
        n_segments=int(np.sum(path.kind != P.BLEND)), n_blends=int(np.sum(path.kind == P.BLEND)),
        n_smoothed=int(np.sum(path.kind == P.SPLINE)),
        n_stops=len(stop_idx), grid_points=Ng, sample_bound_mm=pc.sample_bound_mm, iterations=iters,
        grid_s=sg, grid_x=x, grid_h=h, grid_stops=stop_all, grid_L1=Lp, grid_L2=Lpp, grid_L3=Lppp,
        planning_s=time.perf_counter() - t_start,
    )
    return plan


def _event_value(blk):
    """The value an event row reports: spindle rpm, coolant state, tool number, dwell seconds."""
    return {B.SPINDLE: float(getattr(blk, "spindle_rpm", 0.0)), B.COOLANT: getattr(blk, "coolant", "off"),
            B.TOOL_CHANGE: int(getattr(blk, "tool", 0)), B.DWELL: float(getattr(blk, "seconds", 0.0))
            }.get(blk.kind)


def _standstill(cfg, hx, dt: float, events, start_pose, t_start: float) -> Plan:
    """The plan of a program without motion: the start pose held for its dwells (M0/M1 pause there),
    its events at the start, an end row.  Utilisation zero."""
    from .sampler import governor_tables
    if start_pose is None:
        from ..gcode.factory import machine_defaults
        start_pose = machine_defaults(cfg)["start_pose"]
    p0 = R.pose_rad(start_pose, "start", 0)
    line0 = int(events[0][1].line) if events else 0
    pieces = {"kind": [P.LINE], "coef": [R.line_coef(p0, p0)], "slen": [0.0], "u0": [0.0], "uscale": [0.0],
              "tool_mm": [0.0], "feed": [1.0], "rapid": [False], "line": [line0]}
    path = P.Path(cfg, pieces, {})
    n = 2 + int(math.ceil(sum(max(0.0, float(b.seconds or 0.0)) for _, b in events if b.kind == B.DWELL) / dt))
    pauses = [b for _, b in events if b.kind in (B.PAUSE, B.OPTIONAL_PAUSE)]
    n += 2 * len(pauses)
    line_tab = np.full(n, line0, dtype=np.int32)
    flag_tab = np.full(n, FLAG_DWELL, dtype=np.int32)
    ev_out, pause_idx = [], []
    for _, blk in events:
        ev_out.append((0.0, int(blk.line), blk.kind, _event_value(blk)))
    if events:
        flag_tab[0] |= FLAG_EVENT
    for k, blk in enumerate(pauses):
        p = 1 + 2 * k
        pause_idx.append((p, blk.kind == B.OPTIONAL_PAUSE, int(blk.line)))
        flag_tab[p] |= FLAG_PROGRAM_PAUSE
    flag_tab[-1] |= FLAG_END
    z = np.zeros(n)
    X0 = path.platform(np.zeros(1, dtype=np.int64), np.zeros(1))
    jmarg, lmmarg = _check_limits(path, hx, cfg, np.zeros(1), np.zeros(1, dtype=np.int64), X0, np.zeros(1),
                                  np.zeros(1))
    check_box(cfg, X0, path.tip(np.zeros(1, dtype=np.int64), np.zeros(1)), np.array([line0]))
    return Plan(
        cfg=cfg, hexapod=hx, path=path, dt=dt, s_tab=np.zeros(n), line_tab=line_tab, flag_tab=flag_tab,
        duration_s=(n - 1) * dt, utilisation={"velocity": 0.0, "acceleration": 0.0, "jerk": 0.0},
        min_joint_margin_deg=jmarg, min_length_margin_mm=lmmarg,
        line_times=({line0: (0.0, n * dt)} if events else {}), events=ev_out, pause_idx=pause_idx,
        gov=governor_tables(z, z, z, z, z, z, dt), filter_s=0.0, n_segments=0, n_blends=0, n_smoothed=0,
        n_stops=1, grid_points=1, sample_bound_mm=cfg.planner.sample_bound_mm, iterations=0,
        grid_s=np.zeros(1), grid_x=np.zeros(1), grid_h=np.zeros(0), grid_stops=np.zeros(1, dtype=np.int64),
        grid_L1=np.zeros((1, 6)), grid_L2=np.zeros((1, 6)), grid_L3=np.zeros((1, 6)),
        planning_s=time.perf_counter() - t_start)
