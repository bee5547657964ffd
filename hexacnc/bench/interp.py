"""``hexacnc bench interp``: interpreter throughput on the LinuxCNC corpus.

Prints one JSON object:

* ``files``: per corpus file the source line count, the outcome (``ok`` with
  the block count, or ``refused`` with the error's line, column and code), the
  best and the first (cold: empty line-shape cache) lines/s over ``--runs``
  runs, and the time per line in µs;
* ``derived``: ``impeller-7bl-xyzac.ngc`` with its two user M-code lines
  (M428/M429, which are refused) removed: the G93 five-axis body's throughput;
* ``target``: 150,000 lines/s on ``3D_Chips.ngc`` and whether it is met;
* ``stream`` (``--stream-lines N``): an N-line generated CAM file interpreted
  in a fresh child process per run (``--stream-runs``, default 3) by each mode:
  ``stream`` (``iter_blocks`` on the file), ``stream_text`` (``iter_text_blocks``
  on the text in memory, as the daemon streams a program) and, when
  N <= 200,000, ``parse_program`` (reading the file excluded); per mode the best
  and median lines/s of process CPU time (both threads of a stream; the fairer
  figure on a shared machine) and of wall time, and the largest peak RSS (the
  child's own high-water mark, VmHWM); ``stream_vs_parse_cpu`` is the ratio of
  the median CPU rates;
* ``--linuxcnc DIR`` prints instead the comparison with LinuxCNC's canonical
  output (:mod:`hexacnc.bench.interp_linuxcnc`).

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

HELP = ("interpreter throughput (lines/s) on the G-code corpus, target 150,000 lines/s on 3D_Chips.ngc; "
        "--linuxcnc DIR: comparison with LinuxCNC's canonical output; --stream-lines N: streaming peak RSS")

TARGET_FILE = "3D_Chips.ngc"
TARGET_LINES_PER_S = 150_000.0


def default_corpus() -> Path:
    here = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "gcode"
    return here if here.is_dir() else Path("/work/shared/data/gcode")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--corpus", default=None, help="directory of .ngc files (default: ../shared/data/gcode)")
    parser.add_argument("--runs", type=int, default=11, help="runs per file; the best is reported")
    parser.add_argument("--linuxcnc", default=None, metavar="DIR",
                        help="a LinuxCNC source tree: compare with the canonical output of its tests/interp "
                             "programs instead (counts same / unsupported / refused / differ)")
    parser.add_argument("--stream-lines", type=int, default=0, metavar="N",
                        help="also stream a generated N-line CAM file (iter_blocks, iter_text_blocks) and report "
                             "CPU lines/s and peak RSS")
    parser.add_argument("--stream-runs", type=int, default=3, metavar="K",
                        help="child processes per streaming mode (best and median reported)")


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


_STREAM_CHILD = """
import json, resource, sys, time
from hexacnc.gcode import iter_blocks, parse_program
from hexacnc.gcode.textstream import iter_text_blocks

