"""``hexacnc bench stream``: programs of any length with memory bounded by the look-ahead (issue 19, item 3).

A long CAM-like program (``--source synthetic``: :mod:`.camgen` raster passes; ``3dchips``: the body of
../shared/data/gcode/3D_Chips.ngc repeated, bench placement) of ``--lines`` lines is written to a temporary
file, then, each in a fresh process (peak RSS = ``ru_maxrss`` of that process):

* ``validate``: the streamed whole-program validation the daemon runs before motion (interpreter +
  path + limit checks per window, :func:`hexacnc.planner.window.validate_windows`): seconds, peak RSS,
  rate = nominal program seconds / validation seconds (target >= 200);
* ``plan``: windowed planning of the whole program (:func:`hexacnc.planner.window.plan_windows`) with CAM
  smoothing on (``--smooth-mm``, 0: as configured): planned duration, CPU seconds, rate (target >= 100),
  peak RSS (target <= 500 MB), windows and forced stops, the largest window pickled (what the supervisor
  holds AHEAD_WINDOWS + 2 of);
* ``first_motion``: the daemon's :class:`~hexacnc.daemon.planstream.StreamPlan` with
  ``start_before_validated`` (warm forkserver): seconds from the program to its first planned window
  (target <= 1 s), and, in the default mode, seconds until motion may start (the validation); beside it
  the CPU seconds of that first window (``first_window_cpu_s``, in this process: what the wall time is
  on an idle machine).

Timings are CPU-load dependent (a shared machine): the JSON says the load average.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HELP = "streaming: validation and windowed planning of a long CAM program, peak RSS, rates, first motion"

TARGETS = {"peak_rss_mb": 500.0, "validation_rate": 200.0, "planning_rate": 100.0, "first_motion_s": 1.0}

_CHILD = r"""
import json, pickle, resource, sys, time, dataclasses
from hexacnc.bench.stream import bench_config, blocks_of
from hexacnc.kinematics import Hexapod
from hexacnc.planner.window import plan_windows, validate_windows
mode, path, config, smooth, source = sys.argv[1], sys.argv[2], sys.argv[3] or None, float(sys.argv[4]), sys.argv[5]
cfg = bench_config(config, smooth, source, path)
t0, c0 = time.perf_counter(), time.process_time()
out = {}
if mode == "validate":
    for nb, est, line, end in validate_windows(blocks_of(cfg, path), cfg):
        pass
    out.update(blocks=nb, nominal_s=est, last_line=line)
else:
    dur, n, forced, big, nb = 0.0, 0, 0, 0, 0
    for w in plan_windows(blocks_of(cfg, path), cfg, hexapod=Hexapod(cfg)):
        dur += w.plan.duration_s
        n += 1
        forced += w.forced_stop
        nb += w.blocks
        if n <= 3 or n % 50 == 0:
            big = max(big, len(pickle.dumps(w, protocol=pickle.HIGHEST_PROTOCOL)))
    out.update(blocks=nb, duration_s=dur, windows=n, forced_stops=forced, window_pickle_mb_max=big / 2**20)
out.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0,
           peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
