"""``hexacnc bench plan``: planner quality against TOPP-RA, and planning speed against execution time.

(a) ``topp``: a five-axis test path (lines with A/B/C, helical arcs, G64 blends) is planned by
    hexacnc; the same path (our strut lengths L(s) along the executed, blended path, as a cubic
    spline per stop-to-stop section) is time-parameterised by TOPP-RA (``toppra``) under the same
    strut velocity and acceleration limits.  Feed and angular-velocity limits are lifted for both
    so that only the strut limits bind.  hexacnc also honours the jerk limit and stands still for
    the smoothing window at every stop; TOPP-RA does not (its profile has unbounded jerk).
    Reported: both durations, their ratio, hexacnc's measured peak utilisation.
(b) ``corpus``: every program of the G-code corpus is interpreted and placed in the workspace
    with a work offset chosen by the bench (G54 origin such that the centre of the program's
    bounding box lands on the tool tip at the home pose; no scaling), then planned.  Reported per
    file: planning time, planned duration, their ratio, or the reason it was refused.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
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


def topp_path_blocks(cfg):
    """A five-axis path in the default workspace: lines with rotations, helical arcs, one exact stop."""
    from ..gcode.blocks import Block
    home = np.asarray(cfg.home_pose, dtype=float)
    offs = [[0, 0, 0, 0, 0, 0], [100, 0, 0, 0, 0, 0], [100, 100, -30, 8, 0, 0], [-100, 100, -30, 8, -6, 10],
            [-100, -100, 20, -5, -6, 10], [60, -100, 20, -5, 5, -10], [60, 40, -60, 0, 5, -10],
            [-40, 40, 0, 0, 0, 0], [-40, -40, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]]
    tips = [_tip(cfg, home + np.asarray(o, dtype=float)) for o in offs]
    F = 1e6     # feed far above what the struts allow: only strut limits bind
    blocks = []
    line = 1
    for i in range(len(tips) - 1):
        a, b = tips[i], tips[i + 1]
        if i == 6:
            # a helical arc in XY around the midpoint (half turn plus the Z change)
            ctr = 0.5 * (a[:3] + b[:3])
            ctr[2] = a[2]
            blocks.append(Block("arc", line, a, b, feed_mm_s=F, center=ctr, normal=np.array([0, 0, 1.0]),
                                blend_tolerance_mm=0.5))
        else:
            blocks.append(Block("line", line, a, b, feed_mm_s=F, blend_tolerance_mm=0.5, exact_stop=(i == 3)))
        line += 1
    return blocks


def smooth_path_blocks(cfg):
    """A gentler five-axis path: long moves meeting at shallow angles (< 20 deg), large helical arcs."""
    from ..gcode.blocks import Block
    home = np.asarray(cfg.home_pose, dtype=float)
    offs = [[-120, -60, 0, 0, 0, 0], [0, -80, 10, 4, 0, 5], [120, -60, 20, 8, 3, 10], [130, 60, 20, 8, 3, 10],
            [20, 110, 0, 2, -3, 0], [-100, 100, -20, -4, -6, -8]]
    tips = [_tip(cfg, home + np.asarray(o, dtype=float)) for o in offs]
    F = 1e6
    blocks = [Block("line", i + 1, tips[i], tips[i + 1], feed_mm_s=F, blend_tolerance_mm=0.5)
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
    blocks.append(Block("arc", len(blocks) + 1, a, b2, feed_mm_s=F, center=ctr, normal=np.array([0, 0, 1.0]),
                        blend_tolerance_mm=0.5))
    return blocks


def bench_topp(cfg, gridpoints: int, corpus: Path | None = None,
               corpus_files=("tort.ngc", "arcspiral.ngc", "3D_Chips.ngc")) -> dict:
    out = {"corners": _bench_topp(cfg, gridpoints, topp_path_blocks(cfg),
                                  "9 moves (lines with A/B/C, helical arc), right-angle corners, G64 P0.5, "
                                  "one exact stop"),
           "smooth": _bench_topp(cfg, gridpoints, smooth_path_blocks(cfg),
                                 "6 moves with A/B/C meeting at shallow angles, large helical arc, G64 P0.5")}
    if corpus is not None:
        out["corpus"] = bench_topp_corpus(cfg, gridpoints, corpus, corpus_files)
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


def bench_topp_corpus(cfg, gridpoints: int, corpus: Path, files) -> dict:
    """TOPP-RA against hexacnc on corpus programs (bench placement, feeds lifted, dwells zeroed)."""
    res = {"placement": "G54 origin = home tool-tip position minus the program's bounding-box centre; no scaling",
           "feeds": "lifted for both (only strut velocity/acceleration bind; hexacnc also its jerk limit); "
                    "dwell times zeroed (the stops remain)"}
    for name in files:
        f = corpus / name
        if not f.is_file():
            res[name] = {"skipped": f"no file {f}"}
            continue
        try:
            prog, wo = _place(f.read_text(encoding="utf-8", errors="replace"), name, cfg)
            r = _bench_topp(cfg, gridpoints, _lift_feeds(prog.blocks), f"{name} (corpus)")
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


def _bench_topp(cfg, gridpoints: int, blocks, label: str) -> dict:
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint
    from ..planner import path as P
    from ..planner import plan_program

    pc = dataclasses.replace(cfg.planner, max_angular_velocity_deg_s=1e6, rapid_feed_mm_min=1e9)
    cfg = cfg.replace(planner=pc)
    t0 = time.perf_counter()
    plan = plan_program(blocks, cfg)
    t_plan = time.perf_counter() - t0
    hx = plan.hexapod
    path = plan.path
    # sections between stops, on the executed (blended) path
    # (every point where hexacnc's plan is at rest: programmed stops and stopping events alike)
    rest = {float(v) for v in np.asarray(plan.grid_s)[np.asarray(plan.grid_x) <= 0.0]}
    stops = sorted({0.0, path.total} | {float(path.s0[m] + path.slen[m]) for m in path.stops_after} | rest)
    vl = np.stack([-cfg.max_velocity_mm_s, cfg.max_velocity_mm_s], axis=1)
    al = np.stack([-cfg.max_acceleration_mm_s2, cfg.max_acceleration_mm_s2], axis=1)
    total = 0.0
    sections = []
    t1 = time.perf_counter()
    for a, b in zip(stops[:-1], stops[1:]):
        if b - a < 1e-9:
            continue
        # dense samples of L(s) on the section (2 samples per 0.05 mm at least)
        n = max(200, int((b - a) / 0.05))
        s = np.linspace(a, b, n + 1)
        s_in = s.copy()
        s_in[-1] = b - 1e-9
        s_in[0] = a + 1e-9
        X = path.platform(path.piece_at(s_in), s_in)
        L = P.strut_lengths(X, hx.plat, hx.base)
        # path parameter scaled to [0, 1]: TOPP-RA's LP tolerances fail on fine grids in mm (uncontrollable)
        spl = ta.SplineInterpolator((s - a) / (b - a), L)
        ng = int(min(TOPPRA_MAX_GRID, max(gridpoints, (b - a) / TOPPRA_STEP)))
        inst = algo.TOPPRA([constraint.JointVelocityConstraint(vl), constraint.JointAccelerationConstraint(al)],
                           spl, gridpoints=np.linspace(0.0, 1.0, ng + 1),
                           parametrizer="ParametrizeConstAccel")
        traj = inst.compute_trajectory(0, 0)
        if traj is None:
            raise HexacncError(f"TOPP-RA found no parameterisation of section [{a:.3f}, {b:.3f}]")
        sections.append({"s_from": round(a, 4), "s_to": round(b, 4), "toppra_s": round(float(traj.duration), 6)})
        total += float(traj.duration)
    t_topp = time.perf_counter() - t1
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
        "sections": sections,
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
    }


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
