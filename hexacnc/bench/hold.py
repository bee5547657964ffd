"""``hexacnc bench hold``: how fast a feed hold (pause) and a stop take effect on a running program.

The daemon (hot-loop process, simulated drives) runs a program of long straight lines at each
``--speeds`` feed; at mid-line a client sends ``pause`` (then ``resume``) and, on a later pass,
``stop``, over the socket like any user.  Measured from the command's reply (its status carries
the commanded pose at that moment) until the commanded pose stands still:

* ``travel_mm``: distance the tool still travels;
* ``time_to_rest_s``: time until the commanded pose stops changing (polled every 2 ms, so the
  figure is late by up to the poll interval);
* ``queue_only_mm``: the distance the queued rows alone would have taken at that speed before the
  supervisor took them back (``[daemon] feed_ahead_s`` x speed) - what a pause cost before the rewind.

Prints one JSON object; ``loadavg`` says how busy the machine was.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time

import numpy as np

from ..config import load_config

HELP = "feed-hold and stop latency on a running program (travel and time to rest after the command)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--speeds", default="50,100,200", help="tool speeds to test, mm/s (comma separated)")
    parser.add_argument("--repeats", type=int, default=3, help="pauses per speed")
    parser.add_argument("--no-realtime", action="store_true", help="no SCHED_FIFO/mlockall for the hot loop")


def _wait_rest(client, t_cmd: float, timeout_s: float = 10.0):
    last, still, t_last_move = None, 0, time.monotonic()
    while still < 10:
        if time.monotonic() - t_cmd > timeout_s:
            raise RuntimeError("the machine did not come to rest")
        st = client.call("status")
        now = time.monotonic()
        if st["pose_cmd"] == last:
            still += 1
        else:
            still, t_last_move = 0, now
        last = st["pose_cmd"]
        time.sleep(0.002)
    return st, t_last_move - t_cmd


def _at_mid_line(client, x_mid: float, direction: float, timeout_s: float = 30.0) -> None:
    t0 = time.monotonic()
    while True:
        st = client.call("status")
        if st["state"] == "running" and direction * (st["pose_cmd"][0] - x_mid) >= 0.0:
            return
        if time.monotonic() - t0 > timeout_s:
            raise RuntimeError(f"the program never reached x = {x_mid} (state {st['state']})")
        time.sleep(0.002)


def main(args: argparse.Namespace) -> int:
    from ..daemon import core
    from ..daemon import protocol as P
    from ..daemon.server import SocketServer
    from ..gcode.factory import machine_defaults

    import dataclasses
    cfg = load_config(args.config)
    # this measures the hold, not the timing: a loaded machine's late-cycle bursts must not end
    # the run (stated in the output); every strut limit stays as configured
    cfg = cfg.replace(cycle=dataclasses.replace(cfg.cycle, max_overruns_in_row=1000, following_error_mm=25.0))
    speeds = [float(v) for v in str(args.speeds).split(",") if v.strip()]
    md = machine_defaults(cfg)
    off = np.asarray(md["work_offsets"][1], dtype=float)
    home_tip_z = float(md["start_pose"][2]) + 10.0      # the lines run 10 mm above the home tool tip
    tmp = tempfile.mkdtemp(prefix="hxhold", dir="/tmp")
    load0 = os.getloadavg()
    daemon = core.Daemon(cfg, realtime=not args.no_realtime)
    srv = SocketServer(daemon, cfg, os.path.join(tmp, "hold.sock")).start()
    client = P.Client.unix(srv.socket_path)
    out: dict = {"lead_s": core.REWIND_LEAD_S, "feed_chunk_rows": core.FEED_CHUNK_ROWS,
                 "queue_s": cfg.daemon.feed_ahead_s, "period_s": daemon.period_s, "speeds": {},
                 "relaxed": {"max_overruns_in_row": 1000, "following_error_mm": 25.0}}
    try:
        for v in speeds:
            def w(x):
                return f"X{x - off[0]:.4f} Y{-off[1]:.4f} Z{home_tip_z - off[2]:.4f} A0 B0 C0"
            lines = ["G21 G90 G64 P0.1", f"G0 {w(-120.0)}"]
            for k in range(2 * args.repeats + 2):
                lines.append(f"G1 {w(120.0 if k % 2 == 0 else -120.0)} F{60.0 * v:.1f}")
            lines.append("M2")
            client.call("program", text="\n".join(lines) + "\n", name=f"hold-{v:g}", reply_timeout_s=120.0)
            rows = {"pause": [], "stop": []}
            direction = 1.0
            _at_mid_line(client, -110.0, -1.0)          # at the start of the first G1
            for rep in range(args.repeats + 1):
                _at_mid_line(client, 0.0, direction)
                kind = "stop" if rep == args.repeats else "pause"
                t_cmd = time.monotonic()
                at = client.call(kind)["pose_cmd"]
                st, t_rest = _wait_rest(client, t_cmd)
                rows[kind].append({"travel_mm": round(abs(st["pose_cmd"][0] - at[0]), 3),
                                   "time_to_rest_s": round(t_rest, 4)})
                if kind == "pause":
                    client.call("resume")
                    direction = -direction
                    time.sleep(0.05)
            client.call("wait", timeout_s=60.0)
            out["speeds"][f"{v:g}"] = {
                "speed_mm_s": v, "queue_only_mm": round(v * cfg.daemon.feed_ahead_s, 2),
                "pause": rows["pause"], "stop": rows["stop"],
                "pause_travel_mm_max": max(r["travel_mm"] for r in rows["pause"]),
                "pause_time_to_rest_s_max": max(r["time_to_rest_s"] for r in rows["pause"]),
            }
            daemon.move_to(cfg.home_pose, 80.0, name="home")
            client.call("wait", timeout_s=60.0)
    finally:
        client.close()
        srv.close()
        daemon.close()
        shutil.rmtree(tmp, ignore_errors=True)
    out["loadavg"] = {"before": load0, "after": os.getloadavg()}
    out["commands_rewound"], out["commands_at_queue_end"] = daemon.rewinds
    print(json.dumps(out, indent=2))
    return 0