print(json.dumps(out))
"""


def bench_config(config: str | None, smooth_mm: float, source: str, path: str):
    import dataclasses
    from ..config import load_config
    cfg = load_config(config)
    if smooth_mm > 0:
        cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, smooth_max_segment_mm=smooth_mm))
    if source == "3dchips":
        from .placement import _place
        from .toppra_peer import lift_workspace
        cfg = lift_workspace(cfg)
        head = Path(path).read_text(encoding="utf-8", errors="replace")[:200_000]
        head = head[:head.rfind("\n") + 1] or head         # whole lines (a cut line is a G-code error)
        _prog, wo = _place(head + "\nM2\n", "head.ngc", cfg)
        cfg = cfg.replace(planner=dataclasses.replace(cfg.planner, work_offset_mm=tuple(wo)))
    return cfg


def blocks_of(cfg, path: str):
    from ..gcode import iter_blocks
    from ..gcode.factory import machine_defaults
    return iter_blocks(path, Path(path).name, **machine_defaults(cfg))


def write_program(source: str, lines: int, corpus: Path, out: Path) -> dict:
    if source == "synthetic":
        from .camgen import write_cam_program
        write_cam_program(out, lines)
        return {"source": "synthetic CAM raster (hexacnc/bench/camgen.py)", "lines": lines}
    src = corpus / "3D_Chips.ngc"
    if not src.is_file():
        return {"skipped": f"no file {src}"}
    from .memory import repeated_program
    text, n1 = repeated_program(src, 1)
    reps = max(1, lines // max(n1, 1))
    body_text, n = repeated_program(src, reps)
    out.write_text(body_text, encoding="utf-8")
    return {"source": "3D_Chips.ngc body repeated (bench placement)", "lines": n, "repeats": reps}


def _run(mode: str, path: Path, args, source: str) -> dict:
    p = subprocess.run([sys.executable, "-c", _CHILD, mode, str(path), args.config or "", str(args.smooth_mm), source],
                       capture_output=True, text=True, timeout=args.timeout_s)
    if p.returncode != 0:
        return {"failed": (p.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(p.stdout.strip().splitlines()[-1])


def first_motion(path: Path, args, source: str) -> dict:
    """StreamPlan from the program text to its first window (start_before_validated) and to ready (default)."""
    import dataclasses
    from ..daemon.planproc import warm
    from ..daemon.planstream import StreamPlan
    from ..pose import pose_to_rad
    cfg = bench_config(args.config, args.smooth_mm, source, str(path))
    home = pose_to_rad(cfg.home_pose)
    text = path.read_text(encoding="utf-8")
    t0 = time.perf_counter()
    warm()
    sp = StreamPlan(cfg, "M2\n", "warm.ngc", home, cfg.cycle.period_s)   # the forkserver's imports done
    try:
        sp.wait_ready()
    finally:
        sp.cancel()
    out = {"forkserver_start_s": round(time.perf_counter() - t0, 3)}
    out.update(_first_window_cpu(cfg, text, path.name, home))
    for before in (True, False):
        c = cfg.replace(planner=dataclasses.replace(cfg.planner, start_before_validated=before))
        t0 = time.perf_counter()
        sp = StreamPlan(c, text, path.name, home, c.cycle.period_s)
        try:
            sp.wait_ready()
            key = "first_window_s" if before else "ready_after_validation_s"
            out[key] = round(time.perf_counter() - t0, 3)
        except Exception as exc:            # noqa: BLE001 - reported
            out["error" if before else "error_validated"] = str(exc)
        finally:
            sp.cancel()
    return out


def _first_window_cpu(cfg, text: str, name: str, home) -> dict:
    """CPU seconds of what the planning child does before its first window (interpreter stream, first window
    of FIRST_WINDOW_BLOCKS motion blocks), in this process with its modules loaded as the forkserver has them:
    the part of ``first_window_s`` that does not depend on the machine's load (on a loaded machine the wall
    time is this times the CPU share the child gets)."""
    from ..gcode.factory import machine_defaults
    from ..gcode.textstream import iter_text_blocks
    from ..kinematics import Hexapod
    from ..planner.window import FIRST_WINDOW_BLOCKS, plan_windows, tool_tip_pose_deg
    tip = tool_tip_pose_deg(cfg, home)
    kw = {**machine_defaults(cfg), "start_pose": tip}          # as the daemon's planning child streams it
    out = {"first_window_blocks_max": FIRST_WINDOW_BLOCKS}
    for key in ("first_window_cpu_cold_s", "first_window_cpu_s"):     # first call in a process, then again
        c0 = time.process_time()
        gen = plan_windows(iter_text_blocks(text, name, **kw), cfg, hexapod=Hexapod(cfg), start_pose=tip,
                           first_blocks=FIRST_WINDOW_BLOCKS)
        w = next(gen)
        out[key] = round(time.process_time() - c0, 3)
        gen.close()
    out["first_window_motion_s"] = round(w.plan.duration_s, 3)
    return out


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--lines", type=int, default=1_000_000, help="program lines (default 1e6)")
    parser.add_argument("--source", choices=("synthetic", "3dchips"), default="synthetic")
    parser.add_argument("--corpus", default=None, help="G-code corpus (default: <repo>/../shared/data/gcode)")
    parser.add_argument("--smooth-mm", type=float, default=2.0,
                        help="[planner] smooth_max_segment_mm for the run (CAM smoothing on; 0: as configured)")
    parser.add_argument("--skip-plan", action="store_true", help="validation and first motion only")
    parser.add_argument("--timeout-s", type=float, default=3600.0)


def main(args) -> int:
    corpus = Path(args.corpus) if args.corpus else Path(__file__).resolve().parents[2].parent / "shared/data/gcode"
    res: dict = {"load_average": list(os.getloadavg()), "cpus": os.cpu_count(), "targets": TARGETS,
                 "smooth_max_segment_mm": args.smooth_mm}
    with tempfile.TemporaryDirectory(prefix="hexacnc-stream-") as d:
        path = Path(d) / "long.ngc"
        res["program"] = write_program(args.source, args.lines, corpus, path)
        if "skipped" in res["program"]:
            print(json.dumps(res, indent=1))
            return 0
        res["program"]["bytes"] = path.stat().st_size
        v = res["validate"] = _run("validate", path, args, args.source)
        if "nominal_s" in v:
            v["rate"] = round(v["nominal_s"] / max(v["wall_s"], 1e-9), 1)
        if not args.skip_plan:
            p = res["plan"] = _run("plan", path, args, args.source)
            if "duration_s" in p:
                p["rate_cpu"] = round(p["duration_s"] / max(p["cpu_s"], 1e-9), 1)
                p["rate_wall"] = round(p["duration_s"] / max(p["wall_s"], 1e-9), 1)
                if "nominal_s" in v:        # the validation's rate against the planned duration too
                    v["rate_planned"] = round(p["duration_s"] / max(v["wall_s"], 1e-9), 1)
        res["first_motion"] = first_motion(path, args, args.source)
    print(json.dumps(res, indent=1))
    return 0
