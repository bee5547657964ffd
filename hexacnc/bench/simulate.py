"""``hexacnc bench simulate``: simulator speed.

Prints one JSON object:

* ``thermal``: the seeded 2.5 h scenario (10 Hz observer, 40-segment truth,
  drift through the cycle transform every 10 s): wall and process CPU time,
  target < 60 s, the drift figures it produced;
* ``dynamics``: the coupled strut/carrier model along a ``--lines`` (1000)
  line synthetic program sampled at the cycle period: machine time, wall time
  of the simulation (trajectory generation reported apart), real-time ratio
  (target > 1);
* ``loadavg``: ``os.getloadavg()`` before and after (the machine may be shared).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from ..config import load_config

HELP = "simulator speed: 2.5 h thermal scenario (< 60 s), dynamics along a 1000-line program (real-time ratio)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--lines", type=int, default=1000, help="program lines for the dynamics run")
    parser.add_argument("--hours", type=float, default=2.5, help="thermal machine time")
    parser.add_argument("--source", choices=("auto", "planner", "exact-stop"), default="auto",
                        help="strut commands from the look-ahead planner (auto: if available) or exact-stop")


def main(args: argparse.Namespace) -> int:
    from ..sim import thermal
    from ..sim.dynamics import simulate_path
    from ..sim.program import program_trajectory, synthetic_program
    from ..sim.report import worst_and_gains

    cfg = load_config(args.config)
    load0 = os.getloadavg()
    w0, c0 = time.perf_counter(), time.process_time()
    res = thermal.run(cfg, thermal.ThermalScenario(duration_s=args.hours * 3600.0, trajectory_source=args.source))
    w1, c1 = time.perf_counter(), time.process_time()
    th = {"machine_time_h": args.hours, "wall_time_s": w1 - w0, "cpu_time_s": c1 - c0,
          "target_wall_s": 60.0, "target_met": (w1 - w0) < 60.0,
          "observer_updates": int(round(args.hours * 3600 * 10)), "speed_source": res["speed_source"],
          "peak_drift_z_um": res["peak_drift_z_um"], "reduction_pct": res["reduction_pct"],
          "heat_per_speed_W_s_mm": res["heat_per_speed_W_s_mm"]}

    model, _, worst, gains, _ = worst_and_gains(cfg, 3)
    t0 = time.perf_counter()
    tr, desc = program_trajectory(cfg, synthetic_program(cfg, args.lines), cfg.cycle.period_s, args.source)
    t1, c1 = time.perf_counter(), time.process_time()
    path = simulate_path(model, gains, tr.poses, tr.dt_s, tr.line)
    t2, c2 = time.perf_counter(), time.process_time()
    dy = {"lines": args.lines, "source": desc, "machine_time_s": tr.duration_s, "samples": len(tr.t_s),
          "dt_s": tr.dt_s, "trajectory_wall_s": t1 - t0, "simulation_wall_s": t2 - t1,
          "simulation_cpu_s": c2 - c1, "realtime_ratio": tr.duration_s / (t2 - t1),
          "realtime_ratio_incl_trajectory": tr.duration_s / (t2 - t0), "target_ratio": 1.0,
          "target_met": tr.duration_s / (t2 - t1) > 1.0,
          "path_error_max_um": path["path_error_um"]["max"],
          "following_error_max_um": max(path["following_error_um"]["max_per_strut"])}
    json.dump({"thermal": th, "dynamics": dy, "loadavg": {"before": load0, "after": os.getloadavg()},
               "cpus": os.cpu_count()}, sys.stdout, indent=1)
    print()
    return 0
