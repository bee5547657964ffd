"""``hexacnc bench plan``: planner quality against TOPP-RA, and planning speed against execution time.

(a) ``topp``: a five-axis test path (lines with A/B/C, helical arcs, G64 blends) is planned by
    hexacnc; the same path (our strut lengths L(s) along the executed, blended path, as a cubic
    spline per stop-to-stop section) is time-parameterised by TOPP-RA (``toppra``) under the same
    strut velocity and acceleration limits.  Feed and angular-velocity limits are lifted for both
    so that only the strut limits bind.  hexacnc also honours the jerk limit and stands still for
    the smoothing window at every stop; TOPP-RA does not (its profile has unbounded jerk).
    Reported: both durations, their ratio, hexacnc's measured peak utilisation; TOPP-RA's own peak
    strut velocity/acceleration/jerk (its profile sampled at the cycle period through the exact
    inverse kinematics: ``toppra_utilisation``); TOPP-RA again on a grid that resolves every path
    piece (``toppra_piece_grid``); a rest-to-rest lower bound for every jerk-limited plan
    (``jerk_floor``: Ruckig 1-DOF times of each strut's net displacement between stops), shown on a
    dedicated path of exact-stop moves (``stops``).  ``programmed_feeds``: the same comparison with the
    programs' own feeds kept (F, rapids, G93); TOPP-RA gets the planner's feed bound through a
    pseudo-coordinate with a varying velocity limit.
(b) ``corpus``: every program of the G-code corpus is interpreted and placed in the workspace
    with a work offset chosen by the bench (G54 origin such that the centre of the program's
    bounding box lands on the tool tip at the home pose; no scaling), then planned.  Reported per
    file: planning time, planned duration, their ratio, or the reason it was refused.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from ..config import load_config
from ..errors import HexacncError

HELP = "planner benchmark: duration vs TOPP-RA (same path, same strut limits) and planning speed on the corpus"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--corpus", default=None,
                        help="G-code corpus directory (default: <repo>/../shared/data/gcode)")
    parser.add_argument("--skip-corpus", action="store_true", help="only the TOPP-RA comparison")
    parser.add_argument("--skip-topp", action="store_true", help="only the corpus timing")
    parser.add_argument("--gridpoints", type=int, default=2000, help="TOPP-RA grid points per section (at least)")
    parser.add_argument("--topp-files", default="tort.ngc,arcspiral.ngc,3D_Chips.ngc",
                        help="corpus programs also compared with TOPP-RA (comma-separated; empty: none)")


def _tip(cfg, P):
    from ..pose import matrix_from_euler
    P = np.asarray(P, dtype=float)
    out = P.copy()
    out[:3] = P[:3] + matrix_from_euler(*np.radians(P[3:])) @ np.asarray(cfg.tool.tip_platform_mm)
    return out


def _feeds(feed_mm_s, n: int) -> list:
    """Per-move feeds (mm/s): a scalar for all, or a sequence cycled over the moves."""
    if feed_mm_s is None:
        return [FEED_LIFTED] * n
    if np.ndim(feed_mm_s) == 0:
        return [float(feed_mm_s)] * n
    f = [float(v) for v in feed_mm_s]
    return [f[i % len(f)] for i in range(n)]


def topp_path_blocks(cfg, feed_mm_s=None):
    """A five-axis path in the default workspace: lines with rotations, helical arcs, one exact stop.

    ``feed_mm_s``: None (a feed far above what the struts allow: only strut limits bind), a number, or
    one per move (cycled)."""
    from ..gcode.blocks import Block
    home = np.asarray(cfg.home_pose, dtype=float)
    offs = [[0, 0, 0, 0, 0, 0], [100, 0, 0, 0, 0, 0], [100, 100, -30, 8, 0, 0], [-100, 100, -30, 8, -6, 10],
            [-100, -100, 20, -5, -6, 10], [60, -100, 20, -5, 5, -10], [60, 40, -60, 0, 5, -10],
            [-40, 40, 0, 0, 0, 0], [-40, -40, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]
    tips = [_tip(cfg, home + np.asarray(o, dtype=float)) for o in offs]
    F = _feeds(feed_mm_s, len(tips) - 1)
    blocks = []
    line = 1
    for i in range(len(tips) - 1):
        a, b = tips[i], tips[i + 1]
        if i == 6:
            # a helical arc in XY around the midpoint (half turn plus the Z change)
            ctr = 0.5 * (a[:3] + b[:3])
            ctr[2] = a[2]
            blocks.append(Block("arc", line, a, b, feed_mm_s=F[i], center=ctr, normal=np.array([0, 0, 1.0]),
                                blend_tolerance_mm=0.5))
        else:
            blocks.append(Block("line", line, a, b, feed_mm_s=F[i], blend_tolerance_mm=0.5, exact_stop=(i == 3)))
        line += 1
    return blocks


def smooth_path_blocks(cfg, feed_mm_s=None):
    """A gentler five-axis path: long moves meeting at shallow angles (< 20 deg), large helical arcs.

    ``feed_mm_s`` as in :func:`topp_path_blocks`."""
    from ..gcode.blocks import Block
    home = np.asarray(cfg.home_pose, dtype=float)
    offs = [[-120, -60, 0, 0, 0, 0], [0, -80, 10, 4, 0, 5], [120, -60, 20, 8, 3, 10], [130, 60, 20, 8, 3, 10],
            [20, 110, 0, 2, -3, 0], [-100, 100, -20, -4, -6, -8]]
    tips = [_tip(cfg, home + np.asarray(o, dtype=float)) for o in offs]
    F = _feeds(feed_mm_s, len(tips))
    blocks = [Block("line", i + 1, tips[i], tips[i + 1], feed_mm_s=F[i], blend_tolerance_mm=0.5)
              for i in range(len(tips) - 1)]
    # close with a large helical arc back towards the start, then a line home
    a = tips[-1]
    b = _tip(cfg, home + np.asarray([-120, -60, 0, 0, 0, 0], dtype=float))
    b2 = b.copy()
    ctr = 0.5 * (a[:3] + b2[:3])
    ctr[2] = a[2]
    r0 = np.linalg.norm((a[:3] - ctr)[:2])
    d = (b2[:3] - ctr)[:2]
    b2[:2] = ctr[:2] + d / np.linalg.norm(d) * r0
    blocks.append(Block("arc", len(blocks) + 1, a, b2, feed_mm_s=F[-1], center=ctr, normal=np.array([0, 0, 1.0]),
                        blend_tolerance_mm=0.5))
    return blocks


#: the "stops" bench path: (length mm, direction) of each exact-stop move, tool-tip translations
STOP_MOVES = ((2.0, (1, 0, 0)), (40.0, (0, 1, 0)), (5.0, (0, 0, -1)), (25.0, (-1, -1, 0)), (3.0, (1, 0, 1)),
              (12.0, (0, -1, -1)), (8.0, (-1, 1, 1)), (30.0, (1, 0, 0)), (4.0, (0, 1, -1)), (18.0, (-1, -1, 1)))


def stops_path_blocks(cfg, feed_mm_s=None, moves=STOP_MOVES):
    """Short exact-stop (G61) line moves of 2-40 mm in different directions, rest to rest, from the
    home tool tip (translations only).  ``feed_mm_s`` as in :func:`topp_path_blocks`."""
    from ..gcode.blocks import Block
    tip = _tip(cfg, np.asarray(cfg.home_pose, dtype=float))
    F = _feeds(feed_mm_s, len(moves))
    blocks = []
    for i, (length, direction) in enumerate(moves):
        u = np.asarray(direction, dtype=float)
        nxt = tip.copy()
        nxt[:3] += float(length) * u / np.linalg.norm(u)
        blocks.append(Block("line", i + 1, tip, nxt, feed_mm_s=F[i], blend_tolerance_mm=0.5, exact_stop=True))
        tip = nxt
    return blocks


def bench_topp(cfg, gridpoints: int, corpus: Path | None = None,
               corpus_files=("tort.ngc", "arcspiral.ngc", "3D_Chips.ngc"), programmed_feeds: bool = True) -> dict:
    out = {"corners": _bench_topp(cfg, gridpoints, topp_path_blocks(cfg),
                                  "9 moves (lines with A/B/C, helical arc), right-angle corners, G64 P0.5, "
                                  "one exact stop"),
           "smooth": _bench_topp(cfg, gridpoints, smooth_path_blocks(cfg),
                                 "6 moves with A/B/C meeting at shallow angles, large helical arc, G64 P0.5")}
    if corpus is not None:
        out["corpus"] = bench_topp_corpus(cfg, gridpoints, corpus, corpus_files)
    out["stops"] = _bench_topp(cfg, gridpoints, stops_path_blocks(cfg),
                               f"{len(STOP_MOVES)} exact-stop (G61) tool-tip translations of 2-40 mm in different "
                               "directions, rest to rest, feeds lifted")
    if programmed_feeds:
        fm = BENCH_FEEDS_MM_MIN
        pf = {"note": "the same comparison with the programs' own feeds kept: F words (mm/min), rapids at "
                      "[planner] rapid_feed_mm_min, G93 inverse time; dwell times zeroed (the stops remain); the "
                      "angular-velocity limit lifted for both as in the lifted comparison. TOPP-RA gets the "
                      "planner's feed bound |d tip/ds| s_dot <= F (tip xyz speed; deg/s on rotary-only moves) "
                      "through a 7th pseudo-coordinate q7 = scaled path parameter whose velocity limit "
                      "F/|d tip/ds| varies along the path (toppra JointVelocityConstraintVarying, evaluated on "
                      "every piece overlapping each grid cell) and whose acceleration limit "
                      f"({PSEUDO_ACC_LIFTED:g}) never binds. Bench paths corners/smooth: F "
                      + "/".join(f"{f:g}" for f in fm) + " mm/min cycled over their moves",
              "corners": _bench_topp(cfg, gridpoints, topp_path_blocks(cfg, [f / 60.0 for f in fm]),
                                     "corners, F " + "/".join(f"{f:g}" for f in fm) + " mm/min cycled per move",
                                     programmed_feeds=True),
              "smooth": _bench_topp(cfg, gridpoints, smooth_path_blocks(cfg, [f / 60.0 for f in fm]),
                                    "smooth, F " + "/".join(f"{f:g}" for f in fm) + " mm/min cycled per move",
                                    programmed_feeds=True)}
        if corpus is not None:
            pf.update(bench_topp_corpus(cfg, gridpoints, corpus, corpus_files, programmed_feeds=True))
        out["programmed_feeds"] = pf
    return out


def _lift_feeds(blocks):
    """The same blocks with feeds lifted (only strut limits bind) and dwell times zeroed (still stops)."""
    out = []
    for b in blocks:
        kw = {}
        if b.feed_mm_s is not None or b.inverse_time_s is not None:
            kw.update(feed_mm_s=FEED_LIFTED, inverse_time_s=None)
            if b.feed_deg_s is not None:
                kw["feed_deg_s"] = FEED_LIFTED
        if b.seconds:
            kw["seconds"] = 0.0
        out.append(dataclasses.replace(b, **kw) if kw else b)
    return out


def _zero_dwells(blocks):
    """The same blocks with dwell times zeroed (still stops); feeds as programmed."""
    return [dataclasses.replace(b, seconds=0.0) if b.seconds else b for b in blocks]


def bench_topp_corpus(cfg, gridpoints: int, corpus: Path, files, programmed_feeds: bool = False) -> dict:
    """TOPP-RA against hexacnc on corpus programs (bench placement, dwells zeroed, feeds lifted unless
    ``programmed_feeds``)."""
    res = {"placement": "G54 origin = home tool-tip position minus the program's bounding-box centre; no scaling",
           "feeds": ("as programmed (F, rapids at [planner] rapid_feed_mm_min, G93) for both; " if programmed_feeds
                     else "lifted for both (only strut velocity/acceleration bind; hexacnc also its jerk limit); ")
           + "dwell times zeroed (the stops remain)"}
    for name in files:
        f = corpus / name
        if not f.is_file():
            res[name] = {"skipped": f"no file {f}"}
            continue
        try:
            prog, wo = _place(f.read_text(encoding="utf-8", errors="replace"), name, cfg)
            blocks = _zero_dwells(prog.blocks) if programmed_feeds else _lift_feeds(prog.blocks)
            r = _bench_topp(cfg, gridpoints, blocks, f"{name} (corpus)", programmed_feeds=programmed_feeds)
        except HexacncError as exc:
            res[name] = {"planned": False, "reason": str(exc)}
            continue
        r["work_offset_mm"] = [round(v, 3) for v in wo]
        r.pop("sections", None)
        res[name] = r
    return res


#: feed (mm/s) standing for "no feed limit" in the TOPP-RA comparison
FEED_LIFTED = 1e6
#: TOPP-RA grid step (path units) on long sections, and the cap on its grid points per section
TOPPRA_STEP = 0.25
TOPPRA_MAX_GRID = 40_000
#: acceleration bound of the path pseudo-coordinate that carries the feed limit to TOPP-RA (never binds)
PSEUDO_ACC_LIFTED = 1e12
#: TOPP-RA grid cells per path piece in the piece-resolved comparison (``toppra_piece_grid``)
TOPPRA_PIECE_POINTS = 32
#: programmed feeds of the two bench paths in the programmed-feeds comparison (mm/min, cycled per move)
BENCH_FEEDS_MM_MIN = (6000.0, 3000.0, 60000.0)


def _lifted_config(cfg, programmed_feeds: bool):
    """The angular-velocity limit lifted; also the rapid feed unless the program's feeds are kept."""
    if programmed_feeds:
        pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6)
    else:
        pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6, rapid_feed_mm_min=1e9)
    return cfg.replace(planner=pc)


