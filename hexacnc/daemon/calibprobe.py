"""Op ``probe``: a straight probing move of the tool tip that stops on contact (G38.2-G38.5 semantics).

``probe`` {tip_mm: [x, y, z, a, b, c] end of the move (machine frame, mm/deg), feed_mm_min, mode:
"38.2" | "38.3" | "38.4" | "38.5"}.  The move is planned and checked like any program (G53 G1);
the probe input is sampled every 2 ms from the drive readings (simulation: the true tool tip's
distance to the artefact, :mod:`hexacnc.sim.probesignal`).  At the edge (contact for .2/.3, loss
of contact for .4/.5) the readings at the edge are interpolated between the two samples around it
and the daemon's controlled stop decelerates along the path within the strut limits.  Reply:
``contact`` (bool), ``q_mm`` (readings at the edge), ``params`` {"5061".."5069": tool tip x..c and
u, v, w = 0 of the controller's model at the edge, "5070": 1/0}, ``t_s``, ``overtravel_mm``.
No edge by the end of the move: error for .2/.4 (as LinuxCNC), ``contact: false`` for .3/.5.
Already tripped at the start (.2/.3) or not tripped (.4/.5): error.  Every edge goes into the
probe log (last 1000, returned in the reply as ``log_index``; ``calib run`` writes them to
``MEAS.csv.probes.jsonl``).

The drives' own latch (CiA 402 0x60B8-0x60BB, :mod:`drivers.touchprobe`) is armed for the edge
before the move and read by the hot loop over SDO (:mod:`.probelatch`): ``q_mm`` are the readings
the drives latched at the edge (``latched: true``); without a latch (a drive refuses 0x60B8, no
SDO channel, not every drive latched within 0.3 s) the readings interpolated between the two 2 ms
samples around the edge (``latched: false``; both kept: ``q_interp_mm``).  On a machine without
a simulated probe signal the latch alone is the probe input (the first drive that latched stops
the move).
"""
from __future__ import annotations

import math
import time
from collections import deque
from typing import Any

import numpy as np

from ..errors import HexacncError

POLL_S = 0.002
LATCH_WAIT_S = 0.3
MODES = ("38.2", "38.3", "38.4", "38.5")
OPS = {"probe": {"tip_mm": ((list, tuple), True), "feed_mm_min": ((int, float), True), "mode": ((str,), False)}}
MAX_FEED_MM_MIN = 3000.0


def model_tip_pose(cfg, q_mm) -> np.ndarray:
    """Tool tip pose (mm/deg) the controller's model gives for drive readings (map, sag, FK)."""
    from ..kinematics import Hexapod
    from ..pose import matrix_from_euler
    from ..sag import sag_elongation_mm
    from ..strutmap import strut_map_from_config
    hx = Hexapod(cfg)
    L0 = strut_map_from_config(cfg).strut_from_drive(np.asarray(cfg.strut_offset_mm) + np.asarray(q_mm))
    pose = np.asarray(cfg.home_pose, dtype=float)
    for _ in range(3):
        res = hx.forward(L0 + sag_elongation_mm(hx, pose), guess=pose)
        if not res.ok:
            raise HexacncError(f"probe: readings {np.round(q_mm, 4).tolist()} give no pose of the model")
        pose = res.pose
    tip = pose[:3] + matrix_from_euler(*np.radians(pose[3:])) @ np.asarray(cfg.tool.tip_platform_mm)
    return np.r_[tip, pose[3:]]


def _check(fields: dict) -> tuple[np.ndarray, float, str]:
    tip = fields["tip_mm"]
    if len(tip) != 6 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                for v in tip):
        raise ValueError("tip_mm: expected 6 finite numbers x, y, z (mm), a, b, c (deg)")
    feed = float(fields["feed_mm_min"])
    if not 0.0 < feed <= MAX_FEED_MM_MIN:
        raise ValueError(f"feed_mm_min {feed}: expected (0, {MAX_FEED_MM_MIN:g}]")
    mode = fields.get("mode", "38.2")
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    return np.asarray(tip, dtype=float), feed, mode


