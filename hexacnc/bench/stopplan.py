"""``hexacnc bench faults``, path ``stop_during_planning``: a ``stop`` while a 1e6-line program is
being uploaded, interpreted and planned must act within 40 ms on the frames the drives receive.

The machine moves (a point-to-point move at 15 mm/s); the program goes over the socket as a client
sends it: one ``program`` message is refused above ``[daemon] max_message_bytes`` (checked first,
on its own connection: the reply is ``too_large`` and names the chunked upload), so it is uploaded in
chunks (``program_begin`` / ``program_chunk`` / ``program_end``, the pieces ``hexacnc send`` cuts,
each reply timed: ``chunk_reply_s``), then ``stop`` is sent ``stop_after_s`` after ``program_end``
(0: right behind it, while the daemon takes the assembled text; 0.5: while the child plans).

``latency_s``: from sending ``stop`` to the first SYNC whose targets decelerate. The SYNCs' send
times are bounded from above by the tap's copy times and their order (SYNCs never come closer than a
period): ``t_k = min over j >= k of (copy_j - (j - k) dt)``, so the tap's 5 ms polling adds little to
the figure (it can only make it later). A SYNC decelerates when the fastest strut's speed over 4 cycles
is below 99 % of its median over the 100 ms before the stop (the 0.1 um targets make the
single-cycle speed at 15 mm/s jitter by +-1.3 %).
"""
from __future__ import annotations

import os
import socket
import tempfile
import time

import numpy as np

from ..commands.upload_client import CHUNK_BYTES, split_chunks
from .faultjudge import judge, moving_daemon


def first_decel_s(tap, cfg, t0: float) -> float | None:
    """Seconds from ``t0`` to the first decelerating SYNC (see the module doc), None if none."""
    dt = cfg.cycle.period_s
    t, L = tap.lengths_mm(t0 - 0.2)
    keep = t < t0 + 0.3
    t, L = t[keep], L[keep]
    if len(L) < 300:
        return None
    k = np.arange(len(t))
    # send time of SYNC k <= copy time of any later SYNC j minus (j - k) periods (SYNCs never come
    # closer than a period): the reverse running minimum, an upper bound tighter than the copy time
    t_sync = np.minimum.accumulate((t - k * dt)[::-1])[::-1] + k * dt
    v4 = np.max(np.abs(L[4:] - L[:-4]), axis=1) / (4 * dt)
    ts = t_sync[4:]
    before = v4[(ts < t0) & (ts > t0 - 0.1)]
    if len(before) < 20 or np.median(before) < 1.0:
        return None
    slow = np.nonzero((ts >= t0) & (v4 < 0.99 * np.median(before)))[0]
    return float(ts[slow[0]] - 4 * dt - t0) if len(slow) else None     # the first of the 4 cycles


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


def stop_during_planning(cfg, lines: int, stop_after_s: float = 0.5) -> dict:
    """The path (see the module doc)."""
    from ..daemon.server import SocketServer
    text = "G0 X0 Y0 Z20\n" + "".join(f"G1 X{(i % 100) * 0.5 - 25:.1f} Y{(i % 7) - 3} F3000\n" for i in range(lines))
    data = text.encode()
    d, tap = moving_daemon(cfg, 15.0)           # ~7 s of motion
    tmp = tempfile.mkdtemp(prefix="hxbp", dir="/tmp")
    srv = SocketServer(d, cfg, os.path.join(tmp, "b.sock")).start()
    c = None
    try:
        one = _one_message_refused(srv.socket_path, text) if len(data) > cfg.daemon.max_message_bytes else None
        c = _Conn(srv.socket_path)
        c.send({"id": 1, "op": "program_begin", "name": f"{lines}-lines.ngc", "bytes": len(data)})
        if not c.wait(1)[1].get("ok"):
            raise RuntimeError(f"program_begin refused: {c.got[1][1].get('error')}")
        rtt = []
        for seq, part in enumerate(split_chunks(data, min(CHUNK_BYTES, cfg.daemon.max_message_bytes - 4096))):
            t_s = c.send({"id": 100 + seq, "op": "program_chunk", "seq": seq, "text": part.decode()})
            dt_r, m = c.wait(100 + seq, t_s)
            if not m.get("ok"):
                raise RuntimeError(f"chunk {seq} refused: {m.get('error')}")
            rtt.append(dt_r)
        t_end_sent = c.send({"id": 2, "op": "program_end"})
        time.sleep(stop_after_s)
        planning = bool(d._planning)
        tap.drain()
        t0 = c.send({"id": 3, "op": "stop"})
        stop_reply_s, _ = c.wait(3, t0)
        _, end_reply = c.wait(2)
        time.sleep(0.3)
        out = judge(tap, cfg, t0)
        lat = first_decel_s(tap, cfg, t0)
        f = d.status()["fault"]
        out.update(latency_s=round(lat, 4) if lat is not None else None, detected=lat is not None,
                   latency_method="stop sent -> first SYNC decelerating (send times from the SYNC order)",
                   lines=lines, program_bytes=len(data), one_message=one, chunks=len(rtt),
                   chunk_reply_s={"median": round(float(np.median(rtt)), 4), "max": round(max(rtt), 4)},
                   stop_after_program_end_s=round(t0 - t_end_sent, 4), planning_when_stopped=planning,
                   stop_reply_s=round(stop_reply_s, 4), program_refused=not end_reply.get("ok"),
                   program_error=(end_reply.get("error") or {}).get("message"),
                   fault=f and f["code"], spurious=f is not None)
        return out
    finally:
        if c is not None:
            c.close()
        srv.close()
        d.close()
        tap.stop()