def _rest_points(plan) -> list:
    """Path positions (mm) where hexacnc's plan is at rest: programmed stops, stopping events, both ends."""
    path = plan.path
    rest = {float(v) for v in np.asarray(plan.grid_s)[np.asarray(plan.grid_x) <= 0.0]}
    return sorted({0.0, path.total} | {float(path.s0[m] + path.slen[m]) for m in path.stops_after} | rest)


def _sections(stops) -> list:
    return [(a, b) for a, b in zip(stops[:-1], stops[1:]) if b - a >= 1e-9]


def feed_speed_limit(path, s: np.ndarray, half_cell) -> np.ndarray:
    """The planner's feed bound on the path speed (s-units/s) at ``s`` (mm): ``feed / |d tip/ds|``.

    ``|d tip/ds|`` is the planner's measure (tip xyz speed per s-unit; for rotary-only stretches the
    angular speed in deg), by the same central difference.  Every piece overlapping
    ``[s - half_cell, s + half_cell]`` (``half_cell`` a number or one per point) is taken (clamped into the piece), so a lower feed on a piece
    between two grid points is not missed.
    """
    from ..planner.plan import FD_STEP
    s = np.asarray(s, dtype=float)
    lo = path.piece_at(s - half_cell)
    hi = path.piece_at(s + half_cell)
    out = np.full(s.shape, np.inf)
    for k in range(int(np.max(hi - lo)) + 1 if s.size else 0):
        p = np.minimum(lo + k, hi)
        sc = np.clip(s, path.s0[p], path.s0[p] + path.slen[p])
        tm, tp = path.tips(p, [sc - FD_STEP, sc + FD_STEP])
        dtip = (tp - tm) / (2 * FD_STEP)
        xyz = np.linalg.norm(dtip[:, :3], axis=1)
        ang = np.linalg.norm(np.degrees(dtip[:, 3:]), axis=1)
        meas = np.where(xyz > 1e-6, xyz, np.maximum(ang, 1e-12))
        out = np.minimum(out, path.feed[p] / meas)
    return out


