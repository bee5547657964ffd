"""What the drives saw: a read-only tap on the daemon's shared-memory frame rings.

Attaches to the frame ring segments (:mod:`hexacnc.daemon.shmbus`; their names are in the daemon's
log line ``frame rings: ...`` or ``Daemon.sim.segments``) and copies every record both ways as it
is published, from a thread polling every ``poll_s`` (the 4096-record rings hold ~0.5 s). It
never writes to the rings. Decoding uses the layout plan (:func:`drivers.layout.plan_layout`):

* master -> drives: per SYNC the target of every drive (RPDO1), controlwords (RPDO2 or in RPDO1),
  NMT commands, master heartbeats;
* drives -> master: statuswords (TPDO2), positions (TPDO1), EMCY, heartbeats and boot-ups.

Used by the safety tests and ``hexacnc bench faults`` to judge a stop by the frames, not by
what the daemon believes.
"""
from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field
from multiprocessing import shared_memory

import numpy as np

from drivers import framerec
from drivers.layout import MASTER_NODE_ID, SYNC_COB_ID, plan_layout

_HDR = framerec.HEADER
REC = framerec.RECORD
_OFF_DATA = 5 * 64
_I_W = (8, 24)


@dataclass
class Seen:
    """Decoded frames, in order of publication (t: monotonic s when the tap copied them)."""
    targets: list = field(default_factory=list)      #: per bus, per SYNC: (t, [6 targets inc or None])
    cw: list = field(default_factory=list)           #: (t, strut, controlword)
    nmt: list = field(default_factory=list)          #: (t, command, node)
    master_hb: int = 0
    status: list = field(default_factory=list)       #: (t, strut, statusword)
    emcy: list = field(default_factory=list)         #: (t, strut, code)
    bootup: list = field(default_factory=list)       #: (t, strut)
    positions: int = 0
    missed: int = 0                                  #: records overwritten before the tap read them


def write_index(seg, side: int) -> int:
    """Records published so far on one direction of a frame ring (0: master -> drives, 1: back)."""
    return int(np.frombuffer(seg.buf, dtype=np.int64, count=1, offset=8 * _I_W[side])[0])


def attach(name: str) -> shared_memory.SharedMemory:
    """Attach to a daemon's frame ring segment without taking it over (no resource tracking)."""
    seg = shared_memory.SharedMemory(name=name)
    try:
        from multiprocessing import resource_tracker
        resource_tracker.unregister(seg._name, "shared_memory")  # type: ignore[attr-defined]
    except Exception:
        pass
    return seg


