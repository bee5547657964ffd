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
    With ``--optimum-only`` every path also gets ``time_loss`` (:mod:`hexacnc.bench.planloss`): the planner's
    stages re-run on it (TOPP at its speed limits, after spreading, the raw profile, the filtered table) and
    the rows' use of the limits, so that the gap to the optimum splits into its causes.
(b) ``corpus``: every program of the G-code corpus is interpreted and placed in the workspace
    with a work offset chosen by the bench (G54 origin such that the centre of the program's
    bounding box lands on the tool tip at the home pose; no scaling), then planned.  Reported per
    file: planning time, planned duration, their ratio, or the reason it was refused.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from ..config import load_config
from ..errors import HexacncError
from .placement import PLACEMENT_NOTE, _place

#: what to install for the peers (the ``bench`` extra; never runtime dependencies)
TOPPRA_INSTALL = "the TOPP-RA comparison needs toppra: pip install toppra, or pip install 'hexacnc[bench]'"


def have_toppra() -> bool:
    try:
        import toppra  # noqa: F401
    except ImportError:
        return False
    return True

HELP = "planner benchmark: duration vs TOPP-RA (same path, same strut limits) and planning speed on the corpus"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--corpus", default=None,
                        help="G-code corpus directory (default: <repo>/../shared/data/gcode)")
    parser.add_argument("--skip-corpus", action="store_true", help="only the TOPP-RA comparison")
    parser.add_argument("--skip-topp", action="store_true", help="only the corpus timing")
    parser.add_argument("--gridpoints", type=int, default=2000, help="TOPP-RA grid points per section (at least)")
    parser.add_argument("--optimum-only", action="store_true",
                        help="only hexacnc against the jerk-limited optimum (bench paths and CAM excerpts; no "
                             "TOPP-RA); combine with --skip-corpus --skip-memory for that figure alone")
    parser.add_argument("--optimum-at-shares", action="store_true",
                        help="with --optimum-only: also the optimum under the planner's own shares of the limits "
                             "(v 0.995, a/j 0.95): the gap split into the shares' part and the method's part")
    parser.add_argument("--optimum-by-terms", action="store_true",
                        help="with --optimum-only: also the optimum with each strut's jerk terms bounded one by one "
                             "(|L3| v^3 + 3 |L2| v |a| + |L1| |j| <= J, L1-L3 the strut length's path derivatives): "
                             "the best a planner that does not let them cancel can reach; with --optimum-at-shares "
                             "also both at once (by_terms_at_shares_floor)")
    parser.add_argument("--paths", default="",
                        help="with --optimum-only: only these paths (comma-separated: corners, smooth, stops, "
                             "arcspiral, tort, 3D_Chips)")
    parser.add_argument("--retime", action="store_true",
                        help="plan with the final time scaling on (hexacnc.planner.plan.RETIME; off by default)")
    parser.add_argument("--skip-memory", action="store_true",
                        help="no peak-RSS measurement of planning a repeated 3D_Chips program")
    parser.add_argument("--skip-excerpts", action="store_true",
                        help="no CAM excerpts (arcspiral 1-200, tort 25-45, 3D_Chips 1-120) against the optimum")
    parser.add_argument("--topp-files", default="tort.ngc,arcspiral.ngc,3D_Chips.ngc",
                        help="corpus programs also compared with TOPP-RA (comma-separated; empty: none)")


def bench_corpus(cfg, corpus: Path) -> dict:
    from ..planner import plan_program
    from .toppra_peer import lift_workspace
    cfg = lift_workspace(cfg)
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
            "placement": PLACEMENT_NOTE}


