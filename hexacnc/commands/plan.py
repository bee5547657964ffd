"""``hexacnc plan program.ngc``: plan a program offline and report duration and limit utilisation."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..config import load_config
from ..errors import DataError, GcodeError, PlanError

HELP = ("plan a G-code program: duration, peak strut velocity/acceleration/jerk as a fraction of each limit, "
        "smallest joint-angle margin, or the first violation with line and limit")

#: exit codes
EXIT_OK = 0
EXIT_LIMIT = 1       #: the program breaks a machine limit (PlanError)
EXIT_PROGRAM = 2     #: the program cannot be read or interpreted


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("program", help="RS274NGC program file")
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--lines", action="store_true", help="include per-line timing (start_s, end_s)")


def _error(args, code: str, message: str, line, limit, rc: int) -> int:
    if args.json:
        print(json.dumps({"ok": False, "program": args.program,
                          "error": {"code": code, "message": message, "line": line, "limit": limit}}))
    else:
        where = f"line {line}: " if line is not None and not message.startswith("line ") else ""
        print(f"hexacnc plan: {args.program}: {where}{message}" + (f" [limit: {limit}]" if limit else ""),
              file=sys.stderr)
    return rc


def main(args: argparse.Namespace) -> int:
    from ..gcode.factory import program_from_config
    from ..planner import plan_program

    cfg = load_config(args.config)
    try:
        text = Path(args.program).read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{args.program}: cannot read program: {exc}") from exc
    try:
        prog = program_from_config(text, Path(args.program).name, cfg)
    except GcodeError as exc:
        return _error(args, exc.code, str(exc), exc.line, None, EXIT_PROGRAM)
    try:
        plan = plan_program(prog.blocks, cfg)
    except PlanError as exc:
        rc = EXIT_PROGRAM if exc.code in ("gcode", "empty") else EXIT_LIMIT
        return _error(args, exc.code, exc.bare_message, exc.line, exc.limit, rc)
    s = plan.summary()
    if not args.lines:
        s.pop("lines", None)
    s["program"] = args.program
    s["machine"] = cfg.name
    if args.json:
        print(json.dumps(s))
        return EXIT_OK
    u = s["utilisation"]
    print(f"{args.program}: {s['duration_s']:.3f} s on {cfg.name}")
    print(f"  peak strut velocity     {100 * u['velocity']:6.1f} % of limit")
    print(f"  peak strut acceleration {100 * u['acceleration']:6.1f} % of limit")
    print(f"  peak strut jerk         {100 * u['jerk']:6.1f} % of limit")
    print(f"  smallest joint-angle margin {s['min_joint_margin_deg']:.3f} deg, "
          f"strut-length margin {s['min_length_margin_mm']:.3f} mm")
    smoothed = f" ({s['smoothed']} smoothed)" if s.get("smoothed") else ""
    print(f"  {s['segments']} segments{smoothed}, {s['blends']} blends, {s['stops']} stops, "
          f"path {s['path_length']:.1f}, planned in {s['planning_s']:.2f} s")
    if s.get("feed_capped_moves"):
        print(f"  {s['feed_capped_moves']} moves ask more than the rapid feed (first at line "
              f"{s['feed_capped_first_line']}): they run at most at [planner] rapid_feed_mm_min = "
              f"{cfg.planner.rapid_feed_mm_min:g} mm/min")
    if args.lines:
        for ln, (a, b) in s["lines"].items():
            print(f"  line {ln}: {a:.4f} .. {b:.4f} s")
    return EXIT_OK
