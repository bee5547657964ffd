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
   average of width ``w = max(A/J)``; no window holds an acceleration
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

import numpy as np

from ..gcode import blocks as B
from ..kinematics import Hexapod
from ..setpoint import (FLAG_DWELL, FLAG_END, FLAG_EVENT, FLAG_MOTION, FLAG_PAUSED,  # noqa: F401 (re-exported)
                        FLAG_PROGRAM_PAUSE, FLAG_RAPID, FLAG_STOPPING)
from . import path as P
from . import rawmoves as R
from .consts import (ACC_SHARE, CAP_JERK_SPEED, CAP_ROUNDS, ETA_V, FD_MIN_STEP, FD_PIECE_STEPS,  # noqa: F401
                     FILTER_JERK_SHARE, GRADE_MM, MODEL_SCREEN, REST_PIECE_INTERVALS, RHO_J, RHO_STEP, SCREEN,
                     SPREAD_REACH)
from .blocktime import feeds_above_rapid
from .grid import build_grid, check_grid, derivatives
from .holds import Hold, rests  # noqa: F401 (Hold re-exported)
from .limits import _check_limits
from .profile import ETA  # noqa: F401 (re-exported)
from .reachgrid import with_reach_points
from .reststretch import rest_to_rest, trim_end, trim_start
from .retime import hold_times, retime
from .softlimits import check_box
from .speeds import speed_limits
from .tables import event_value, row_tables
from .tighten import Tightener, tighten
from .verify import _measure_fast

#: run the verified table faster where its rows leave room below the shares (retime.py, measured from the rows);
#: off: 3D_Chips.ngc 93.05 -> 87.83 s but planning 1.0 -> 3.3 s CPU (below the 100x real-time target)
RETIME = False
#: a grid point at every binding end of the speed limits' spreading (:mod:`.reachgrid`)
REACH_POINTS = True
#: short stretches between rests also planned as one S-curve, kept where it takes fewer cycles (:mod:`.reststretch`)
REST_STRETCHES = True