class _Watch:
    """The probe input seen by the supervisor: the simulated signal (2 ms samples, edge readings
    interpolated) and/or the drives' latch (hot loop over SDO, :mod:`.probelatch`)."""

    def __init__(self, daemon: Any, mode: str):
        from . import probelatch as PL
        self.d, self.mode, self.PL = daemon, mode, PL
        self.want = mode in ("38.2", "38.3")
        self.sig = getattr(daemon, "calib_probe_signal", None)
        self.hist = daemon.calib_history
        self.req = PL.arm(daemon.sh, 1 if self.want else 2)
        self.latch_ok = PL.wait_state(daemon.sh, self.req, (PL.ARMED,), LATCH_WAIT_S) == PL.ARMED
        if self.sig is None and not self.latch_ok:
            PL.disarm(daemon.sh)
            raise HexacncError("no probe input on this daemon: the drives' touch-probe latch cannot be armed "
                               "(simulation: hexacnc run --truth)")
        t, q = self.hist.current()
        s = self.sig.distance_mm(q, time.monotonic()) if self.sig is not None else 1.0
        if self.sig is not None and self.want == (s <= 0):
            PL.disarm(daemon.sh)
            raise HexacncError(f"G{mode}: the probe is {'already' if self.want else 'not'} tripped at the start")
        self.prev = (t, q, s)
        self.s_min = s
        self.hit = None

    def edge(self) -> bool:
        """One 2 ms look; True at the edge (``hit``: time and interpolated readings, or None)."""
        t, q = self.hist.current()
        s = 1.0
        if self.sig is not None:
            try:
                s = self.sig.distance_mm(q, time.monotonic())
            except (ValueError, np.linalg.LinAlgError) as exc:
                self.d.stop()
                raise HexacncError(f"G{self.mode}: probe input lost ({exc})") from None
            p = self.prev
            if (p[2] > 0 >= s) if self.want else (p[2] <= 0 < s):
                w = p[2] / (p[2] - s) if p[2] != s else 1.0
                self.hit = (p[0] + w * (t - p[0]), p[1] + w * (q - p[1]))
                return True
        elif self.latch_ok and self.PL.read(self.d.sh)[1]:
            self.hit = (t, q)
            return True
        self.prev = (t, q, s)
        self.s_min = min(self.s_min, s)
        return False

    def latched(self):
        """The drive readings (mm) latched at the edge, or None (latch not armed, not every drive)."""
        PL = self.PL
        if not self.latch_ok:
            return None
        st = PL.wait_state(self.d.sh, self.req, (PL.LATCHED,), LATCH_WAIT_S)
        if st != PL.LATCHED:
            return None
        return np.asarray(PL.read(self.d.sh)[2], dtype=float) / float(self.d.cfg.bus.increments_per_mm)


def _move_until_edge(daemon: Any, w: _Watch, tip: np.ndarray, feed: float, mode: str) -> bool:
    words = " ".join(f"{a}{v:.6f}" for a, v in zip("XYZABC", tip))
    stops = daemon._stops
    daemon.load_program(f"G21 G90 G94\nG53 G1 {words} F{feed:.4f}\nM2\n", f"probe G{mode}")
    found = False
    t_end = time.monotonic() + 600.0
    t_start = time.monotonic() + 10.0
    started = False
    while time.monotonic() < t_end:
        time.sleep(POLL_S)
        if w.edge():
            daemon.stop()
            stops += 1                      # our own stop at the edge
            found = True
            break
        st = daemon.status_state()
        started = started or st == "running"
        idle = daemon.current is None and not daemon.queue
        if st == "fault" or (idle and (started or time.monotonic() > t_start)):
            break
    st = daemon.wait(60.0)
    if daemon._stops != stops:
        raise HexacncError(f"G{mode}: probe move stopped")
    if st.get("state") == "fault":
        raise HexacncError(f"G{mode}: probe move aborted: {(st.get('fault') or {}).get('message', 'fault')}")
    return found


def probe_move(daemon: Any, tip: np.ndarray, feed: float, mode: str) -> dict:
    from . import probelatch as PL
    w = _Watch(daemon, mode)
    try:
        found = _move_until_edge(daemon, w, tip, feed, mode)
        q_latch = w.latched() if found else None
    finally:
        PL.disarm(daemon.sh)
    if not found:
        if mode in ("38.2", "38.4"):
            near = f" (closest {w.s_min:.4f} mm from the surface)" if w.sig is not None else ""
            raise HexacncError(f"G{mode}: move finished without the probe {'tripping' if w.want else 'releasing'}"
                               + near)
        return {"contact": False, "params": {"5070": 0}, "mode": mode}
    t_c, q_i = w.hit if w.hit is not None else (time.time(), None)
    q_c = q_latch if q_latch is not None else q_i
    if q_c is None:
        raise HexacncError(f"G{mode}: the probe tripped but the drives' latched readings could not be read")
    pose = model_tip_pose(daemon.cfg, q_c)
    _, q_end = w.hist.current()
    over = float(np.linalg.norm(model_tip_pose(daemon.cfg, q_end)[:3] - pose[:3]))
    params = {str(5061 + i): float(v) for i, v in enumerate(pose)}
    params.update({"5067": 0.0, "5068": 0.0, "5069": 0.0, "5070": 1})
    entry = {"mode": mode, "t_s": float(t_c), "q_mm": [float(v) for v in q_c], "tip_pose": pose.tolist(),
             "overtravel_mm": over, "latched": q_latch is not None,
             "q_interp_mm": None if q_i is None else [float(v) for v in q_i]}
    log = daemon.__dict__.setdefault("calib_probe_log", deque(maxlen=1000))
    log.append(entry)
    return dict(entry, contact=True, params=params, log_index=len(log) - 1)


def register(server_cls: Any) -> None:
    from . import protocol as P
    P.OPS.update(OPS)

    def _op_probe(self, conn, req) -> None:
        if not self._take_control(conn, req):
            return
        try:
            tip, feed, mode = _check(req.fields)
        except ValueError as exc:
            self._send(conn, P.error_reply(req.id, P.BAD_VALUE, str(exc)))
            return
        d = self.daemon
        self._submit_motion(conn, req, lambda: probe_move(d, tip, feed, mode),
                            lambda r: P.ok_reply(req.id, **P.plain(r)))

    server_cls._op_probe = _op_probe
