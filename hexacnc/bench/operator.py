"""``hexacnc bench operator``: reaction of operator commands, measured on what the drives receive.

The daemon (hot-loop process, simulated drives, socket) runs a program of long lines at
``--speed``; at mid-line a client sends ``pause``, ``override`` (feed 50 %) or ``stop`` over the
socket.  The setpoint rows queued before the command are copied out of the shared ring first; the
first row that differs afterwards is the first setpoint the drives get that the command changed:

* ``reaction_ms`` = (its ring index - the hot loop's read index when the command was sent + 1) x
  the cycle period - the time until the command reaches the drives, exact in cycles;
* ``reaction_wall_ms``: the same seen on the wall clock (the hot loop passed that row; polled
  every 0.2 ms);
* ``time_to_rest_ms`` (pause, stop): until the strut commands stop changing;
* ``loop_speed``: hot-loop time / wall-clock time over the reaction (< 1: the loop fell behind the
  wall clock, e.g. without SCHED_FIFO on a loaded machine: judge the wall-clock figures with it and
  ``loadavg``).

Jog deadman: a continuous jog confirmed every 20 ms for 0.3 s, then the confirmations stop;
``stop_after_deadline_ms`` is from the deadman deadline (last confirmation + ``[jog] deadman_s``)
until the strut commands stand still, ``stop_after_last_confirm_ms`` from the last confirmation
(wall clock), ``stop_after_last_confirm_cycles_ms`` the same in hot-loop cycles x period (the drives'
time base: one setpoint per cycle) and ``loop_speed`` their ratio (< 1: the hot loop fell behind
the wall clock, e.g. without SCHED_FIFO on a loaded machine).

Persistence: offsets and a tool set over the socket, the daemon closed, a new one started on the
same state directory: ``survive_restart`` says whether both came back.  ``jog_deadman_early_stops``
counts jogs the deadman stopped while the bench was still confirming (a confirmation later than
``deadman_s`` on a loaded machine: the safe side; the jog is then repeated).  Prints one JSON object.
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

HELP = "pause / stop / feed-override reaction and jog deadman stop on the drives' setpoints; " \
       "offsets and tools across a restart"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="machine description (default: embedded default)")
    parser.add_argument("--speed", type=float, default=100.0, help="tool speed of the program, mm/s")
    parser.add_argument("--repeats", type=int, default=3, help="commands of each kind")
    parser.add_argument("--no-realtime", action="store_true", help="no SCHED_FIFO/mlockall for the hot loop")


def _ring_rows(sh, S, a: int, b: int) -> np.ndarray:
    out = np.empty((max(0, b - a), S.ROW))
    ring = sh.ring
    for n, k in enumerate(range(a, b)):
        base = (k % S.RING_ROWS) * S.ROW
        out[n] = ring[base:base + S.ROW]
    return out


def _struts(sh, S) -> tuple:
    return tuple(sh.s[S.S_STRUT_CMD:S.S_STRUT_CMD + 6])


def _time_to_rest(sh, S, t0: float, timeout_s: float = 10.0, cyc0: int | None = None):
    """Seconds from ``t0`` until the strut commands last changed (still for 50 ms); with ``cyc0``
    also the hot loop's cycles from ``cyc0`` to that change."""
    last, t_last, c_last = _struts(sh, S), time.monotonic(), sh.h[S.H_CYCLES]
    while time.monotonic() - t_last < 0.05:
        if time.monotonic() - t0 > timeout_s:
            raise RuntimeError("the machine did not come to rest")
        time.sleep(0.0002)
        now = _struts(sh, S)
        if now != last:
            last, t_last, c_last = now, time.monotonic(), sh.h[S.H_CYCLES]
    return (t_last - t0) if cyc0 is None else (t_last - t0, c_last - cyc0)