def _optimum_summary(topp: dict) -> dict:
    """Per bench path the ratio hexacnc / jerk-limited optimum, the worst, and the 8 % target."""
    rows = {k: topp[k] for k in ("corners", "smooth", "stops") if isinstance(topp.get(k), dict)}
    rows.update({k: v for k, v in topp.get("cam_excerpts", {}).items() if isinstance(v, dict)})
    ratios = {k: v.get("jerk_optimum_ratio") for k, v in rows.items() if v.get("jerk_optimum_ratio")}
    util = {k: v["jerk_optimum"].get("utilisation") for k, v in rows.items()
            if isinstance(v.get("jerk_optimum"), dict) and v["jerk_optimum"].get("utilisation")}
    worst = max(ratios.values()) if ratios else None
    at_shares = {k: v.get("jerk_optimum_at_shares_ratio") for k, v in rows.items() if v.get("jerk_optimum_at_shares_ratio")}
    by_terms = {k: v.get("jerk_optimum_by_terms_ratio") for k, v in rows.items() if v.get("jerk_optimum_by_terms_ratio")}
    both = {k: v.get("jerk_optimum_by_terms_at_shares_ratio") for k, v in rows.items()
            if v.get("jerk_optimum_by_terms_at_shares_ratio")}
    floor = {k: v.get("by_terms_at_shares_cost") for k, v in rows.items() if v.get("by_terms_at_shares_cost")}
    return {"ratios": ratios, "worst_ratio": worst, "target_ratio": 1.08,
            **({"ratios_at_shares": at_shares} if at_shares else {}),
            **({"ratios_by_terms": by_terms} if by_terms else {}),
            **({"ratios_by_terms_at_shares": both, "by_terms_at_shares_floor": floor} if both else {}),
            "within_target": bool(worst is not None and worst <= 1.08),
            "hexacnc_utilisation_ok": all(bool(v.get("utilisation_ok")) for v in rows.values() if "utilisation_ok" in v),
            "optimum_utilisation": util}


def main(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    res: dict = {"bench": "plan", "machine": cfg.name, "cpu_count": os.cpu_count()}
    if args.retime:
        from ..planner import plan as planner_plan
        planner_plan.RETIME = True
    res["retime"] = bool(args.retime)
    corpus = Path(args.corpus) if args.corpus else Path(__file__).resolve().parents[3] / "shared/data/gcode"
    if args.optimum_only:
        from .excerpts import bench_optimum_only
        only = {p.strip() for p in args.paths.split(",") if p.strip()}
        res["optimum"] = bench_optimum_only(cfg, corpus if corpus.is_dir() else None,
                                            at_shares=args.optimum_at_shares, only=only or None,
                                            by_terms=args.optimum_by_terms)
        res["optimum"]["jerk_optimum_summary"] = _optimum_summary(
            {**{k: res["optimum"].get(k) for k in ("corners", "smooth", "stops")},
             "cam_excerpts": {k: v for k, v in res["optimum"].items() if " lines " in k}})
        args.skip_topp = True
    if not args.skip_topp and not have_toppra():
        print(f"hexacnc bench plan: {TOPPRA_INSTALL} (skipping the peer comparisons; --skip-topp hides this)",
              file=sys.stderr)
        res["topp"] = {"skipped": TOPPRA_INSTALL}
    elif not args.skip_topp:
        from .excerpts import bench_excerpts
        from .jerkopt import INSTALL, have_casadi
        from .toppra_peer import bench_topp
        if not have_casadi():
            print(f"hexacnc bench plan: {INSTALL} (jerk_optimum skipped)", file=sys.stderr)
        files = [f for f in (args.topp_files or "").split(",") if f.strip()]
        res["topp"] = bench_topp(cfg, args.gridpoints, corpus if (files and corpus.is_dir()) else None,
                                 tuple(f.strip() for f in files))
        if corpus.is_dir() and not args.skip_excerpts:
            res["topp"]["cam_excerpts"] = bench_excerpts(cfg, args.gridpoints, corpus)
        res["topp"]["jerk_optimum_summary"] = _optimum_summary(res["topp"])
    if not args.skip_memory and corpus.is_dir():
        from .memory import bench_memory
        res["memory"] = bench_memory(corpus, args.config)
    if not args.skip_corpus:
        if corpus.is_dir():
            res["corpus"] = bench_corpus(cfg, corpus)
        else:
            res["corpus"] = {"skipped": f"no corpus at {corpus}"}
    print(json.dumps(res))
    return 0
