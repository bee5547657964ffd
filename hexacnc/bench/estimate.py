"""``hexacnc bench estimate``: the time-left estimate of streamed programs against their planned time.

A program is planned window by window as the daemon streams it (:func:`~hexacnc.planner.window.plan_windows`)
and counted as its validator counts it (:func:`~hexacnc.planner.window.validate_windows`); after every prefix
of planned windows the estimate the daemon gives (:func:`hexacnc.planner.timefit.unplanned_s`, what
``StreamPlan.unplanned_s`` calls) is compared with the whole program's planned seconds.  Two modes:

* validated (the default): the validator has counted the whole program before motion starts;
* ``start_before_validated``: a short first window, and the validator's counts so far where it is ``ahead``
  times as far into the program as the planner (1: never ahead; the estimate is then by lines).

Programs: the synthetic CAM raster (``hexacnc.bench.camgen``, 800 lines) at its feeds and at feeds 1000x
what the struts follow (as 3D_Chips.ngc's F4.5e6), and the corpus files where present.  Deterministic: no
timing is measured, so the figures do not depend on the machine's load.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

HELP = "time-left estimate of streamed programs against the planned time, after every prefix of windows"

#: corpus files measured where present
CORPUS_FILES = ("3D_Chips.ngc", "tort.ngc", "arcspiral.ngc")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--corpus", help="G-code corpus directory (default: <repo>/../shared/data/gcode)")
    parser.add_argument("--skip-corpus", action="store_true", help="only the synthetic rasters")
    parser.add_argument("--raster-window-blocks", type=int, default=60,
                        help="window_blocks for the 800-line rasters (default 60: 23 windows)")
    parser.add_argument("--ahead", default="1,2,4",
                        help="start_before_validated: the validator this many times as far as the planner")


def replay(windows, counts, total_lines: int, validated: bool, ahead: float = 1.0) -> list[float]:
    """Relative errors (estimate / planned - 1) after each prefix of ``windows`` but the last (after it the
    estimate is exact).  ``counts``: the validator's reports [(line, nominal s, blocks)], the last one the
    whole program; ``validated``: it has counted all before motion, else its report at or below ``ahead``
    times the planner's last line is used."""
    from ..planner.timefit import Counted, Planned, unplanned_s
    total_s = sum(float(w.plan.duration_s) for w in windows)
    line, nominal, blocks = counts[-1]
    whole = Counted(int(line), float(nominal), int(blocks), True)
    planned, errs = Planned(), []
    for w in windows[:-1]:
        planned.add(w)
        counted = whole
        if not validated:
            seen = [c for c in counts[:-1] if c[0] <= ahead * planned.last_line]
            counted = Counted(int(seen[-1][0]), float(seen[-1][1]), int(seen[-1][2]), False) if seen else None
        errs.append((planned.seconds + unplanned_s(planned, total_lines, counted)) / total_s - 1.0)
    return errs


def planned_windows(prog, cfg, first_blocks: int = 0) -> list:
    """The program's windows as the daemon plans them from home (``first_blocks``: start_before_validated)."""
    from ..pose import pose_to_rad
    from ..planner.window import plan_windows, tool_tip_pose_deg
    start = tool_tip_pose_deg(cfg, pose_to_rad(cfg.home_pose))
    return list(plan_windows(prog.blocks, cfg, start_pose=start, first_blocks=first_blocks))


def validator_counts(prog, cfg) -> list:
    """The validator's reports [(line, nominal s, blocks)] from home, the last one the whole program."""
    from ..pose import pose_to_rad
    from ..planner.window import validate_windows
    home = pose_to_rad(cfg.home_pose)
    return [(line, est, nb) for nb, est, line, _end in validate_windows(prog.blocks, cfg, start_rad=home)]


def measure(text: str, name: str, cfg, window_blocks: int | None, aheads) -> dict:
    """Figures of one program: planned seconds, windows, and the errors of both modes."""
    from ..gcode import program_from_config
    from ..planner.window import FIRST_WINDOW_BLOCKS
    if window_blocks is not None:
        cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, window_blocks=int(window_blocks)))
    prog = program_from_config(text, name, cfg)
    total_lines = text.count("\n") + 1
    counts = validator_counts(prog, cfg)
    ws = planned_windows(prog, cfg)
    out = {"planned_s": round(sum(w.plan.duration_s for w in ws), 3), "nominal_s": round(counts[-1][1], 3),
           "blocks": int(counts[-1][2]), "windows": len(ws), "validated": _summary(replay(ws, counts, total_lines,
                                                                                            True))}
    ws = planned_windows(prog, cfg, FIRST_WINDOW_BLOCKS)
    out["before_validated"] = {f"ahead_{a:g}x": _summary(replay(ws, counts, total_lines, False, a)) for a in aheads}
    return out


def _summary(errs: list[float]) -> dict:
    """After the first window, the worst from the second on and from the half on (percent, signed)."""
    if not errs:
        return {"single_window": True}
    worst = lambda e: round(100 * max(e, key=abs), 1) if e else None   # noqa: E731
    return {"after_first_pct": round(100 * errs[0], 1), "worst_from_second_pct": worst(errs[1:]),
            "worst_from_half_pct": worst(errs[len(errs) // 2:])}


def main(args: argparse.Namespace) -> int:
    from ..config import load_config
    from .camgen import cam_program
    cfg = load_config(args.config)
    aheads = [float(a) for a in str(args.ahead).split(",") if a.strip()]
    raster = cam_program(800)
    fast = cam_program(800, feed_scale=1000)
    res = {"note": "estimate / planned - 1 after each prefix of planning windows (the last prefix is exact); "
                   "deterministic, no timing",
           "raster_800_fast_feeds": measure(fast, "raster_fast.ngc", cfg, args.raster_window_blocks, aheads),
           "raster_800": measure(raster, "raster.ngc", cfg, args.raster_window_blocks, aheads)}
    if not args.skip_corpus:
        corpus = Path(args.corpus) if args.corpus else Path(__file__).resolve().parents[2].parent / "shared/data/gcode"
        for name in CORPUS_FILES:
            f = corpus / name
            if not f.is_file():
                res[name] = {"skipped": f"no file {f}"}
                continue
            res[name] = measure(f.read_text(encoding="utf-8", errors="replace"), name, cfg, None, aheads)
    print(json.dumps(res, indent=1))
    return 0