def _command(daemon, client, S, op: str, fields: dict) -> dict:
    sh = daemon.sh
    r0, w0 = sh.h[S.H_RING_R], sh.h[S.H_RING_W]
    old = _ring_rows(sh, S, r0, w0)
    t_cmd = time.monotonic()
    r_cmd = sh.h[S.H_RING_R]
    client.call(op, **fields)
    t_reply = time.monotonic()
    new = _ring_rows(sh, S, r0, w0)
    diff = np.nonzero(np.any(old != new, axis=1))[0]
    if not len(diff):
        return {"reaction_ms": None, "note": "no queued row changed"}
    k = r0 + int(diff[0])
    while sh.h[S.H_RING_R] <= k and time.monotonic() - t_cmd < 2.0:
        time.sleep(0.0002)
    t_seen = time.monotonic()
    loop_s = (k - r_cmd + 1) * daemon.period_s
    out = {"reaction_ms": round(loop_s * 1e3, 2),
           "reaction_wall_ms": round((t_seen - t_cmd) * 1e3, 2),
           "reply_ms": round((t_reply - t_cmd) * 1e3, 2),
           "loop_speed": round(loop_s / max(t_seen - t_cmd, 1e-9), 3)}
    if op in ("pause", "stop"):
        out["time_to_rest_ms"] = round(_time_to_rest(sh, S, t_cmd) * 1e3, 1)
    return out


def _at_mid_line(client, x_mid: float, direction: float) -> None:
    t0 = time.monotonic()
    while True:
        st = client.call("status")
        if st["state"] == "running" and direction * (st["tool_tip"]["machine"][0] - x_mid) >= 0.0:
            return
        if time.monotonic() - t0 > 30.0:
            raise RuntimeError("the program never reached mid-line")
        time.sleep(0.002)


def _program(client, v: float, repeats: int) -> None:
    lines = ["G21 G90 G64 P0.1", "G53 G0 X-120 Y0 Z-1140"]
    for k in range(3 * repeats + 3):
        lines.append(f"G53 G1 X{120 if k % 2 == 0 else -120} F{60.0 * v:.1f}")
    lines.append("M2")
    client.call("program", text="\n".join(lines) + "\n", name="bench-operator", reply_timeout_s=120.0)


def _holds(daemon, client, S, args) -> dict:
    rows: dict = {"pause": [], "feed_override": [], "stop": []}
    _program(client, args.speed, args.repeats)
    direction = 1.0
    _at_mid_line(client, -110.0, -1.0)
    for rep in range(args.repeats):
        _at_mid_line(client, 0.0, direction)
        rows["pause"].append(_command(daemon, client, S, "pause", {}))
        client.call("resume")
        direction = -direction
        _at_mid_line(client, 0.0, direction)
        rows["feed_override"].append(_command(daemon, client, S, "override", {"feed": 0.5}))
        client.call("override", feed=1.0)
        direction = -direction
    _at_mid_line(client, 0.0, direction)
    rows["stop"].append(_command(daemon, client, S, "stop", {}))
    client.call("wait", timeout_s=30.0)
    return rows


def _deadman(daemon, client, S, repeats: int, P) -> tuple[list, int]:
    """Deadman stops; also the count of jogs the deadman stopped early (a confirmation came late)."""
    out = []
    early = 0
    deadman_s = daemon.cfg.operator.jog.deadman_s
    k = 0
    while len(out) < repeats and k < 4 * repeats:
        k += 1
        client.call("jog", axis="x", direction=1 if k % 2 == 0 else -1)
        t_end = time.monotonic() + 0.3
        t_last = time.monotonic()
        c_last = daemon.sh.h[S.H_CYCLES]
        try:
            while time.monotonic() < t_end:
                t_last, c_last = time.monotonic(), daemon.sh.h[S.H_CYCLES]
                client.call("jog", action="confirm")
                time.sleep(0.02)
        except P.DaemonError:
            early += 1
            client.call("wait", timeout_s=10.0)
            continue
        t_rest, cycles = _time_to_rest(daemon.sh, S, t_last, cyc0=c_last)
        out.append({"stop_after_last_confirm_ms": round(t_rest * 1e3, 1),
                    "stop_after_deadline_ms": round((t_rest - deadman_s) * 1e3, 1),
                    "stop_after_last_confirm_cycles_ms": round(cycles * daemon.period_s * 1e3, 1),
                    "loop_speed": round(cycles * daemon.period_s / max(t_rest, 1e-9), 3)})
        client.call("wait", timeout_s=10.0)
    return out, early