def peak_kb():
    # this process's own high-water mark (ru_maxrss keeps the parent's size at the fork across exec)
    try:
        with open("/proc/self/status") as f:
            for ln in f:
                if ln.startswith("VmHWM:"):
                    return int(ln.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

path, mode = sys.argv[1], sys.argv[2]
text = open(path).read() if mode != "stream" else None
base = peak_kb()
c0, t0 = time.process_time(), time.perf_counter()
if mode == "parse_program":
    p = parse_program(text, path)
    n, reason = len(p.blocks), p.end_reason
else:
    s = iter_blocks(path) if mode == "stream" else iter_text_blocks(text, path)
    n = sum(1 for _ in s)
    reason = s.program.end_reason
print(json.dumps({"blocks": n, "end_reason": reason, "cpu_s": time.process_time() - c0,
                  "wall_s": time.perf_counter() - t0, "base_kb": base,
                  "peak_kb": peak_kb()}))
"""

#: the modes of :func:`stream_rss`: streaming a file, streaming text in memory, the whole-program parse
STREAM_MODES = ("stream", "stream_text", "parse_program")
#: largest file also interpreted as a whole (its blocks are all held)
PARSE_PROGRAM_MAX_LINES = 200_000


def _cam_file(path: str, n: int) -> None:
    import random
    rnd = random.Random(1)
    with open(path, "w") as f:
        f.write("G21 G90 G64 P0.01\nG0 X0 Y0 Z5\nF1200\nG1 Z-1\n")
        for _ in range(n - 6):
            f.write(f"X{rnd.uniform(-50, 50):.4f} Y{rnd.uniform(-50, 50):.4f} Z{rnd.uniform(-2, 0):.4f}\n")
        f.write("G0 Z5\nM2\n")


def _child_run(path: str, mode: str) -> dict:
    """One interpretation of ``path`` in a fresh process (cold caches, as a daemon's planning child)."""
    import subprocess
    r = subprocess.run([sys.executable, "-c", _STREAM_CHILD, path, mode], capture_output=True, text=True,
                       timeout=3600)
    if r.returncode:
        return {"error": r.stderr.strip()[-500:]}
    return json.loads(r.stdout)


def _rates(n: int, runs: list[dict]) -> dict:
    """Best and median lines/s (CPU and wall) and the largest peak RSS of a mode's runs."""
    cpu = sorted(n / max(1e-9, r["cpu_s"]) for r in runs)
    wall = sorted(n / max(1e-9, r["wall_s"]) for r in runs)
    return {"blocks": runs[0]["blocks"], "end_reason": runs[0]["end_reason"], "runs": len(runs),
            "cpu_lines_per_s": round(cpu[-1]), "median_cpu_lines_per_s": round(cpu[len(cpu) // 2]),
            "lines_per_s": round(wall[-1]), "median_lines_per_s": round(wall[len(wall) // 2]),
            "seconds": round(min(r["wall_s"] for r in runs), 2),
            "rss_at_start_mb": round(max(r["base_kb"] for r in runs) / 1024, 1),
            "peak_rss_mb": round(max(r["peak_kb"] for r in runs) / 1024, 1)}


def stream_rss(n: int, runs: int = 3) -> dict:
    """Speed and peak RSS of an ``n``-line CAM file streamed (file and text) and, for
    n <= PARSE_PROGRAM_MAX_LINES, interpreted as a whole; ``runs`` child processes per mode, interleaved."""
    import tempfile
    out: dict = {"lines": n}
    modes = [m for m in STREAM_MODES if m != "parse_program" or n <= PARSE_PROGRAM_MAX_LINES]
    with tempfile.TemporaryDirectory(prefix="hxstream") as d:
        path = os.path.join(d, "cam.ngc")
        _cam_file(path, n)
        got: dict[str, list] = {m: [] for m in modes}
        for _ in range(max(1, runs)):
            for mode in modes:
                got[mode].append(_child_run(path, mode))
        for mode in modes:
            bad = [r["error"] for r in got[mode] if "error" in r]
            out[mode] = {"error": bad[0]} if bad else _rates(n, got[mode])
    parse = out.get("parse_program", {})
    for mode in ("stream", "stream_text"):
        if "median_cpu_lines_per_s" in out[mode] and "median_cpu_lines_per_s" in parse:
            out[mode]["stream_vs_parse_cpu"] = round(out[mode]["median_cpu_lines_per_s"]
                                                     / parse["median_cpu_lines_per_s"], 3)
    return out


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
    if args.stream_lines:
        out["stream"] = stream_rss(int(args.stream_lines), int(args.stream_runs))
    tf = out["files"].get(TARGET_FILE, {})
    got = tf.get("lines_per_s")
    out["target"] = {"file": TARGET_FILE, "lines_per_s": TARGET_LINES_PER_S, "measured": got,
                     "measured_cpu": tf.get("cpu_lines_per_s"),
                     "met": bool(got is not None and got >= TARGET_LINES_PER_S)}
    print(json.dumps(out, indent=2))
    return 0