@dataclasses.dataclass
class _Section:
    a: float                    #: start (mm of path)
    b: float                    #: end
    grid: np.ndarray            #: TOPP-RA grid, scaled path parameter in [0, 1]
    sd: np.ndarray              #: TOPP-RA path speed at the grid (scaled units / s)
    duration_s: float
    feed_sd: np.ndarray | None  #: feed bound on the scaled path speed at the grid (programmed feeds only)


def _piece_points(path, a: float, b: float, k: int, base: np.ndarray, min_gap: float) -> np.ndarray:
    """``base`` (sorted, in [a, b]) plus ``k + 1`` evenly spaced points on every piece overlapping [a, b]
    (its ends included), points closer than ``min_gap`` merged; both ends kept exactly."""
    m = np.nonzero((path.s0 < b) & (path.s0 + path.slen > a))[0]
    pts = [base] + [np.linspace(path.s0[i], path.s0[i] + path.slen[i], k + 1) for i in m]
    g = np.unique(np.clip(np.concatenate(pts), a, b))
    g = g[np.concatenate([[True], np.diff(g) > min_gap])]
    g[0] = a
    if g[-1] < b - min_gap:
        g = np.append(g, b)
    g[-1] = b
    return g


def _toppra_section(plan, cfg, a: float, b: float, gridpoints: int, feeds: bool,
                    piece_points: int = 0) -> _Section:
    """TOPP-RA on the stop-to-stop section [a, b] of the plan's path: strut v/a limits, and with
    ``feeds`` the feed bound through a 7th pseudo-coordinate ``q7 = (s - a) / (b - a)`` whose velocity
    limit varies along the path (``JointVelocityConstraintVarying``) and whose acceleration never binds.

    ``piece_points`` > 0: TOPP-RA's grid also holds every piece boundary and ``piece_points`` cells per
    piece (short blends and arcs included), the L(s) samples 4x as many; 0: the uniform grid alone."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint
    from ..planner import path as P
    path, hx = plan.path, plan.hexapod
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float)
    # dense samples of L(s) on the section (2 samples per 0.05 mm at least)
    n = max(200, int((b - a) / 0.05))
    s = np.linspace(a, b, n + 1)
    if piece_points > 0:
        s = _piece_points(path, a, b, 4 * piece_points, s, 1e-5)
    s_in = s.copy()
    s_in[-1] = b - 1e-9
    s_in[0] = a + 1e-9
    X = path.platform(path.piece_at(s_in), s_in)
    L = P.strut_lengths(X, hx.plat, hx.base)
    # path parameter scaled to [0, 1]: TOPP-RA's LP tolerances fail on fine grids in mm (uncontrollable)
    sig = (s - a) / (b - a)
    ng = int(min(TOPPRA_MAX_GRID, max(gridpoints, (b - a) / TOPPRA_STEP)))
    grid = np.linspace(0.0, 1.0, ng + 1)
    if piece_points > 0:
        grid = (_piece_points(path, a, b, piece_points, a + grid * (b - a), 1e-4) - a) / (b - a)
    vl = np.stack([-vmax, vmax], axis=1)
    al = np.stack([-amax, amax], axis=1)
    feed_sd = None
    if feeds:
        spl = ta.SplineInterpolator(sig, np.column_stack([L, sig]))
        sg = np.clip(a + grid * (b - a), a, b)
        hs = np.diff(sg)
        half = 0.5 * np.maximum(np.concatenate([[0.0], hs]), np.concatenate([hs, [0.0]]))
        feed_sd = np.minimum(feed_speed_limit(path, sg, half) / (b - a), 1e12)
        vlim = np.empty((grid.shape[0], 7, 2))
        vlim[:, :6, :] = vl[None]
        vlim[:, 6, 0] = -feed_sd
        vlim[:, 6, 1] = feed_sd
        last = grid.shape[0] - 1

        def vlim_at(x: float) -> np.ndarray:
            """The limits at the grid point nearest to ``x`` (TOPP-RA asks at its grid points)."""
            i = min(last, int(np.searchsorted(grid, x)))
            if i > 0 and x - grid[i - 1] < grid[i] - x:
                i -= 1
            return vlim[i]
        cons = [constraint.JointVelocityConstraintVarying(vlim_at),
                constraint.JointAccelerationConstraint(np.vstack([al, [[-PSEUDO_ACC_LIFTED, PSEUDO_ACC_LIFTED]]]))]
    else:
        spl = ta.SplineInterpolator(sig, L)
        cons = [constraint.JointVelocityConstraint(vl), constraint.JointAccelerationConstraint(al)]
    inst = algo.TOPPRA(cons, spl, gridpoints=grid, parametrizer="ParametrizeConstAccel")
    traj = inst.compute_trajectory(0, 0)
    if traj is None:
        raise HexacncError(f"TOPP-RA found no parameterisation of section [{a:.3f}, {b:.3f}]")
    return _Section(a, b, np.asarray(inst.problem_data.gridpoints, dtype=float),
                    np.asarray(inst.problem_data.sd_vec, dtype=float), float(traj.duration), feed_sd)


def toppra_utilisation(plan, cfg, sections) -> dict:
    """Peak strut velocity, acceleration and jerk of TOPP-RA's trajectory as fractions of the limits.

    Each section's profile (constant path acceleration between grid points, as TOPP-RA's
    ``ParametrizeConstAccel``) is sampled at the cycle period (times clamped to the section's end),
    padded with three samples at rest on both sides, mapped through the exact inverse kinematics
    of the executed path, and differentiated by finite differences at the cycle period.
    """
    from ..planner import path as P
    path, hx = plan.path, plan.hexapod
    dt = float(cfg.cycle.period_s)
    lim = [np.asarray(x, dtype=float) for x in (cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2,
                                                   cfg.max_jerk_mm_s3)]
    peak = np.zeros(3)
    for sec in sections:
        h = np.diff(sec.grid)
        v0, v1 = sec.sd[:-1], sec.sd[1:]
        dtau = 2.0 * h / np.maximum(v0 + v1, 1e-300)
        ts = np.concatenate([[0.0], np.cumsum(dtau)])
        u = (v1 * v1 - v0 * v0) / (2.0 * h)
        T = ts[-1]
        t = np.minimum(np.arange(int(np.ceil(T / dt)) + 1) * dt, T)
        i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, h.shape[0] - 1)
        tau = t - ts[i]
        sig = np.clip(sec.grid[i] + v0[i] * tau + 0.5 * u[i] * tau * tau, sec.grid[i], sec.grid[i + 1])
        s = np.clip(sec.a + sig * (sec.b - sec.a), sec.a + 1e-9, sec.b - 1e-9)
        L = P.strut_lengths(path.platform(path.piece_at(s), s), hx.plat, hx.base)
        L = np.vstack([np.repeat(L[:1], 3, axis=0), L, np.repeat(L[-1:], 3, axis=0)])
        for k in range(3):
            L = np.diff(L, axis=0) / dt
            peak[k] = max(peak[k], float(np.max(np.abs(L) / lim[k][None])))
    return {"velocity": float(peak[0]), "acceleration": float(peak[1]), "jerk": float(peak[2])}


def rest_to_rest_time(d_mm: float, v_max: float, a_max: float, j_max: float) -> float:
    """Minimum time (s) of any 1-DOF profile moving ``|d_mm|`` from rest to rest under
    ``|v| <= v_max``, ``|a| <= a_max``, ``|j| <= j_max``: Ruckig's time-optimal duration
    (offline ``calculate``; constructed with one argument, never the cloud ``max_waypoints``).
    ``j_max = inf``: the closed-form bang-bang time (:func:`double_s_time`)."""
    d = abs(float(d_mm))
    if d == 0.0:
        return 0.0
    if not math.isfinite(j_max):
        return double_s_time(d, v_max, a_max, j_max)
    from ruckig import InputParameter, Result, Ruckig, Trajectory
    otg = Ruckig(1)
    inp = InputParameter(1)
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [d], [0.0], [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [float(v_max)], [float(a_max)], [float(j_max)]
    traj = Trajectory(1)
    res = otg.calculate(inp, traj)
    if res not in (Result.Working, Result.Finished):
        raise HexacncError(f"Ruckig could not time a rest-to-rest move of {d} mm: {res}")
    return float(traj.duration)


def double_s_time(d_mm: float, v_max: float, a_max: float, j_max: float) -> float:
    """Closed-form minimum rest-to-rest time (s) over ``|d_mm|`` under v/a/j limits (``j_max`` may be inf)."""
    d, v, a, j = abs(float(d_mm)), float(v_max), float(a_max), float(j_max)
    if d == 0.0:
        return 0.0
    if not math.isfinite(j):
        return d / v + v / a if d >= v * v / a else 2.0 * math.sqrt(d / a)
    # time to reach speed w from rest (and the distance covered is w * t / 2 by symmetry)
    ta = (lambda w: w / a + a / j if w * j >= a * a else 2.0 * math.sqrt(w / j))
    if d >= v * ta(v):
        return d / v + ta(v)
    # v_max not reached: peak speed w with d = w * ta(w)
    if a * a / j * (a / j) * 2.0 <= d:
        # a_max reached: d = w^2 / a + w a / j
        w = 0.5 * (-a * a / j + math.sqrt((a * a / j) ** 2 + 4.0 * a * d))
        return 2.0 * ta(w)
    return 4.0 * (d / (2.0 * j)) ** (1.0 / 3.0)


def jerk_floor(plan, cfg, stops=None, max_moves: int = 20) -> dict:
    """A lower bound on the duration of every jerk-limited plan that rests where this plan rests.

    Per rest-to-rest section and strut i the strut must move by the net ``|dL_i|`` from rest to rest
    under its v/a/j limits: at least :func:`rest_to_rest_time`; the section takes at least the
    maximum over struts; the sum over sections bounds the whole path (stop holds and dwells not
    counted).  The same with ``j_max = inf`` bounds every plan under v/a limits only (TOPP-RA's problem).
    """
    from ..planner import path as P
    path, hx = plan.path, plan.hexapod
    stops = _rest_points(plan) if stops is None else stops
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float)
    jmax = np.asarray(cfg.max_jerk_mm_s3, dtype=float)
    secs = _sections(stops)
    if not secs:
        return {"jerk_floor_s": 0.0, "bang_bang_floor_s": 0.0, "rest_to_rest_sections": 0}
    ends = np.array(secs, dtype=float)
    sa, sb = ends[:, 0], ends[:, 1]
    La = P.strut_lengths(path.platform(path.piece_at(sa), sa), hx.plat, hx.base)
    Lb = P.strut_lengths(path.platform(path.piece_at(np.maximum(sb - 1e-9, sa)), sb), hx.plat, hx.base)
    dL = np.abs(Lb - La)
    moves = []
    fl = bb = 0.0
    for k in range(dL.shape[0]):
        tj = max(rest_to_rest_time(dL[k, i], vmax[i], amax[i], jmax[i]) for i in range(6))
        tb = max(double_s_time(dL[k, i], vmax[i], amax[i], math.inf) for i in range(6))
        fl += tj
        bb += tb
        moves.append({"s_from_mm": round(float(sa[k]), 4), "s_to_mm": round(float(sb[k]), 4),
                      "max_abs_dL_mm": round(float(dL[k].max()), 6), "jerk_floor_s": round(tj, 6),
                      "bang_bang_floor_s": round(tb, 6)})
    out = {"jerk_floor_s": fl, "bang_bang_floor_s": bb, "rest_to_rest_sections": len(moves)}
    if len(moves) <= max_moves:
        out["moves"] = moves
    return out


def _bench_topp(cfg, gridpoints: int, blocks, label: str, programmed_feeds: bool = False) -> dict:
    from ..planner import plan_program

    cfg = _lifted_config(cfg, programmed_feeds)
    t0 = time.perf_counter()
    plan = plan_program(blocks, cfg)
    t_plan = time.perf_counter() - t0
    # sections between stops, on the executed (blended) path
    # (every point where hexacnc's plan is at rest: programmed stops and stopping events alike)
    stops = _rest_points(plan)
    t1 = time.perf_counter()
    secs = [_toppra_section(plan, cfg, a, b, gridpoints, programmed_feeds) for a, b in _sections(stops)]
    t_topp = time.perf_counter() - t1
    total = float(sum(sec.duration_s for sec in secs))
    tu = toppra_utilisation(plan, cfg, secs)
    t1 = time.perf_counter()
    fine = [_toppra_section(plan, cfg, a, b, gridpoints, programmed_feeds, TOPPRA_PIECE_POINTS)
            for a, b in _sections(stops)]
    t_fine = time.perf_counter() - t1
    fine_s = float(sum(sec.duration_s for sec in fine))
    piece_grid = {
        "duration_s": round(fine_s, 6),
        "ratio": round(plan.duration_s / fine_s, 6),
        "within_5_percent": bool(plan.duration_s <= 1.05 * fine_s),
        "utilisation": {k: round(v, 6) for k, v in toppra_utilisation(plan, cfg, fine).items()},
        "grid_points": int(sum(sec.grid.shape[0] for sec in fine)),
        "grid_points_uniform": int(sum(sec.grid.shape[0] for sec in secs)),
        "planning_s": round(t_fine, 4),
        "note": "TOPP-RA as in toppra_duration_s (same constraints) on a grid that also holds every path piece's "
                f"ends and {TOPPRA_PIECE_POINTS} cells per piece (L(s) samples 4x as dense): the uniform grid "
                f"({TOPPRA_STEP} mm) steps over short blends and arcs, where TOPP-RA's profile then exceeds the "
                "strut acceleration limit (toppra_utilisation); ratio = hexacnc / this duration; utilisation "
                "measured as toppra_utilisation",
    }
    fl = jerk_floor(plan, cfg, stops)
    floor = _floor_report(fl, total, plan.duration_s)
    tu_note = ("TOPP-RA's trajectory (constant path acceleration between its grid points) sampled at the cycle "
               f"period ({float(cfg.cycle.period_s) * 1e3:g} ms), strut lengths by exact inverse kinematics of "
               "the executed path, finite differences at the cycle period, peak |v|, |a|, |jerk| over the "
               "limits; hexacnc_utilisation is the same measurement of hexacnc's table")
    if programmed_feeds:
        return {
            "path": label,
            "hexacnc_duration_s": round(plan.duration_s, 6),
            "toppra_duration_s": round(total, 6),
            "ratio": round(plan.duration_s / total, 6),
            "within_5_percent": bool(plan.duration_s <= 1.05 * total),
            "hexacnc_utilisation": {k: round(v, 6) for k, v in plan.utilisation.items()},
            "utilisation_ok": bool(max(plan.utilisation.values()) <= 1.0),
            "toppra_utilisation": {k: round(v, 6) for k, v in tu.items()},
            "toppra_utilisation_note": tu_note,
            "hexacnc_planning_s": round(t_plan, 4),
            "toppra_planning_s": round(t_topp, 4),
            "feed_bound": _feed_bound(plan, secs),
            "jerk_floor": floor,
            "toppra_piece_grid": piece_grid,
        }
    from ..planner.topp import interval_times
    gs = np.asarray(plan.grid_s)
    raw_s = float(np.sum(interval_times(np.maximum(np.diff(gs), 0.0), np.asarray(plan.grid_x))))
    dec = topp_decomposition(plan, cfg)
    return {
        "path": label,
        "hexacnc_duration_s": round(plan.duration_s, 6),
        "toppra_duration_s": round(total, 6),
        "ratio": round(plan.duration_s / total, 6),
        "within_5_percent": bool(plan.duration_s <= 1.05 * total),
        "hexacnc_utilisation": {k: round(v, 6) for k, v in plan.utilisation.items()},
        "utilisation_ok": bool(max(plan.utilisation.values()) <= 1.0),
        "hexacnc_planning_s": round(t_plan, 4),
        "toppra_planning_s": round(t_topp, 4),
        "sections": [{"s_from": round(sec.a, 4), "s_to": round(sec.b, 4), "toppra_s": round(sec.duration_s, 6)}
                     for sec in secs],
        "note": "TOPP-RA: strut velocity+acceleration only (no jerk limit, no standstill at stops); "
                "hexacnc: also jerk-limited, stops held for the smoothing window",
        "jerk_filter_s": round(float(plan.filter_s), 6),
        "hexacnc_topp_profile_s": round(raw_s, 6),
        "hexacnc_topp_profile_note": "duration of hexacnc's own TOPP profile, whose speed limits include the "
                                     "constant-speed jerk bound |d3L/ds3| s_dot^3 <= RHO_J ETA j_max, the spread of "
                                     "slow spots over the filter's reach and the verification's local lowering; "
                                     "before the moving-average jerk filter, without stop holds",
        "topp_decomposition_s": {k: round(v, 6) for k, v in dec.items()},
        "topp_decomposition_ratio": {k: round(v / total, 6) for k, v in dec.items()},
        "topp_decomposition_note": "hexacnc's own TOPP pass on hexacnc's grid, no jerk filter, no holds: "
                                   "va_full = strut v/a at 100 % (TOPP-RA's problem: checks the pass); "
                                   "va_plan = v 99.5 %, a ETA*ACC_SHARE (the shares the plan may use); "
                                   "va_full_jerk_const_speed = va_full plus |d3L/ds3| s_dot^3 <= j_max, the jerk "
                                   "at constant path speed (an estimate for jerk-limited profiles, not a proven "
                                   "bound: a profile that accelerates through a stretch can exceed it locally); "
                                   "plan_limits = every speed limit of the plan (shares, RHO_J jerk bound, "
                                   "junction curvature steps) before the filter's spreading; plan_limits_spread "
                                   "= the same after spreading slow spots over the moving-average filter's "
                                   "reach (what the plan starts its verification from)",
        "gap_reason": "jerk limiting by a moving average of width jerk_filter_s = 2 max(a_max/j_max): every "
                      "stop, slowdown and curvature-bound stretch costs time a jerk-free profile does not pay; "
                      "a jerk-aware (third-order) pass that only pays where the jerk limit binds is not implemented",
        "toppra_utilisation": {k: round(v, 6) for k, v in tu.items()},
        "toppra_utilisation_note": tu_note,
        "jerk_floor": floor,
        "toppra_piece_grid": piece_grid,
    }


def _floor_report(fl: dict, toppra_s: float, hexacnc_s: float) -> dict:
    jf, bb = fl["jerk_floor_s"], fl["bang_bang_floor_s"]
    out = {"jerk_floor_s": round(jf, 6), "bang_bang_floor_s": round(bb, 6),
           "toppra_duration_s": round(toppra_s, 6), "hexacnc_duration_s": round(hexacnc_s, 6),
           "floor_over_toppra": round(jf / toppra_s, 6) if toppra_s > 0 else None,
           "hexacnc_over_floor": round(hexacnc_s / jf, 6) if jf > 0 else None,
           "bang_bang_floor_le_toppra": bool(bb <= toppra_s * (1 + 1e-9)),
           "floor_excludes_5_percent": bool(jf > 1.05 * toppra_s),
           "rest_to_rest_sections": fl["rest_to_rest_sections"],
           "note": "lower bound on every plan that rests where hexacnc's plan rests (programmed stops and "
                   "stopping events): per rest-to-rest section the max over struts of the minimum time to move "
                   "that strut by its net |dL| from rest to rest under |v|<=v_max, |a|<=a_max, |j|<=j_max "
                   "(Ruckig 1-DOF time-optimal, offline), summed over sections; stop holds and dwells not "
                   "counted. bang_bang_floor_s: the same with j_max infinite (closed form), a lower bound for "
                   "TOPP-RA's problem. floor_excludes_5_percent: jerk_floor_s > 1.05 x TOPP-RA, i.e. no "
                   "jerk-limited plan of this path can be within 5 % of TOPP-RA. Only net displacements are "
                   "used, so the bound is weak on sections with many moves between stops"}
    if "moves" in fl:
        out["moves"] = fl["moves"]
    return out


def _feed_bound(plan, secs) -> dict:
    """Where TOPP-RA's profile runs at the feed bound (within 0.1 %), by path length, overall and per line."""
    path = plan.path
    tot = bound = 0.0
    per_line: dict[int, list] = {}
    for sec in secs:
        if sec.feed_sd is None:
            continue
        n = sec.grid.shape[0]
        w = np.full(n, (sec.b - sec.a) / max(n - 1, 1))
        w[0] = w[-1] = 0.5 * w[0]
        at = sec.sd >= 0.999 * sec.feed_sd
        s = np.clip(sec.a + sec.grid * (sec.b - sec.a), sec.a + 1e-9, sec.b - 1e-9)
        lines = path.line[path.piece_at(s)]
        tot += float(w.sum())
        bound += float(w[at].sum())
        for ln in np.unique(lines):
            m = lines == ln
            acc = per_line.setdefault(int(ln), [0.0, 0.0])
            acc[0] += float(w[m].sum())
            acc[1] += float(w[m & at].sum())
    out = {"share": round(bound / tot, 4) if tot > 0 else None,
           "note": "share of the path length (TOPP-RA grid points weighted by spacing) where TOPP-RA's path "
                   "speed is within 0.1 % of the feed bound; elsewhere the strut velocity/acceleration limits "
                   "(or the stops) bind"}
    if len(per_line) <= 20:
        out["share_per_line"] = {str(k): round(v[1] / v[0], 4) if v[0] > 0 else None
                                 for k, v in sorted(per_line.items())}
    return out


def topp_decomposition(plan, cfg) -> dict:
    """Durations (s) of hexacnc's TOPP pass on the plan's own grid under three constraint sets.

    Only strut limits (the bench lifts feeds); the plan's stops are kept.  See the JSON note.
    """
    from ..planner.plan import ACC_SHARE, ETA, RHO_J, RHO_STEP, _dilate_min
    from ..planner.topp import accel_coefficients, forward_backward, interval_times
    h = np.asarray(plan.grid_h)
    Lp, Lpp, Lppp = (np.asarray(a) for a in (plan.grid_L1, plan.grid_L2, plan.grid_L3))
    vmax = np.asarray(cfg.max_velocity_mm_s, dtype=float)
    amax = np.asarray(cfg.max_acceleration_mm_s2, dtype=float)
    jmax = np.asarray(cfg.max_jerk_mm_s3, dtype=float)
    rest = np.concatenate([np.asarray(plan.grid_stops, dtype=np.int64), [0, h.shape[0]]])
    rest = rest[rest <= h.shape[0]]

    def duration(v_share: float, a_share: float, j_share: float | None, plan_limits: bool = False,
                 spread: bool = False) -> float:
        aLp = np.abs(Lp)
        with np.errstate(divide="ignore", over="ignore"):
            xl = np.min(np.where(aLp > 1e-12, (v_share * vmax[None] / np.maximum(aLp, 1e-300)) ** 2, np.inf), axis=1)
            if j_share is not None:
                aL3 = np.abs(Lppp)
                xl = np.minimum(xl, np.min(np.where(aL3 > 1e-12, (j_share * jmax[None] / np.maximum(aL3, 1e-300))
                                                    ** (2.0 / 3.0), np.inf), axis=1))
        c, e, d, xmvc = accel_coefficients(Lp, Lpp, a_share * amax)
        xl = np.minimum(xl, xmvc)
        if plan_limits:
            # the planner's curvature-step bound at tangent-continuous junctions
            jn = np.nonzero(h == 0)[0]
            if jn.size:
                dL = np.abs(Lpp[jn + 1] - Lpp[jn])
                with np.errstate(divide="ignore", over="ignore"):
                    xs = np.min(np.where(dL > 1e-12, RHO_STEP * jmax[None] * plan.dt / np.maximum(dL, 1e-300),
                                         np.inf), axis=1)
                xl[jn] = np.minimum(xl[jn], xs)
                xl[jn + 1] = np.minimum(xl[jn + 1], xs)
        if spread:
            xl[rest[rest < xl.shape[0]]] = np.inf
            xl = _dilate_min(np.asarray(plan.grid_s), xl, 0.5 * float(plan.filter_s))
        xl[rest[rest < xl.shape[0]]] = 0.0
        return float(np.sum(interval_times(h, forward_backward(h, xl, c, e, d))))

    return {"va_full": duration(1.0, 1.0, None),
            "va_plan": duration(0.995, ETA * ACC_SHARE, None),
            "va_full_jerk_const_speed": duration(1.0, 1.0, 1.0),
            "plan_limits": duration(0.995, ETA * ACC_SHARE, RHO_J * ETA, plan_limits=True),
            "plan_limits_spread": duration(0.995, ETA * ACC_SHARE, RHO_J * ETA, plan_limits=True, spread=True)}


def _place(text: str, name: str, cfg):
    """Interpret once at G54 = 0 to find the bounding box, then again with the centring work offset."""
    from ..gcode.factory import program_from_config
    from ..pose import matrix_from_euler
    home = np.asarray(cfg.home_pose, dtype=float)
    zero = [0.0, 0.0, 0.0] + [float(v) for v in home[3:]]
    prog = program_from_config(text, name, cfg, work_offsets={1: zero})
    E = np.array([b.end for b in prog.blocks if getattr(b, "end", None) is not None])
    if E.size == 0:
        return prog, [0.0, 0.0, 0.0]
    ctr = 0.5 * (E[:, :3].min(axis=0) + E[:, :3].max(axis=0))
    tip_home = home[:3] + matrix_from_euler(*np.radians(home[3:])) @ np.asarray(cfg.tool.tip_platform_mm)
    off = tip_home - ctr
    wo = [float(v) for v in off] + [float(v) for v in home[3:]]
    return program_from_config(text, name, cfg, work_offsets={1: wo}), wo[:3]


def bench_corpus(cfg, corpus: Path) -> dict:
    from ..planner import plan_program
    files = sorted(corpus.glob("*.ngc"))
    out = []
    sum_exec = 0.0
    sum_plan = 0.0
    sum_cpu = 0.0
    for f in files:
        rec = {"file": f.name}
        try:
            text = f.read_text(encoding="utf-8", errors="replace")
            t0 = time.perf_counter()
            prog, wo = _place(text, f.name, cfg)
            t_interp = time.perf_counter() - t0
            rec["work_offset_mm"] = [round(v, 3) for v in wo]
            t0 = time.perf_counter()
            c0 = time.process_time()
            plan = plan_program(prog.blocks, cfg)
            t_plan = time.perf_counter() - t0
            c_plan = time.process_time() - c0
        except HexacncError as exc:
            rec.update({"planned": False, "reason": str(exc), "error": type(exc).__name__,
                        "line": getattr(exc, "line", None), "limit": getattr(exc, "limit", None)})
            out.append(rec)
            continue
        rec.update({"planned": True, "blocks": len(prog.blocks), "interpret_s": round(t_interp, 4),
                    "planning_s": round(t_plan, 4), "planning_cpu_s": round(c_plan, 4),
                    "duration_s": round(plan.duration_s, 4),
                    "ratio": round(plan.duration_s / t_plan, 2),
                    "ratio_cpu": round(plan.duration_s / max(c_plan, 1e-9), 2),
                    "utilisation": {k: round(v, 4) for k, v in plan.utilisation.items()},
                    "iterations": plan.iterations})
        sum_exec += plan.duration_s
        sum_plan += t_plan
        sum_cpu += c_plan
        out.append(rec)
    ratios = [r["ratio"] for r in out if r.get("planned")]
    return {"corpus": str(corpus), "files": out,
            "min_ratio": min(ratios) if ratios else None,
            "total_ratio": round(sum_exec / sum_plan, 2) if sum_plan > 0 else None,
            "min_ratio_cpu": min((r["ratio_cpu"] for r in out if r.get("planned")), default=None),
            "total_ratio_cpu": round(sum_exec / sum_cpu, 2) if sum_cpu > 0 else None,
            "load_average_1min": round(os.getloadavg()[0], 2),
            "target_ratio": 100.0,
            "placement": "G54 origin = home tool-tip position minus the program's bounding-box centre; no scaling"}


def main(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    res: dict = {"bench": "plan", "machine": cfg.name, "cpu_count": os.cpu_count()}
    corpus = Path(args.corpus) if args.corpus else Path(__file__).resolve().parents[3] / "shared/data/gcode"
    if not args.skip_topp:
        files = [f for f in (args.topp_files or "").split(",") if f.strip()]
        res["topp"] = bench_topp(cfg, args.gridpoints, corpus if (files and corpus.is_dir()) else None,
                                 tuple(f.strip() for f in files))
    if not args.skip_corpus:
        if corpus.is_dir():
            res["corpus"] = bench_corpus(cfg, corpus)
        else:
            res["corpus"] = {"skipped": f"no corpus at {corpus}"}
    print(json.dumps(res))
    return 0
