"""``hexacnc bench faults``, path ``stop_during_planning``: a ``stop`` while a 1e6-line program is
being uploaded, interpreted and planned must act within 40 ms on the frames the drives receive.

The machine moves (a point-to-point move at 15 mm/s); the program goes over the socket as a client
sends it: one ``program`` message is refused above ``[daemon] max_message_bytes`` (checked first,
on its own connection: the reply is ``too_large`` and names the chunked upload), so it is uploaded in
chunks (``program_begin`` / ``program_chunk`` / ``program_end``, the pieces ``hexacnc send`` cuts,
each reply timed: ``chunk_reply_s``), then ``stop`` is sent ``stop_after_s`` after the program's
planning children started (streamed validation and windowed planning, :mod:`hexacnc.daemon.planstream`; 0.5: while they interpret, validate
and plan; the move starts once they run, so that it is under way at the stop whatever the time the
daemon took to take the program on a loaded machine) or right behind ``program_end`` (0: while the
daemon takes the chunks).

``latency_s``: from sending ``stop`` to the first SYNC whose targets leave the motion they
followed: a strut's target more than :data:`DEPARTURE_INCREMENTS` increments off a quadratic fitted
over the 100 ms before the stop. The SYNCs' send times are bounded from above by the tap's copy times
and their order (SYNCs never come closer than a period): ``t_k = min over j >= k of (copy_j - (j -
k) dt)``, so the tap's 5 ms polling adds little (it can only make the figure later). A jerk-limited
stop departs slowly: at 6.6 mm/s strut speed and the playback's 5000 /s^3 rate jerk, 3 increments
take ~20 ms, included. ``latency_cycles_s``: the same in SYNCs sent x period (what the figure is
with a hot loop on time; on a starved machine it sends far fewer SYNCs). ``stop_after_s`` None: the same stop with no program sent (the baseline).
"""
from __future__ import annotations

import os
import socket
import tempfile
import time

import numpy as np

from ..commands.upload_client import CHUNK_BYTES, split_chunks
from .faultjudge import judge, moving_daemon, start_move

#: a SYNC has left the motion before the stop when a strut's target is this many increments off
#: its extrapolation (a quadratic fitted over the 100 ms before the stop): above the rounding
DEPARTURE_INCREMENTS = 3


def first_decel_s(tap, cfg, t0: float) -> tuple[float, float] | None:
    """(seconds from ``t0`` to the first SYNC whose targets leave the motion before the stop (see the
    module doc), the same in cycles x period: what it is with a loop on time), None if none."""
    dt = cfg.cycle.period_s
    t, L = tap.lengths_mm(t0 - 0.2)
    keep = t < t0 + 0.3
    t, L = t[keep], L[keep]
    if len(L) < 100:
        return None
    k = np.arange(len(t))
    # send time of SYNC k <= copy time of any later SYNC j minus (j - k) periods (SYNCs never come
    # closer than a period): the reverse running minimum, an upper bound tighter than the copy time
    t_sync = np.minimum.accumulate((t - k * dt)[::-1])[::-1] + k * dt
    fit = (t_sync < t0) & (t_sync > t0 - 0.1)
    if fit.sum() < 20:
        return None
    tol = DEPARTURE_INCREMENTS / cfg.bus.increments_per_mm
    for i in range(6):
        if np.ptp(L[fit, i]) < 0.05:                # this strut hardly moved: no reference
            L[:, i] = 0.0
    dev = np.zeros(len(t))
    for i in range(6):
        c = np.polyfit(k[fit], L[fit, i], 2)        # the motion before the stop, extrapolated
        dev = np.maximum(dev, np.abs(L[:, i] - np.polyval(c, k)))
    late = np.nonzero((t_sync >= t0) & (dev > tol))[0]
    if not len(late):
        return None
    first = int(np.nonzero(t_sync >= t0)[0][0])
    return float(t_sync[late[0]] - t0), (int(late[0]) - first) * dt


class _Conn:
    """A raw client connection (requests written while earlier replies are outstanding)."""

    def __init__(self, path: str):
        from ..daemon import protocol as P
        self.P = P
        self.s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.s.connect(path)
        self.s.settimeout(60.0)
        self.dec = P.Decoder(1 << 26)
        self.got: dict = {}

    def send(self, msg: dict) -> float:
        self.s.sendall(self.P.encode(msg))
        return time.monotonic()

    def wait(self, mid, t_from: float | None = None) -> tuple[float, dict]:
        while mid not in self.got:
            data = self.s.recv(65536)
            if not data:
                raise ConnectionError("the daemon closed the connection")
            self.dec.feed(data)
            for m in self.dec.messages():
                self.got[m.get("id")] = (time.monotonic(), m)
        t, m = self.got[mid]
        return (t - t_from if t_from is not None else t), m

    def close(self) -> None:
        self.s.close()


def _one_message_refused(path: str, text: str) -> dict:
    c = _Conn(path)
    try:
        try:
            c.send({"id": 1, "op": "program", "text": text, "name": "one-message.ngc"})
        except OSError:
            pass                                 # closed after the refusal: the reply is still to be read
        _, m = c.wait(None)
        err = m.get("error") or {}
        return {"code": err.get("code"), "names_chunks": "program_chunk" in str(err.get("message"))}
    except (ConnectionError, OSError) as exc:
        return {"code": None, "error": str(exc)}
    finally:
        c.close()


