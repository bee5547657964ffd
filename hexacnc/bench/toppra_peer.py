"""TOPP-RA peer comparison for ``hexacnc bench plan`` (``topp``): the bench paths, TOPP-RA on the
stop-to-stop sections of hexacnc's executed path under the same strut limits (feeds lifted, or kept through
a pseudo-coordinate), TOPP-RA's own strut utilisation, the piece-resolved grid, and the decomposition of
hexacnc's TOPP pass.  The rest-to-rest jerk floor is in :mod:`hexacnc.bench.jerkfloor`."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from ..errors import HexacncError
from .jerkfloor import _floor_report, _rest_points, _sections, jerk_floor
from .placement import PLACEMENT_NOTE, _place

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


def _tip(cfg, P):
    """Tool-tip pose (mm, deg) of the platform pose ``P`` (mm, deg): its orientation kept as given."""
    from ..daemon.program import tool_tip_pose_deg
    P = np.asarray(P, dtype=float)
    out = P.copy()
    out[:3] = tool_tip_pose_deg(cfg, np.concatenate([P[:3], np.radians(P[3:])]))[:3]
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
    res = {"placement": PLACEMENT_NOTE,
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
            r = _bench_topp(cfg, gridpoints, blocks, f"{name} (corpus)", programmed_feeds=programmed_feeds,
                            jerk_opt=False)
        except HexacncError as exc:
            res[name] = {"planned": False, "reason": str(exc)}
            continue
        r["work_offset_mm"] = [round(v, 3) for v in wo]
        r.pop("sections", None)
        res[name] = r
    return res


def _lifted_config(cfg, programmed_feeds: bool):
    """The angular-velocity limit lifted; also the rapid feed unless the program's feeds are kept; the
    workspace box lifted (:func:`lift_workspace`)."""
    if programmed_feeds:
        pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6)
    else:
        pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6, rapid_feed_mm_min=1e9)
    return lift_workspace(cfg.replace(planner=pc))


def lift_workspace(cfg):
    """The [workspace] box (Cartesian soft limits) lifted: the bench's paths and placed corpus programs are
    compared under the strut limits alone (the smooth path's arc leaves the default box by 0.07 mm)."""
    big = np.array([1e6, 1e6, 1e6, 1e6, 1e6, 1e6])
    return cfg.replace(workspace_min=np.asarray(cfg.workspace_min) - big,
                       workspace_max=np.asarray(cfg.workspace_max) + big)


def feed_speed_limit(path, s: np.ndarray, half_cell) -> np.ndarray:
    """The planner's feed bound on the path speed (s-units/s) at ``s`` (mm): ``feed / |d tip/ds|``.

    ``|d tip/ds|`` is the planner's measure (tip xyz speed per s-unit; for rotary-only stretches the
    angular speed in deg), by the same central difference.  Every piece overlapping
    ``[s - half_cell, s + half_cell]`` (``half_cell`` a number or one per point) is taken (clamped into the piece), so a lower feed on a piece
    between two grid points is not missed.
    """
    from ..planner.verify import FD_STEP
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


def _bench_topp(cfg, gridpoints: int, blocks, label: str, programmed_feeds: bool = False,
                jerk_opt: bool = True) -> dict:
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
    from .jerkopt import jerk_optimum_report
    jopt = (jerk_optimum_report(plan, cfg, stops) if jerk_opt and not programmed_feeds else
            {"skipped": "programmed feeds: not computed" if programmed_feeds else "whole corpus file: see cam_excerpts"})
    tu_note = ("TOPP-RA's trajectory (constant path acceleration between its grid points) sampled at the cycle "
               f"period ({float(cfg.cycle.period_s) * 1e3:g} ms), strut lengths by exact inverse kinematics of "
               "the executed path, finite differences at the cycle period, peak |v|, |a|, |jerk| over the "
               "limits; hexacnc_utilisation is the same measurement of hexacnc's table")
    # the keys both comparisons report first, in this order
    head = {
        "path": label,
        "hexacnc_duration_s": round(plan.duration_s, 6),
        "toppra_duration_s": round(total, 6),
        "ratio": round(plan.duration_s / total, 6),
        "within_5_percent": bool(plan.duration_s <= 1.05 * total),
        "hexacnc_utilisation": {k: round(v, 6) for k, v in plan.utilisation.items()},
        "utilisation_ok": bool(max(plan.utilisation.values()) <= 1.0),
        "jerk_optimum_s": jopt.get("jerk_optimum_s"),
        "jerk_optimum_ratio": jopt.get("jerk_optimum_ratio"),
        "jerk_optimum_utilisation": jopt.get("utilisation"),
        "jerk_optimum": jopt,
    }
    if programmed_feeds:
        return {
            **head,
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
        **head,
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
    from ..planner.plan import ACC_SHARE, RHO_J, RHO_STEP
    from ..planner.profile import ETA
    from ..planner.spread import dilate_min as _dilate_min
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
