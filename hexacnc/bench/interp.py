"""``hexacnc bench interp``: interpreter throughput on the LinuxCNC corpus.

Prints one JSON object:

* ``files``: per corpus file the source line count, the outcome (``ok`` with
  the block count, or ``refused`` with the error's line, column and code), the
  best and the first (cold: empty line-shape cache) lines/s over ``--runs``
  runs, and the time per line in µs;
* ``derived``: ``impeller-7bl-xyzac.ngc`` with its two user M-code lines
  (M428/M429, which are refused) removed: the G93 five-axis body's throughput;
* ``target``: 50,000 lines/s on ``3D_Chips.ngc`` and whether it is met.

Lines/s = source lines / wall time of a whole ``parse_program`` call (reading
the file excluded), best of ``--runs`` (default 11) with the garbage collector
enabled as in use; the median and the best process CPU time are given too
(the machine may be shared).  ``os.getloadavg()`` is reported.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import sys
import time
from pathlib import Path

from ..errors import GcodeError
from ..gcode import expr, lexer, parse_program

HELP = "interpreter throughput (lines/s) on the G-code corpus, target 50,000 lines/s on 3D_Chips.ngc"

TARGET_FILE = "3D_Chips.ngc"
TARGET_LINES_PER_S = 50_000.0


def default_corpus() -> Path:
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "gcode"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--corpus", default=None, help="directory of .ngc files (default: ../shared/data/gcode)")
    parser.add_argument("--runs", type=int, default=11, help="runs per file; the best is reported")
    parser.add_argument("--linuxcnc", default=None, metavar="DIR",
                        help="a LinuxCNC source tree: compare with the canonical output of its tests/interp "
                             "programs instead (counts same / unsupported / refused / differ)")
    parser.add_argument("--stream-lines", type=int, default=0, metavar="N",
                        help="also stream a generated N-line CAM file through iter_blocks and report peak RSS")


def _measure(text: str, name: str, runs: int) -> dict:
    nlines = len(text.split("\n")) - (1 if text.endswith("\n") else 0)
    lexer._SHAPES.clear()
    expr._FN_CACHE.clear()
    times = []
    cpu = []
    outcome: dict = {}
    for _ in range(max(1, runs)):
        c0 = time.process_time()
        t0 = time.perf_counter()
        try:
            prog = parse_program(text, name)
            dt = time.perf_counter() - t0
            outcome = {"outcome": "ok", "blocks": len(prog.blocks),
                       "motion_blocks": sum(1 for b in prog.blocks if b.kind in ("rapid", "line", "arc")),
                       "end_reason": prog.end_reason, "lines_executed": prog.lines_executed}
        except GcodeError as exc:
            dt = time.perf_counter() - t0
            outcome = {"outcome": "refused", "error": {"line": exc.line, "column": exc.column, "code": exc.code,
                                                       "message": exc.bare_message}}
        times.append(dt)
        cpu.append(time.process_time() - c0)
    best = min(times)
    res = {"lines": nlines, **outcome, "runs": len(times)}
    if outcome.get("outcome") == "refused":
        res.update(lines_per_s=None, seconds_to_refusal=round(best, 6),
                   note="refused before any motion; the rest of the program is not interpreted")
    else:
        res.update(lines_per_s=round(nlines / best, 1), first_run_lines_per_s=round(nlines / times[0], 1),
                   median_lines_per_s=round(nlines / sorted(times)[len(times) // 2], 1),
                   cpu_lines_per_s=round(nlines / max(1e-9, min(cpu)), 1),
                   us_per_line=round(1e6 * best / max(1, nlines), 3))
    return res


def main(args: argparse.Namespace) -> int:
    if args.linuxcnc:
        from .interp_linuxcnc import run_all
        res = run_all(Path(args.linuxcnc))
        print(json.dumps(res, indent=2))
        return 0 if res["tests"] else 2
    corpus = Path(args.corpus) if args.corpus else default_corpus()
    files = sorted(corpus.glob("*.ngc")) if corpus.is_dir() else []
    if not files:
        print(json.dumps({"error": f"no .ngc files in {corpus}"}), file=sys.stdout)
        return 2
    out: dict = {"corpus": str(corpus), "python": platform.python_version(),
                 "load_average_1min": round(os.getloadavg()[0], 2), "files": {}, "derived": {}}
    for f in files:
        out["files"][f.name] = _measure(f.read_text(), f.name, args.runs)
    imp = corpus / "impeller-7bl-xyzac.ngc"
    if imp.exists():
        body = re.sub(r"(?im)^\s*M42[89]\b.*$", "", imp.read_text())
        out["derived"]["impeller-7bl-xyzac.ngc without M428/M429 lines"] = _measure(body, "impeller", args.runs)
    tf = out["files"].get(TARGET_FILE, {})
    got = tf.get("lines_per_s")
    out["target"] = {"file": TARGET_FILE, "lines_per_s": TARGET_LINES_PER_S, "measured": got,
                     "measured_cpu": tf.get("cpu_lines_per_s"),
                     "met": bool(got is not None and got >= TARGET_LINES_PER_S)}
    print(json.dumps(out, indent=2))
    return 0