def _restart(cfg, core, P, SocketServer, tmp: str) -> dict:
    def serve(tag):
        d = core.Daemon(cfg, realtime=False)
        return d, SocketServer(d, cfg, os.path.join(tmp, f"{tag}.sock")).start()
    d1, s1 = serve("a")
    try:
        with P.Client.unix(s1.socket_path) as c:
            c.call("offsets", system="G57", values={"x": 12.345, "y": -6.5, "z": -1100.25})
            c.call("tools", tool=9, z_mm=11.125, diameter_mm=3.0, comment="bench")
    finally:
        s1.close()
        d1.close()
    d2, s2 = serve("b")
    try:
        with P.Client.unix(s2.socket_path) as c:
            offs = c.call("offsets")["G57"][:3]
            tools = {t["tool"]: t for t in c.call("tools")["tools"]}
    finally:
        s2.close()
        d2.close()
    ok_o = offs == [12.345, -6.5, -1100.25]
    ok_t = 9 in tools and tools[9]["z_mm"] == 11.125 and tools[9]["comment"] == "bench"
    return {"offsets_survive_restart": ok_o, "tools_survive_restart": ok_t, "survive_restart": ok_o and ok_t}


def _summary(rows: list, key: str) -> dict:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return {"max": max(vals) if vals else None, "median": float(np.median(vals)) if vals else None}


def main(args: argparse.Namespace) -> int:
    from ..daemon import core
    from ..daemon import protocol as P
    from ..daemon import shm as S
    from ..daemon.server import SocketServer
    tmp = tempfile.mkdtemp(prefix="hxbop", dir="/tmp")
    base = load_config(args.config)
    # timing under load must not end the run; every strut limit stays as configured
    cfg = base.replace(cycle=dataclasses.replace(base.cycle, max_overruns_in_row=1000, following_error_mm=25.0),
                       operator=dataclasses.replace(base.operator, state_dir=tmp))
    load0 = os.getloadavg()
    out: dict = {"period_s": None, "speed_mm_s": args.speed, "lead_s": core.REWIND_LEAD_S,
                 "realtime_requested": not args.no_realtime,
                 "relaxed": {"max_overruns_in_row": 1000, "following_error_mm": 25.0}}
    try:
        daemon = core.Daemon(cfg, realtime=not args.no_realtime)
        srv = SocketServer(daemon, cfg, os.path.join(tmp, "op.sock")).start()
        try:
            with P.Client.unix(srv.socket_path) as client:
                out["period_s"] = daemon.period_s
                out["hot_loop_sched_fifo"] = bool(daemon.sh.h[S.H_PRIV_FIFO])
                rows = _holds(daemon, client, S, args)
                out["deadman_s"] = cfg.operator.jog.deadman_s
                out["jog_deadman"], out["jog_deadman_early_stops"] = _deadman(daemon, client, S, args.repeats, P)
        finally:
            srv.close()
            daemon.close()
        for k, v in rows.items():
            out[k] = {"runs": v, "reaction_ms": _summary(v, "reaction_ms"),
                      "reaction_wall_ms": _summary(v, "reaction_wall_ms")}
        out["jog_deadman_stop_after_deadline_ms"] = _summary(out["jog_deadman"], "stop_after_deadline_ms")
        out["jog_deadman_stop_after_last_confirm_ms"] = _summary(out["jog_deadman"], "stop_after_last_confirm_ms")
        out["jog_deadman_stop_after_last_confirm_cycles_ms"] = _summary(out["jog_deadman"],
                                                                        "stop_after_last_confirm_cycles_ms")
        out["commands_rewound"], out["commands_at_queue_end"] = daemon.rewinds
        out.update(_restart(cfg, core, P, SocketServer, tmp))
        out["targets"] = {"reaction_ms_max": 40.0, "deadman_stop_ms_max": 100.0}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["loadavg"] = {"before": load0, "after": os.getloadavg()}
    print(json.dumps(out, indent=2))
    return 0
