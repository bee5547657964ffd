"""``hexacnc bench homing``: CiA 402 homing (``[homing] method = "cia402"``, mode 6) of all six struts
against the simulated drives, per homing method: the time to reference them, and the reference's
accuracy and repeatability against the drives' true home position.

For each method (0x6098) the daemon (hot-loop process, simulated drives process, socket) is started,
and ``--repeats`` times: the machine is moved (a z jog of a different length each time, so every run
starts elsewhere), ``home`` is sent over the socket and timed (``time_s``: from the request to the
reply, all six struts referenced and back in cyclic synchronous position mode), and the simulated
drives report their physical state (:func:`hexacnc.daemon.simhost.write_truth`):

* 35 / 37 (the current position is home): the true home is where the strut stood (its raw encoder
  count when homing began); the position value there must be the home offset;
* 17 / 18 (negative / positive limit switch): the true home is the switch's releasing edge (the
  simulated switch is ideal: no hysteresis or noise; the drive latches it at its servo cycle).

``error_um`` per strut = position value - (home offset + raw count - raw count at the true home);
``accuracy_um`` is the largest |error| of a method, ``repeatability_um`` the largest spread
(max - min) of one strut's error over the runs.  Each run starts once the struts have settled (no
strut moving by 0.05 um in 50 ms).  Timings are wall clock (``loadavg`` printed: judge
them with it).  Prints one JSON object.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import tempfile
import time

import numpy as np

from ..config import load_config

HELP = "CiA 402 homing of the six struts per method: time to reference, accuracy and repeatability " \
       "against the simulated drives' true home"
METHODS = (35, 37, 17, 18)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--methods", default=",".join(str(m) for m in METHODS),
                        help="homing methods 0x6098 to run, comma-separated (the simulated drives do 35 37 17 18)")
    parser.add_argument("--repeats", type=int, default=3, help="homing runs per method")
    parser.add_argument("--speed-search", type=float, default=10.0, help="[homing] speed_search_mm_s")
    parser.add_argument("--speed-zero", type=float, default=2.0, help="[homing] speed_zero_mm_s")
    parser.add_argument("--no-realtime", action="store_true", help="no SCHED_FIFO/mlockall for the hot loop")


def _machine(base, method: int, args, state_dir: str):
    from drivers.simhoming import SWITCH_FROM_START_MM
    from ..kinematics import Hexapod
    from ..config.operator import HomingConfig
    start = Hexapod(base).lengths(base.home_pose) - np.asarray(base.strut_offset_mm, dtype=float)
    # the offsets keep the position values on the raw scale (the power-up values), so a wrong home
    # shows as a difference there
    shift = {17: -SWITCH_FROM_START_MM, 18: SWITCH_FROM_START_MM}.get(method, 0.0)
    hm = HomingConfig(method="cia402", required=False, homing_method=method, speed_search_mm_s=args.speed_search,
                      speed_zero_mm_s=args.speed_zero, acceleration_mm_s2=100.0, offset_mm=start + shift)
    cycle = dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0)
    return base.replace(cycle=cycle, operator=dataclasses.replace(base.operator, homing=hm, state_dir=state_dir))


def _true_home_raw_mm(method: int, node: dict, before: dict) -> float:
    if method in (17, 18):
        return float(node["switch_mm"][0 if method == 17 else 1])
    return float(before["raw_mm"])          # 35 / 37: where it stood


def _settled(daemon, path: str, timeout_s: float = 3.0) -> dict:
    """The drives' state once no strut moves by more than 0.05 um in 50 ms (after a jog the struts
    settle behind their commands)."""
    last = daemon.sim.truth(path)
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        time.sleep(0.05)
        now = daemon.sim.truth(path)
        if max(abs(now[n]["raw_mm"] - last[n]["raw_mm"]) for n in now) < 5e-5:
            return now
        last = now
    return last


def _run_method(cfg, method: int, args, tmp: str) -> dict:
    from ..daemon import core
    from ..daemon import protocol as P
    from ..daemon.server import SocketServer
    offsets = np.asarray(cfg.operator.homing.offset_mm, dtype=float)
    runs, errors = [], []
    daemon = core.Daemon(cfg, realtime=not args.no_realtime)
    srv = SocketServer(daemon, cfg, os.path.join(tmp, f"h{method}.sock")).start()
    truth_path = os.path.join(tmp, "truth.json")
    try:
        with P.Client.unix(srv.socket_path) as c:
            for k in range(args.repeats):
                if k:
                    c.call("jog", axis="z", distance=(0.3 + 0.2 * k) * (-1) ** k, reply_timeout_s=30.0)
                    c.call("wait", timeout_s=30.0)
                before = _settled(daemon, truth_path)
                t0 = time.monotonic()
                c.call("home", reply_timeout_s=120.0)
                t_home = time.monotonic() - t0
                after = daemon.sim.truth(truth_path)
                err = []
                for i in range(6):
                    nd = after[i + 1]
                    home_raw = _true_home_raw_mm(method, nd, before[i + 1])
                    err.append(1e3 * (nd["position_mm"] - (offsets[i] + nd["raw_mm"] - home_raw)))
                errors.append(err)
                runs.append({"time_s": round(t_home, 3), "error_um": [round(e, 3) for e in err],
                             "referenced_drives": sum(bool(after[n]["referenced"]) for n in after)})
    finally:
        srv.close()
        daemon.close()
    E = np.asarray(errors)
    times = [r["time_s"] for r in runs]
    return {"runs": runs, "time_s": {"median": float(np.median(times)), "max": max(times)},
            "accuracy_um": round(float(np.max(np.abs(E))), 3),
            "repeatability_um": round(float(np.max(np.ptp(E, axis=0))), 3),
            "resolution_um": round(1e3 / cfg.bus.increments_per_mm, 3)}


def main(args: argparse.Namespace) -> int:
    try:
        methods = [int(m) for m in str(args.methods).split(",") if m.strip()]
    except ValueError:
        print(f"hexacnc bench homing: --methods {args.methods!r}: comma-separated integers expected")
        return 2
    bad = [m for m in methods if m not in METHODS]
    if bad or args.repeats < 1:
        print(f"hexacnc bench homing: methods {bad} not simulated (one of {METHODS}) or --repeats < 1")
        return 2
    base = load_config(args.config)
    tmp = tempfile.mkdtemp(prefix="hxbhm", dir="/tmp")
    out: dict = {"speed_search_mm_s": args.speed_search, "speed_zero_mm_s": args.speed_zero,
                 "repeats": args.repeats, "loadavg_before": os.getloadavg(), "methods": {}}
    try:
        for m in methods:
            out["methods"][str(m)] = _run_method(_machine(base, m, args, tmp), m, args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["loadavg_after"] = os.getloadavg()
    print(json.dumps(out, indent=2))
    return 0