class RingTap:
    """``RingTap(cfg, names).start()`` ... ``.stop()``; ``.seen`` holds the decoded frames."""

    def __init__(self, cfg, names, poll_s: float = 0.005):
        self.plan = plan = plan_layout(cfg.bus)
        self.ipm = float(cfg.bus.increments_per_mm)
        self.off = np.asarray(cfg.strut_offset_mm, dtype=float)
        self.poll_s = poll_s
        self.segs = [attach(name) for name in names]
        self.n = [int(np.frombuffer(seg.buf, dtype=np.int64, count=2)[1]) for seg in self.segs]
        self.pos = [[self._w(b, 0), self._w(b, 1)] for b in range(len(self.segs))]
        self.seen = Seen(targets=[[] for _ in self.segs])
        self._last = [None] * 6          # the targets of the last RPDOs seen, per strut
        rx = {}
        for frame in plan.frames:
            rx[(frame.bus, frame.cob_id)] = ("rpdo1", frame)
        for nd in plan.nodes:
            if nd.rpdo2_cob_id is not None:
                rx[(nd.bus, nd.rpdo2_cob_id)] = ("cw", nd.index)
        self._rx_master = rx
        self._rx_drive = {}
        for nd in plan.nodes:
            self._rx_drive[nd.tpdo2_cob_id] = ("status", nd.index)
            self._rx_drive[nd.tpdo1_cob_id] = ("pos", nd.index)
            self._rx_drive[0x080 + nd.node_id] = ("emcy", nd.index)
            self._rx_drive[0x700 + nd.node_id] = ("hb", nd.index)
        self._stop = threading.Event()
        self._thread = None
        self.lock = threading.Lock()

    def _w(self, b: int, side: int) -> int:
        return write_index(self.segs[b], side)

    def start(self) -> "RingTap":
        self._thread = threading.Thread(target=self._run, name="ringtap", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> Seen:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.drain()
        for seg in self.segs:
            try:
                seg.close()
            except BufferError:
                pass
        self.segs = []
        return self.seen

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            self.drain()

    def drain(self) -> None:
        """Decode what the rings got since the last call. Frames of one call get the time of the call
        plus 1 ns per frame, so each ring's order survives (a SYNC before a controlword stays before it)."""
        with self.lock:
            now = time.monotonic()
            k = 0
            for b, seg in enumerate(self.segs):
                for side in (0, 1):
                    w = self._w(b, side)
                    r = self.pos[b][side]
                    n = self.n[b]
                    if w - r > n:
                        self.seen.missed += w - r - n
                        r = w - n
                    base = _OFF_DATA + side * n * REC
                    buf = seg.buf
                    while r < w:
                        p = base + (r % n) * REC
                        arb, flags, length = _HDR.unpack_from(buf, p)
                        data = bytes(buf[p + _HDR.size:p + _HDR.size + length])
                        if side == 0:
                            self._master(now + k * 1e-9, b, arb, data)
                        else:
                            self._drive(now + k * 1e-9, arb, data)
                        k += 1
                        r += 1
                    self.pos[b][side] = w

    def _master(self, t: float, b: int, arb: int, data: bytes) -> None:
        s = self.seen
        if arb == SYNC_COB_ID:
            s.targets[b].append((t, [self._last[i] for i in self.plan.bus_nodes[b]]))
            return
        if arb == 0x700 + MASTER_NODE_ID:
            s.master_hb += 1
            return
        if arb == 0 and len(data) >= 2:
            s.nmt.append((t, data[0], data[1]))
            return
        hit = self._rx_master.get((b, arb))
        if hit is None:
            return
        kind, x = hit
        if kind == "cw":
            s.cw.append((t, x, struct.unpack_from("<H", data)[0]))
        else:
            for i, off in x.slots:
                self._last[i] = struct.unpack_from("<i", data, off)[0]
                if x.has_controlword:
                    cw = struct.unpack_from("<H", data, off - 2)[0]
                    if not s.cw or s.cw[-1][1:] != (i, cw):
                        s.cw.append((t, i, cw))

    def _drive(self, t: float, arb: int, data: bytes) -> None:
        hit = self._rx_drive.get(arb)
        if hit is None:
            return
        kind, i = hit
        s = self.seen
        if kind == "status" and len(data) >= 2:
            s.status.append((t, i, struct.unpack_from("<H", data)[0]))
        elif kind == "pos":
            s.positions += 1
        elif kind == "emcy" and len(data) >= 2:
            s.emcy.append((t, i, struct.unpack_from("<H", data)[0]))
        elif kind == "hb" and data and data[0] & 0x7F == 0:
            s.bootup.append((t, i))

    # -- analysis ---------------------------------------------------------------------------
    def lengths_mm(self, since_t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(times, (N, 6) commanded strut lengths in mm) of the SYNCs after ``since_t`` (the buses'
        SYNC series aligned at their ends: every cycle sends one SYNC on every bus)."""
        with self.lock:
            per_bus = [[(t, v) for t, v in rows if t >= since_t and None not in v] for rows in self.seen.targets]
        n = min(len(rows) for rows in per_bus)
        if n == 0:
            return np.zeros(0), np.zeros((0, 6))
        inc = np.zeros((n, 6))
        for b, rows in enumerate(per_bus):
            cols = self.plan.bus_nodes[b]
            inc[:, list(cols)] = np.array([v for _, v in rows[len(rows) - n:]], dtype=float)
        t = np.array([r[0] for r in per_bus[0][len(per_bus[0]) - n:]])
        return t, inc / self.ipm + self.off

    def last_controlwords(self) -> list:
        out = [None] * 6
        with self.lock:
            for _, i, cw in self.seen.cw:
                out[i] = cw
        return out

    def last_statuswords(self) -> list:
        out = [None] * 6
        with self.lock:
            for _, i, sw in self.seen.status:
                out[i] = sw
        return out


#: worst-case error of a peak estimate from the rounding of the targets to drive increments, as a
#: share of the limit: each estimate uses the shortest window that keeps it within this
RESOLUTION_TARGET = 0.02


@dataclass(frozen=True)
class PeakEstimator:
    """How :func:`motion_peaks` estimates v/a/j from targets rounded to ``increment_mm``.

    The k-th derivative is the k-th difference over ``h_k`` cycles divided by ``(h_k dt)^k``: a
    weighted average (positive weights, sum 1: a B-spline kernel over ``k h_k`` cycles) of the
    single-cycle derivative of the unrounded stream, so it never exceeds that stream's largest
    single-cycle value. Rounding each target by at most half an increment adds at most
    ``2^(k-1) increment / (h_k dt)^k`` (the ``resolution``, here as a share of the smallest limit);
    ``h_k`` is the shortest window that keeps it within :data:`RESOLUTION_TARGET`. A longer window
    averages a jerk pulse shorter than ``3 h_3`` cycles down (it measures its mean, not its peak)."""
    window_cycles: dict
    resolution: dict

    def as_dict(self, period_s: float) -> dict:
        return {"window_cycles": self.window_cycles,
                "span_ms": {k: round(n * self.window_cycles[k] * period_s * 1e3, 2)
                            for n, k in ((1, "v"), (2, "a"), (3, "j"))},
                "resolution_fraction": {k: round(x, 4) for k, x in self.resolution.items()},
                "method": "k-th difference over h_k cycles (B-spline average of the single-cycle values); "
                          "resolution = worst-case rounding error of the 0.5-increment targets / smallest limit"}


def peak_estimator(period_s: float, increment_mm: float, vmax, amax, jmax) -> PeakEstimator:
    """Windows and worst-case rounding resolution for targets of ``increment_mm`` (see :class:`PeakEstimator`)."""
    lim = {"v": float(np.min(vmax)), "a": float(np.min(amax)), "j": float(np.min(jmax))}
    win, res = {}, {}
    for k, name in ((1, "v"), (2, "a"), (3, "j")):
        h = 1
        while 2 ** (k - 1) * increment_mm / (h * period_s) ** k > RESOLUTION_TARGET * lim[name] and h < 64:
            h += 1
        win[name] = h
        res[name] = 2 ** (k - 1) * increment_mm / (h * period_s) ** k / lim[name]
    return PeakEstimator(win, res)


def motion_peaks(L: np.ndarray, period_s: float, vmax, amax, jmax, increment_mm: float = 1e-4) -> dict:
    """Peak |v|, |a|, |j| per strut of a command stream (one row per SYNC) as fractions of the limits,
    by :func:`peak_estimator` for targets rounded to ``increment_mm`` (0.1 um: ``[bus]
    increments_per_mm`` 10,000). Single-cycle third differences of such targets would read up to
    16x the 200,000 mm/s^3 limit by rounding alone."""
    est = peak_estimator(period_s, increment_mm, vmax, amax, jmax)
    h1, h2, h3 = est.window_cycles["v"], est.window_cycles["a"], est.window_cycles["j"]
    if len(L) < 3 * h3 + 2:
        return {"v": 0.0, "a": 0.0, "j": 0.0}
    dt = period_s
    v = (L[h1:] - L[:-h1]) / (h1 * dt)
    a = (L[2 * h2:] - 2 * L[h2:-h2] + L[:-2 * h2]) / (h2 * dt) ** 2
    j = (L[3 * h3:] - 3 * L[2 * h3:-h3] + 3 * L[h3:-2 * h3] - L[:-3 * h3]) / (h3 * dt) ** 3
    return {"v": float(np.max(np.abs(v) / np.asarray(vmax))),
            "a": float(np.max(np.abs(a) / np.asarray(amax))),
            "j": float(np.max(np.abs(j) / np.asarray(jmax)))}


def stop_figures(tap: RingTap, cfg, period_s: float, t_from: float) -> dict:
    """Stop distance per strut (mm, from ``t_from`` to the last SYNC) and peak v/a/j fractions."""
    t, L = tap.lengths_mm(t_from)
    if len(L) == 0:
        return {"syncs": 0}
    pk = motion_peaks(L, period_s, cfg.max_velocity_mm_s, cfg.max_acceleration_mm_s2, cfg.max_jerk_mm_s3,
                      1.0 / cfg.bus.increments_per_mm)
    return {"syncs": int(len(L)), "stop_distance_mm": [round(float(x), 4) for x in np.abs(L[-1] - L[0])],
            "peak_fraction": {k: round(v, 3) for k, v in pk.items()},
            "final_speed_mm_s": round(float(np.max(np.abs(L[-1] - L[-2]))) / period_s, 3) if len(L) > 1 else 0.0}