class Plan:
    """A planned program: a setpoint table at ``dt`` plus a summary.

    Attributes: ``duration_s``, ``utilisation`` (dict of peak strut velocity,
    acceleration and jerk as fractions of each limit), ``min_joint_margin_deg``,
    ``min_length_margin_mm``, ``line_times`` {line: (start_s, end_s)}, ``feed_capped`` (count, first line)
    of the feed moves that ask more than the rapid feed, which caps them,
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
            "feed_capped_moves": int(self.feed_capped[0]),
            "feed_capped_first_line": self.feed_capped[1],
            "lines": {str(k): [round(a, 4), round(b, 4)] for k, (a, b) in sorted(self.line_times.items())},
        }


def _retimed(path, hx, g, dv, tt, cfg, prof, dt: float, nf: int, lims):
    """The final time scaling of the verified table (:mod:`.retime`), kept only where the exact
    measurement of its rows stays within the shares; else the table as verified."""
    vmax, amax, jmax = lims
    rt = retime(path, hx, prof.s_f, dt, vmax, amax, jmax, (ETA_V * 0.995, ETA, ETA),
                cfg.planner.max_angular_velocity_deg_s)
    if rt.rounds >= 0:
        m = _measure_fast(path, hx, g.sg, dv.Lp, dv.Lpp, dv.Lppp, tt.bounds, rt.s_tab, dt, vmax, amax, jmax,
                          True, SCREEN)
        if m[0].max() <= max(ETA_V * 0.9995, prof.meas[0].max()) and m[1].max() <= ETA and m[2].max() <= ETA:
            return rt.s_tab, hold_times(rt.t_of_old, prof.TH, nf * dt, dt), m
    return prof.s_f, prof.TH, prof.meas


# ---------------------------------------------------------------------------
def plan_program(blocks, cfg, hexapod: Hexapod | None = None, period_s: float | None = None,
                 start_pose=None) -> Plan:
    """Plan a whole program (list of :class:`~hexacnc.gcode.blocks.Block`) for the machine ``cfg``.

    ``start_pose``: tool-tip pose (mm, deg; tool length 0) where a program without motion stands
    (default: the tool tip at ``[workspace] home_pose``); a program with motion starts where its first
    move starts.  Programs of any length: :func:`hexacnc.planner.window.plan_windows` plans them window
    by window.

    Raises :class:`PlanError` (line, limit) at the first strut-length, joint-angle
    or singularity violation along the path, or for bad input.
    """
    t_start = time.perf_counter()
    hx = hexapod if hexapod is not None else Hexapod(cfg)
    dt = float(period_s if period_s is not None else cfg.cycle.period_s)
    lims = tuple(np.asarray(v, dtype=float) for v in (cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
                                                      cfg.max_jerk_mm_s3))
    path, events = P.build_path(blocks, cfg)
    if path.n == 0:
        # no motion (empty, comments only, M2 only, dwells and events): a standstill at the start pose
        return _standstill(cfg, hx, dt, events, start_pose, t_start)
    w_f = float(np.max(lims[1] / lims[2])) / FILTER_JERK_SHARE
    nf = max(1, int(math.ceil(w_f / dt)))
    hold_min = nf * dt + 2 * dt      # the smoothed motion rests for at least two cycles at a stop
    w_plateau = nf * dt + 2 * dt     # raw plateau at every speed peak (two cycles of rounding margin)
    g = build_grid(path, hx, cfg, events)
    dv = derivatives(path, hx, g)
    jmarg, lmmarg = check_grid(path, hx, cfg, g, dv.Xg, dv.tip_g)
    dv.tip_g = None
    xlim, c, e, dd = speed_limits(path, cfg, g, dv, dt, *lims)
    rs = rests(path, events, g, hold_min, dt)
    if REACH_POINTS:
        g, dv, rs, (xlim, c, e, dd) = with_reach_points(path, hx, cfg, events, g, dv, rs, (xlim, c, e, dd), lims,
                                                        dt, SPREAD_REACH * nf * dt, hold_min)
    tt = Tightener(path, hx, g, dv, rs, xlim, c, e, dd, lims, dt, nf, w_plateau)
    prof = tighten(tt)
    del c, e, dd, xlim
    s_f, TH, meas = prof.s_f, prof.TH, prof.meas
    if RETIME:            # the verified table, run faster where its rows leave room (retime.py)
        s_f, TH, meas = _retimed(path, hx, g, dv, tt, cfg, prof, dt, nf, lims)
    s_f, TH, meas = trim_start(s_f, TH, meas, g.sg, rs.holds_s, nf, dt)
    s_f, meas = trim_end(s_f, TH, meas, g.sg, rs.holds_s, nf, dt)
    if REST_STRETCHES:    # short stretches between rests as one S-curve where that is faster (reststretch.py)
        s_f, TH, meas = rest_to_rest(path, hx, cfg, g, rs.stop_idx, rs.holds_s, s_f, TH, meas,
                                     lambda t: tt.measure(t, True), nf, dt, lims)
    line_tab, flag_tab, ev_out, pause_idx, line_times = row_tables(path, events, g, rs, s_f, TH, dt, nf)
    uv, ua, uj, va, ajr, vjr, _n = meas
    util = {"velocity": float(uv.max()), "acceleration": float(ua.max()), "jerk": float(uj.max())}
    # governor data for the sampler: block maxima (GOV samples) looking ahead
    from .sampler import governor_tables
    speed_share = np.abs(np.diff(s_f, append=s_f[-1])) / (dt * cfg.planner.rapid_feed_mm_min / 60.0)
    gov = governor_tables(uv, ua, uj, va, ajr, vjr, dt, speed_share)
    return Plan(
        cfg=cfg, hexapod=hx, path=path, dt=dt, s_tab=s_f, line_tab=line_tab, flag_tab=flag_tab,
        duration_s=(s_f.shape[0] - 1) * dt, utilisation=util, min_joint_margin_deg=jmarg,
        min_length_margin_mm=lmmarg, line_times=line_times, events=ev_out, pause_idx=pause_idx, gov=gov,
        filter_s=nf * dt, n_segments=int(np.sum(path.kind != P.BLEND)), n_blends=int(np.sum(path.kind == P.BLEND)),
        n_smoothed=int(np.sum(path.kind == P.SPLINE)), n_stops=len(rs.stop_idx), grid_points=g.n,
        feed_capped=feeds_above_rapid(blocks, cfg),
        sample_bound_mm=cfg.planner.sample_bound_mm, iterations=prof.iterations,
        grid_s=g.sg, grid_x=prof.x, grid_h=g.h, grid_stops=rs.stop_all, grid_L1=dv.Lp, grid_L2=dv.Lpp,
        grid_L3=dv.Lppp, planning_s=time.perf_counter() - t_start,
    )


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
        ev_out.append((0.0, int(blk.line), blk.kind, event_value(blk)))
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
        feed_capped=(0, None),
        grid_s=np.zeros(1), grid_x=np.zeros(1), grid_h=np.zeros(0), grid_stops=np.zeros(1, dtype=np.int64),
        grid_L1=np.zeros((1, 6)), grid_L2=np.zeros((1, 6)), grid_L3=np.zeros((1, 6)),
        planning_s=time.perf_counter() - t_start)