def _baseline(c: _Conn, d, tap, cfg) -> dict:
    time.sleep(0.3)
    tap.drain()
    t0 = c.send({"id": 3, "op": "stop"})
    stop_reply_s, _ = c.wait(3, t0)
    time.sleep(0.3)
    out = judge(tap, cfg, t0)
    out.pop("drives_end", None)
    lat = first_decel_s(tap, cfg, t0)
    f = d.status()["fault"]
    out.update(latency_s=round(lat[0], 4) if lat else None, latency_cycles_s=round(lat[1], 4) if lat else None,
               detected=lat is not None, note="baseline: the same stop with no program sent", stop_reply_s=round(stop_reply_s, 4),
               drives_stay_enabled=True,
               fault=f and f["code"], spurious=f is not None)
    return out


def _wait_planning(d, timeout_s: float) -> float | None:
    """When the program's planning children run (monotonic s), None if not within ``timeout_s``."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        plans = list(d._planning)
        if any(p.alive() for p in plans if hasattr(p, "alive")):
            return time.monotonic()
        time.sleep(0.005)
    return None


def _validated_lines(d) -> int | None:
    for p in list(d._planning):
        v = getattr(p, "validation", None)
        if v is not None:
            return int(v.get("line", 0))
    return None


def stop_during_planning(cfg, lines: int, stop_after_s: float | None = 0.5) -> dict:
    """The path (see the module doc)."""
    from ..daemon.server import SocketServer
    body = (f"G1 X{(i % 100) * 0.5 - 25:.1f} Y{(i % 7) - 3} F3000\n" for i in range(lines))
    text = "" if stop_after_s is None else "G0 X0 Y0 Z20\n" + "".join(body)
    data = text.encode()
    during = stop_after_s is not None and stop_after_s > 0
    d, tap = moving_daemon(cfg, 15.0, move=not during)      # ~7 s of motion (during planning: started then)
    tmp = tempfile.mkdtemp(prefix="hxbp", dir="/tmp")
    srv = SocketServer(d, cfg, os.path.join(tmp, "b.sock")).start()
    c = None
    try:
        baseline = stop_after_s is None
        one = (_one_message_refused(srv.socket_path, text) if len(data) > cfg.daemon.max_message_bytes
               and not baseline else None)
        c = _Conn(srv.socket_path)
        rtt = []
        if baseline:
            return _baseline(c, d, tap, cfg)
        c.send({"id": 1, "op": "program_begin", "name": f"{lines}-lines.ngc", "bytes": len(data)})
        if not c.wait(1)[1].get("ok"):
            raise RuntimeError(f"program_begin refused: {c.got[1][1].get('error')}")
        for seq, part in enumerate(split_chunks(data, min(CHUNK_BYTES, cfg.daemon.max_message_bytes - 4096))):
            t_s = c.send({"id": 100 + seq, "op": "program_chunk", "seq": seq, "text": part.decode()})
            dt_r, m = c.wait(100 + seq, t_s)
            if not m.get("ok"):
                raise RuntimeError(f"chunk {seq} refused: {m.get('error')}")
            rtt.append(dt_r)
        t_end_sent = c.send({"id": 2, "op": "program_end"})
        t_planning = None
        if during:          # the motion runs while the planning children interpret, validate and plan
            t_planning = _wait_planning(d, 120.0)
            start_move(d, tap, cfg, 15.0)
            time.sleep(stop_after_s)
        planning = bool(d._planning)
        validated_lines = _validated_lines(d)
        tap.drain()
        t0 = c.send({"id": 3, "op": "stop"})
        stop_reply_s, _ = c.wait(3, t0)
        _, end_reply = c.wait(2)
        time.sleep(0.3)
        out = judge(tap, cfg, t0)
        out.pop("drives_end", None)         # a stop keeps the drives enabled: their statuswords do not change
        lat = first_decel_s(tap, cfg, t0)
        f = d.status()["fault"]
        out.update(latency_s=round(lat[0], 4) if lat else None, latency_cycles_s=round(lat[1], 4) if lat else None,
                   detected=lat is not None,
                   latency_method="stop sent -> first SYNC off the motion before it (see hexacnc/bench/stopplan.py)",
                   lines=lines, program_bytes=len(data), one_message=one, chunks=len(rtt),
                   chunk_reply_s={"median": round(float(np.median(rtt)), 4), "max": round(max(rtt), 4)},
                   stop_after_program_end_s=round(t0 - t_end_sent, 4), planning_when_stopped=planning,
                   planning_started_after_s=None if t_planning is None else round(t_planning - t_end_sent, 3),
                   validated_lines_when_stopped=validated_lines,
                   stop_reply_s=round(stop_reply_s, 4), program_refused=not end_reply.get("ok"),
                   program_error=(end_reply.get("error") or {}).get("message"),
                   fault=f and f["code"], spurious=f is not None,
                   drives_stay_enabled=True)       # a stop keeps the drives enabled (not an end: by design)
        return out
    finally:
        if c is not None:
            c.close()
        srv.close()
        d.close()
        tap.stop()
